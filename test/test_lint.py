"""The package, the research package, tests and launch files are ruff-clean (ruff.toml:
100 columns, import order)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def ruff() -> list[str]:
    # installed by requirements-dev.txt (make test); `python -m ruff` finds the venv's copy
    return [sys.executable, "-m", "ruff"]


def test_ruff_check_is_clean():
    result = subprocess.run(
        ruff() + ["check", "egovib_ros", "research", "test", "launch", "setup.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_format_is_applied():
    result = subprocess.run(
        ruff() + ["format", "--check", "egovib_ros", "research", "test", "launch", "setup.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr
