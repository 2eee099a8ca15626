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
live benchmark) import ROS 2. A package's `__main__.py` is an entry point like the commands
and may use cli/'s option types.

Tests mirror modules: every library module has test/test_<area>_<module>.py, or a reason in
UNTESTED; every test file is named for a module, or is a whole-package test in SYSTEM_TESTS.
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
    "nodes": {"core", "bag", "sim", "evaluation", "gap", *BASE},  # gap: a report's advice
    "viz": {"core", "bag", *BASE},  # the figures of `egovib model show`
    "experiments": {"core", "bag", "sim", "altreality", "evaluation", "gap", "tools", "viz", *BASE},
    "tools": {"core", "bag", "sim", "evaluation", "gap", "nodes", "experiments", "viz", *BASE},
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
        "viz",
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


# --------------------------------------------------------------------------
# Tests mirror modules: egovib_ros/<area>/<module>.py is tested in test/test_<area>_<module>.py
# (or test_<area>_<module>_<aspect>.py; the longest module name a test file starts with wins)
# --------------------------------------------------------------------------
TEST_DIR = Path(__file__).resolve().parent

#: Modules deliberately without a test file of their own, and where they are exercised.
UNTESTED = {
    "errors": "exception classes only; every bad-input test checks their messages",
    "sim/pr2": "the PR2 hand's published constants, no behaviour",
    "core/timebase": "one constant (ns per s)",
    "cli/bench": "`egovib bench` runs in test_tools_bench",
    "cli/demo": "starts ROS 2 nodes; parsed in test_nodes_launch, run by `make demo`",
    "cli/live_bench": "starts ROS 2 nodes; parsed in test_nodes_launch",
    "cli/jobs": "--jobs/--scheduler of every many-bag command (test_cli_denoise, test_cli_gap)",
    "cli/model": "`egovib model show` runs in test_viz_model_show",
    "cli/real": "`egovib real convert|evaluate|gap` run in test_experiments_flight_*, _gap_flight",
    "cli/simulate_robot": "`egovib simulate robot` runs in test_sim_robot",
    "experiments/flight/flightlog": "read by the converter in test_experiments_flight_convert",
    "experiments/flight/recording": "built from the shipped bag in test_experiments_flight_*",
    "experiments/paper_figures": "drawn by `egovib figures --quick` in test_cli_evaluate",
    "nodes/bag_recorder": "records the replay in test_nodes_bag_player",
    "nodes/watcher": "the test harness's diagnostics reader (conftest)",
    "tools/demo": "ROS 2 processes; run by `make demo`",
    "tools/live_bench": "ROS 2 processes; run by `egovib live-bench`, figures in docs/",
    "tools/orchestration": "starts the nodes of every test_nodes_* file (conftest)",
}
#: Test files not named for one module: tests of the whole package or of the repository.
SYSTEM_TESTS = {
    "test_bag_conformance": "every command on bags laid out as other writers lay them out",
    "test_bag_properties": "property-based: reading, calibrating, denoising any bag",
    "test_colcon_build": "the package as colcon builds and installs it",
    "test_core_any_robot": "the core on robots other than the PR2 (N joints, any rate)",
    "test_faults": "the fault-injection table across every command",
    "test_layers": "this file: the layout",
    "test_lint": "ruff over the repository",
    "test_nodes_launch": "the launch files and the executables they name",
    "test_walkthrough": "README's walk-through, command by command",
}


def module_names() -> dict[str, Path]:
    """'area_module' -> path of every library module (not __init__ / __main__)."""
    names = {}
    for path in MODULES:
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if parts[-1] not in ("__init__", "__main__"):
            names["_".join(parts)] = path
    return names


def modules_with_tests() -> dict[str, list[str]]:
    """'area_module' -> the test files named for it; '' -> test files named for none."""
    names = module_names()
    found: dict[str, list[str]] = {}
    for test in sorted(TEST_DIR.glob("test_*.py")):
        stem = test.stem.removeprefix("test_")
        matches = [name for name in names if stem == name or stem.startswith(name + "_")]
        found.setdefault(max(matches, key=len) if matches else "", []).append(test.stem)
    return found


def test_every_module_has_a_test_file_or_a_reason():
    tested = modules_with_tests()
    allowed = {name.replace("/", "_") for name in UNTESTED}
    missing = sorted(
        str(path.relative_to(PACKAGE))
        for name, path in module_names().items()
        if name not in tested and name not in allowed
    )
    assert not missing, f"modules without test/test_<area>_<module>.py: {missing}"
    stale = sorted(name for name in UNTESTED if name.replace("/", "_") in tested)
    assert not stale, f"these have a test file now: drop them from UNTESTED: {stale}"
    unknown = sorted(name for name in UNTESTED if name.replace("/", "_") not in module_names())
    assert not unknown, f"UNTESTED names modules that do not exist: {unknown}"


def test_every_test_file_is_named_for_a_module_or_is_a_system_test():
    unnamed = sorted(set(modules_with_tests().get("", [])) - set(SYSTEM_TESTS))
    assert not unnamed, (
        f"test files named for no module (rename, or list in SYSTEM_TESTS): {unnamed}"
    )
    gone = sorted(name for name in SYSTEM_TESTS if not (TEST_DIR / f"{name}.py").exists())
    assert not gone, f"SYSTEM_TESTS lists files that do not exist: {gone}"
