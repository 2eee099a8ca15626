"""The layer rules of docs/DESIGN.md, read from the imports of every module.

egovib_ros (what a robot installs):

    cli/                             the top: the egovib commands
    nodes/                           ROS 2 executables (the only rclpy users)
    evaluation/, gap/                metrics and diagnosis
    viz/                             figures: the matplotlib set-up, egovib model show's views
    sim/                             the simulators
    bag/                             bags <-> numpy, the core run on bags
    core/                            the algorithm: numpy, scipy, numba
    robot.py, errors.py, outputs.py  profiles, errors, output staging (used by every layer)

A module imports its own layer or the layers below, never above: the library never imports
the command line (cli/), and only nodes/ imports ROS 2. egovib_ros never imports the
repository's research package (research/egovib_research), which sits above all of it:

    commands/                        the egovib commands it adds (bench, figures, ...)
    tools/                           benchmarks, the demo, node orchestration (ROS 2 allowed)
    experiments/                     the experiments that write docs/
    altreality/                      an independent PR2-hand generator (never egovib_ros.sim)
    thirdhand/                       a third, from the effect vocabulary alone (the same)

A package's `__main__.py` is an entry point like the commands and may use cli/'s option
types.

No two modules import each other, directly, round about or inside a function
(test_no_import_cycles). egovib_ros imports inside a function only to defer a dependency on
purpose (a `deferred:` comment on the import or just above it says why), and a function
over LONG_FUNCTION lines says in its docstring why it is one ("One function: ...").

Tests mirror modules: every module has test/test_<area>_<module>.py, or a reason in
UNTESTED; every test file is named for a module, or is a whole-package test in SYSTEM_TESTS.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "egovib_ros"
RESEARCH = ROOT / "research" / "egovib_research"

# what each area may import from egovib_ros (besides itself)
BASE = {"robot", "errors", "outputs", "__init__"}
ALLOWED = {
    "core": {"robot", "errors"},
    "bag": {"core", *BASE},
    "sim": {"core", "bag", *BASE},
    "evaluation": {"core", "bag", "sim", *BASE},
    "gap": {"core", "bag", "sim", "evaluation", "viz", *BASE},  # viz: the figure set-up
    "nodes": {"core", "bag", "sim", "evaluation", "gap", *BASE},  # gap: a report's advice
    "viz": {"core", "bag", *BASE},  # the figures of `egovib model show`
    "cli": {"core", "bag", "sim", "evaluation", "gap", "nodes", "viz", *BASE},
    "robot": {"errors"},
    "errors": set(),
    "outputs": {"errors"},
    "__init__": set(),
}
# what each area of the research package may import from it (besides itself); any of
# egovib_ros but for RESEARCH_NEVER
RESEARCH_ALLOWED = {
    "altreality": set(),
    "thirdhand": set(),
    "experiments": {"altreality", "thirdhand"},
    "tools": {"experiments"},  # the demo draws the paper's figure; the bench's timing helper
    "commands": {"tools", "experiments", "altreality", "thirdhand"},
    "__init__": set(),
}
# an independent generator shares no simulator code
RESEARCH_NEVER = {"altreality": {"sim"}, "thirdhand": {"sim"}}
ROS = ("rclpy", "sensor_msgs", "std_msgs", "geometry_msgs", "diagnostic_msgs", "rosgraph_msgs")
ROS += ("builtin_interfaces", "rcl_interfaces")
ROS_AREAS = {PACKAGE: {"nodes"}, RESEARCH: {"tools"}}  # tools: the live benchmark, the demo


def area(path: Path, root: Path = PACKAGE) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return parts[0]


def imported(path: Path) -> set[str]:
    """Modules a file imports (absolute names), at any depth of the file."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            if node.module in ("egovib_ros", "egovib_research"):  # from egovib_ros import cli
                names.update(
                    f"{node.module}.{alias.name}" if alias.name != "__version__" else node.module
                    for alias in node.names
                )
    return names


def within(names: set[str], package: str) -> set[str]:
    """The areas of `package` among `names` (the package itself, its __version__, is free)."""
    return {name.split(".")[1] for name in names if name.startswith(package + ".")}


MODULES = sorted(PACKAGE.rglob("*.py"))
RESEARCH_MODULES = sorted(RESEARCH.rglob("*.py"))


