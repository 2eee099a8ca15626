"""The egovib command set: the robot package's commands, and those the repository's
research package adds through the entry-point group egovib.commands; where it is not
installed (a robot's `pip install .` or colcon build), each of those is one line, exit 2."""

from __future__ import annotations

import importlib.metadata

import pytest

from egovib_ros import cli
from egovib_ros.cli import COMMAND_GROUP, REPOSITORY_COMMANDS, build_parser, main

ROBOT_COMMANDS = ("simulate", "calibrate", "denoise", "model", "evaluate", "detect", "gap")


def _parser_of(parser, words: list[str]):
    for word in words:
        parser = parser.commands.choices[word]
    return parser


def test_the_research_package_adds_exactly_the_repository_commands():
    names = {e.name for e in importlib.metadata.entry_points(group=COMMAND_GROUP)}
    assert names == set(REPOSITORY_COMMANDS)
    parser = build_parser()
    top = [*ROBOT_COMMANDS, "bench", "demo", "figures", "live-bench", "real"]  # by name
    assert list(parser.commands.choices) == top
    for command in REPOSITORY_COMMANDS:
        words = command.split()
        assert _parser_of(parser, words).prog == f"egovib {command}"


@pytest.fixture
def robot_install(monkeypatch):
    """egovib as a robot installs it: no package adds commands."""
    real = importlib.metadata.entry_points

    def entry_points(**selection):
        if selection.get("group") == COMMAND_GROUP:
            return importlib.metadata.EntryPoints(())
        return real(**selection)

    monkeypatch.setattr(cli, "entry_points", entry_points)


@pytest.mark.parametrize("command", REPOSITORY_COMMANDS)
def test_without_the_research_package_its_commands_are_one_line(robot_install, command, capsys):
    assert main([*command.split(), "--help"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"egovib: error: egovib {command} is a tool of the egovib_ros repository, not of the "
        "installed package: run it in a clone's venv (make venv installs research/)"
    ]


def test_without_the_research_package_the_robot_commands_are_whole(robot_install, capsys):
    parser = build_parser()
    assert list(parser.commands.choices) == list(ROBOT_COMMANDS)
    assert _parser_of(parser, ["gap"]).commands is None  # no empty ACTION under gap
    assert main(["gap", "--help"]) == 0
    assert "ACTION ..." not in capsys.readouterr().out
    # a bag named like a repository command is still a bag
    assert main(["gap", "--model", "m.npz", "--real", "bench", "--out", "o"]) == 2
    assert "m.npz" in capsys.readouterr().err
