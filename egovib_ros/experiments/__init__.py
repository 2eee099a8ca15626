"""Experiments that write docs/: the paper's tables and figures, the simulator's validation,
the gap diagnosis's blind validation, the real quadcopter flights."""

from __future__ import annotations

import math
from pathlib import Path


def fmt(value, digits: int = 1) -> str:
    """`value` with `digits` decimals; "n/a" for None and non-finite floats."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}"


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only), imported when a figure is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Lay `fig` out, write it to `path` and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path