def _ros(path: Path, root: Path) -> list[str]:
    if area(path, root) in ROS_AREAS[root]:
        return []
    return sorted(n for n in imported(path) if n.split(".")[0] in ROS)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_a_module_imports_only_its_layer_and_those_below(path):
    own = area(path)
    allowed = ALLOWED[own] | {own}
    if path.name == "__main__.py":
        allowed = allowed | {"cli"}
    names = imported(path)
    wrong = sorted(within(names, "egovib_ros") - allowed)
    assert not wrong, f"{own}/ may not import {wrong}"
    research = sorted(n for n in names if n.split(".")[0] == "egovib_research")
    assert not research, f"egovib_ros never imports the research package ({research})"
    assert not _ros(path, PACKAGE), f"only nodes/ imports ROS 2 ({_ros(path, PACKAGE)})"


@pytest.mark.parametrize("path", RESEARCH_MODULES, ids=lambda p: str(p.relative_to(RESEARCH)))
def test_a_research_module_imports_only_its_layer_and_those_below(path):
    own = area(path, RESEARCH)
    names = imported(path)
    wrong = sorted(within(names, "egovib_research") - RESEARCH_ALLOWED[own] - {own})
    assert not wrong, f"egovib_research/{own}/ may not import {wrong}"
    never = sorted(within(names, "egovib_ros") & RESEARCH_NEVER.get(own, set()))
    assert not never, f"egovib_research/{own}/ may not import egovib_ros {never}"
    assert not _ros(path, RESEARCH), f"only tools/ imports ROS 2 ({_ros(path, RESEARCH)})"


