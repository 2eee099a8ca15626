"""Figures of the installed package (`egovib model show`), drawn on matplotlib's Agg
backend: pyplot() and save_figure(), the figure set-up the repository's experiments
(research/) share."""

from __future__ import annotations

from pathlib import Path


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only), imported when a figure is drawn."""
    # deferred: matplotlib takes about a second to import; only what draws a figure pays it
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: as above

    return plt


def save_figure(fig, path: Path, dpi: int = 110) -> Path:
    """Lay `fig` out, write it to `path` and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path
