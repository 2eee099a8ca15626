"""Launch files and parameter files name what exists: executables, parameters, arguments.

`launch` is not on PyPI, so the launch files cannot run here (they do on a colcon
install); they are compiled and read: every Node(...) names an installed executable
and only parameters that node declares; every LaunchConfiguration has its
DeclareLaunchArgument. config/<node>.yaml sets only declared parameters.
"""

from __future__ import annotations

import ast
import importlib
import py_compile
import sys
from pathlib import Path

import pytest
import yaml

from egovib_ros.nodes import NODES

pytestmark = pytest.mark.nodes  # the node suite: `pytest -m nodes`

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
LAUNCH_FILES = sorted((REPO / "launch").glob("*.launch.py"))


def declared(executable: str) -> set[str]:
    """Names of the parameters an egovib_ros node declares."""
    return {p.name for p in importlib.import_module(f"egovib_ros.nodes.{executable}").PARAMETERS}


def keyword(call: ast.Call, name: str):
    return next((k.value for k in call.keywords if k.arg == name), None)


def calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", None)) == name
    ]


def test_both_launch_files_exist():
    assert {p.name for p in LAUNCH_FILES} == {"calibrate.launch.py", "denoise.launch.py"}


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_names_existing_executables_parameters_and_arguments(path, tmp_path):
    py_compile.compile(str(path), cfile=str(tmp_path / "compiled.pyc"), doraise=True)
    tree = ast.parse(path.read_text())
    assert any(
        isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description"
        for n in tree.body
    )
    nodes = calls(tree, "Node")
    assert nodes
    for node in nodes:
        assert ast.literal_eval(keyword(node, "package")) == "egovib_ros"
        executable = ast.literal_eval(keyword(node, "executable"))
        assert executable in NODES and (BIN / executable).is_file(), executable
        known = declared(executable)
        parameters = keyword(node, "parameters")
        keys = [
            ast.literal_eval(k)
            for d in ast.walk(parameters)
            if isinstance(d, ast.Dict)
            for k in d.keys
        ]
        assert keys and set(keys) <= known, (executable, set(keys) - known)
    arguments = {ast.literal_eval(c.args[0]) for c in calls(tree, "DeclareLaunchArgument")}
    used = {
        c.args[0].value
        for c in calls(tree, "LaunchConfiguration")
        if isinstance(c.args[0], ast.Constant)
    }
    assert used and used <= arguments, used - arguments


@pytest.mark.parametrize("executable", NODES)
def test_parameter_files_set_only_declared_parameters(executable):
    data = yaml.safe_load((REPO / "config" / f"{executable}.yaml").read_text())
    values = data[executable]["ros__parameters"]
    assert set(values) <= declared(executable), set(values) - declared(executable)


def test_demo_and_live_bench_are_egovib_subcommands(capsys):
    from egovib_ros.cli import build_parser, main

    parser = build_parser()
    for command, module in (
        ("demo", "egovib_research.tools.demo"),
        ("live-bench", "egovib_research.tools.live_bench"),
    ):
        args = parser.parse_args(
            [command] + (["--json", "x.json"] if command == "live-bench" else [])
        )
        assert args.func is importlib.import_module(module).run
    assert main(["live-bench"]) == 2  # --json is required: a one-line usage error, exit 2
    assert "--json" in capsys.readouterr().err


def test_the_node_list_names_every_module_with_a_main_and_each_is_installed():
    with_main = {
        p.stem
        for p in (REPO / "egovib_ros" / "nodes").glob("*.py")
        if any(
            isinstance(n, ast.FunctionDef) and n.name == "main"
            for n in ast.parse(p.read_text()).body
        )
    }
    assert with_main == set(NODES)
    assert all((BIN / name).is_file() for name in NODES)  # setup.py's entry points