def module_graph(roots: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules of `roots` ({package name: its directory}) it imports, at any
    depth of the file (function-local imports too), relative imports resolved: for
    `import a.b` and `from a import b` the deepest module named (a.b if it is one, else
    the package a, whose __init__ provides b)."""
    files = {}
    for name, root in roots.items():
        for path in root.rglob("*.py"):
            parts = [name, *path.relative_to(root).with_suffix("").parts]
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path

    def deepest(name: str) -> set[str]:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return {name} if name else set()

    graph = {}
    for module, path in files.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    targets |= deepest(alias.name)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                for alias in node.names:
                    targets |= deepest(f"{base}.{alias.name}")
        graph[module] = targets - {module}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other, directly or round about (Tarjan's
    strongly connected components of more than one module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles():
    """No two modules of either package import each other, not even round about or inside
    a function (where a cycle hides until the first call)."""
    graph = module_graph({"egovib_ros": PACKAGE, "egovib_research": RESEARCH})
    assert len(graph) == len(MODULES) + len(RESEARCH_MODULES)
    assert sum(map(len, graph.values())) > 300  # the imports were read
    assert cycles(graph) == []


def test_the_cycle_finder_finds_cycles_hidden_in_functions(tmp_path):
    root = tmp_path / "pkg"
    (root / "sub").mkdir(parents=True)
    (root / "sub" / "__init__.py").write_text("")
    (root / "a.py").write_text("from pkg.sub import b\n")
    (root / "sub" / "b.py").write_text("def f():\n    from .. import c\n")
    (root / "c.py").write_text("import pkg.a\n")
    (root / "d.py").write_text("from pkg import a\n")  # imports into the cycle, not part of it
    (root / "e.py").write_text("from pkg import f\n")  # a name of pkg/__init__.py ...
    (root / "__init__.py").write_text("from pkg.e import g\nf = 1\n")  # ... which imports e
    graph = module_graph({"pkg": root})
    assert graph["pkg.sub.b"] == {"pkg.c"} and graph["pkg.a"] == {"pkg.sub.b"}
    assert graph["pkg.e"] == {"pkg"} and graph["pkg.d"] == {"pkg.a"}
    assert cycles(graph) == [["pkg", "pkg.e"], ["pkg.a", "pkg.c", "pkg.sub.b"]]


LONG_FUNCTION = 100


def _functions(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def deferred_imports_without_reason(paths) -> list[str]:
    """Function-local imports with no `deferred:` comment on their line or the two above."""
    found = []
    for path in paths:
        lines = path.read_text().splitlines()
        for function in _functions(path):
            for node in ast.walk(function):
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    near = lines[max(0, node.lineno - 3) : node.lineno]
                    if not any("# deferred:" in line for line in near):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno} {function.name}")
    return found


def long_functions_without_reason(paths) -> list[str]:
    found = []
    for path in paths:
        for function in _functions(path):
            length = function.end_lineno - function.lineno + 1
            if length > LONG_FUNCTION and "One function" not in (ast.get_docstring(function) or ""):
                found.append(f"{path.relative_to(ROOT)}:{function.lineno} {function.name}")
    return found


def test_function_local_imports_are_deferred_on_purpose_with_a_reason():
    """Inside a function only what is deferred on purpose (an optional extra, matplotlib,
    a codec, numba's compilation), each saying why: a hidden import is where cycles hide."""
    assert deferred_imports_without_reason(MODULES) == []


def test_long_functions_say_why_they_are_one():
    assert long_functions_without_reason(MODULES) == []


def test_the_structure_checks_find_what_they_look_for(tmp_path):
    module = tmp_path / "m.py"
    body = "".join(f"    x{i} = {i}\n" for i in range(LONG_FUNCTION))
    module.write_text(
        "def f():\n    import json\n\n\n"
        "def g():\n    import zlib  # deferred: a reason\n\n\n"
        f"def long():\n{body}\n\n"
        f'def said():\n    """One function: a reason."""\n{body}'
    )
    root = ROOT
    try:
        globals()["ROOT"] = tmp_path
        assert deferred_imports_without_reason([module]) == ["m.py:2 f"]
        assert long_functions_without_reason([module]) == ["m.py:9 long"]
    finally:
        globals()["ROOT"] = root


def test_the_rules_cover_every_area():
    assert {area(p) for p in MODULES} <= set(ALLOWED)
    assert {area(p, RESEARCH) for p in RESEARCH_MODULES} <= set(RESEARCH_ALLOWED)


# --------------------------------------------------------------------------
# Tests mirror modules: egovib_ros/<area>/<module>.py (and research/egovib_research/<area>/
# <module>.py) is tested in test/test_<area>_<module>.py (or test_<area>_<module>_<aspect>.py;
# the longest module name a test file starts with wins)
# --------------------------------------------------------------------------
TEST_DIR = Path(__file__).resolve().parent

#: Modules deliberately without a test file of their own, and where they are exercised.
UNTESTED = {
    "errors": "exception classes only; every bad-input test checks their messages",
    "sim/pr2": "the PR2 hand's published constants, no behaviour",
    "core/timebase": "one constant (ns per s)",
    "cli/jobs": "--jobs/--scheduler of every many-bag command (test_cli_denoise, test_cli_gap)",
    "cli/model": "`egovib model show` runs in test_viz_model_show",
    "nodes/bag_recorder": "records the replay in test_nodes_bag_player",
    "gap/chain": "the forward selection's cross-fitted chains: test_gap_diagnose, test_gap_change",
    # research/egovib_research
    "commands/bench": "`egovib bench` runs in test_tools_bench",
    "commands/demo": "starts ROS 2 nodes; parsed in test_nodes_launch, run by `make demo`",
    "commands/live_bench": "starts ROS 2 nodes; parsed in test_nodes_launch",
    "commands/real": "`egovib real convert|evaluate|gap` run in test_experiments_flight_*, "
    "_gap_flight",
    "experiments/flight/flightlog": "read by the converter in test_experiments_flight_convert",
    "experiments/flight/recording": "built from the shipped bag in test_experiments_flight_*",
    "experiments/paper_figures": "drawn by `egovib figures --quick` in test_commands_figures",
    "tools/demo": "ROS 2 processes; run by `make demo`",
    "tools/live_bench": "ROS 2 processes; run by `egovib live-bench`, figures in docs/",
    "tools/orchestration": "starts the nodes of every test_nodes_* file (conftest)",
    "tools/watcher": "the test harness's diagnostics reader (conftest)",
    "thirdhand/motion": "the third hand's trajectories, run by every test_thirdhand_hand case",
}
#: Test files not named for one module: tests of the whole package or of the repository.
SYSTEM_TESTS = {
    "test_bag_conformance": "every command on bags laid out as other writers lay them out",
    "test_bag_properties": "property-based: reading, calibrating, denoising any bag",
    "test_colcon_build": "the package as colcon builds and installs it",
    "test_core_any_robot": "the core on robots other than the PR2 (N joints, any rate)",
    "test_docs_links": "every relative link of README.md and docs/ resolves",
    "test_egovib_commands": "the egovib command set, with and without the research package",
    "test_faults": "the fault-injection table across every command",
    "test_layers": "this file: the layout",
    "test_lint": "ruff over the repository",
    "test_nodes_launch": "the launch files and the executables they name",
    "test_walkthrough": "README's walk-through, command by command",
}


def module_names() -> dict[str, Path]:
    """'area_module' -> path of every module of both packages (not __init__ / __main__)."""
    names = {}
    for root, modules in ((PACKAGE, MODULES), (RESEARCH, RESEARCH_MODULES)):
        for path in modules:
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] not in ("__init__", "__main__"):
                assert "_".join(parts) not in names, f"two modules named {'_'.join(parts)}"
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
        str(path.relative_to(PACKAGE.parent))
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
