"""The layer rules of docs/DESIGN.md, read from the imports of every module.

    cli/, tools/, experiments/       the top: commands, demo/benchmarks, the docs' experiments
    nodes/                           ROS 2 executables (the only rclpy users)
    evaluation/, gap/                metrics and diagnosis
    sim/, altreality/                the generators
    bag/                             bags <-> numpy, the core run on bags
    core/                            the algorithm: numpy, scipy, numba
    robot.py, errors.py, outputs.py  profiles, errors, output staging (used by every layer)

A module imports its own layer or the layers below, never above: the library never imports
the command line (cli/), the tools or the experiments, and only nodes/ and tools/ (the
live benchmark) import ROS 2. A
package's `__main__.py` is an entry point like the commands and may use cli/'s option types.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "egovib_ros"

# what each area may import from egovib_ros (besides itself)
BASE = {"robot", "errors", "outputs", "__init__"}
ALLOWED = {
    "core": {"robot", "errors"},
    "bag": {"core", *BASE},
    "sim": {"core", "bag", *BASE},
    "altreality": {"core", "bag", *BASE},  # never sim/: an independent generator
    "evaluation": {"core", "bag", "sim", *BASE},
    "gap": {"core", "bag", "sim", "evaluation", *BASE},
    "nodes": {"core", "bag", "sim", "evaluation", *BASE},
    "experiments": {"core", "bag", "sim", "altreality", "evaluation", "gap", "tools", *BASE},
    "tools": {"core", "bag", "sim", "evaluation", "gap", "nodes", "experiments", *BASE},
    "cli": {
        "core",
        "bag",
        "sim",
        "altreality",
        "evaluation",
        "gap",
        "nodes",
        "tools",
        "experiments",
        *BASE,
    },  # fmt: skip
    "robot": {"errors"},
    "errors": set(),
    "outputs": {"errors"},
    "__init__": set(),
}
ROS = ("rclpy", "sensor_msgs", "std_msgs", "geometry_msgs", "diagnostic_msgs", "rosgraph_msgs")
ROS += ("builtin_interfaces", "rcl_interfaces")


def area(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return parts[0]


def imported(path: Path) -> set[str]:
    """Modules a file imports (absolute names), at any depth of the file."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            if node.module == "egovib_ros":  # from egovib_ros import cli, sim, __version__
                names.update(
                    f"egovib_ros.{alias.name}" if alias.name != "__version__" else "egovib_ros"
                    for alias in node.names
                )
    return names


MODULES = sorted(PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_a_module_imports_only_its_layer_and_those_below(path):
    own = area(path)
    allowed = ALLOWED[own] | {own}
    if path.name == "__main__.py":
        allowed = allowed | {"cli"}
    wrong = sorted(
        name
        for name in imported(path)
        if name.startswith("egovib_ros.") and name.split(".")[1] not in allowed
    )
    assert not wrong, f"{own}/ may not import {wrong}"
    if own not in ("nodes", "tools"):  # tools: the live benchmark reads DDS itself
        ros = sorted(n for n in imported(path) if n.split(".")[0] in ROS)
        assert not ros, f"only nodes/ and tools/ import ROS 2 ({ros})"


def test_the_rules_cover_every_area():
    assert {area(p) for p in MODULES} <= set(ALLOWED)
