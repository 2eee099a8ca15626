"""`egovib figures` (research/: commands/figures.py): the paper's experiments in reduced
form, their table and every figure."""

import json

from egovib_research.commands.figures import FIGURE_OUTPUTS
from egovib_ros.cli import main


def test_figures_quick_regenerates_table_and_every_figure(tmp_path):
    out = tmp_path / "docs"
    assert main(["figures", "--out", str(out), "--quick", "--quiet"]) == 0
    assert set(FIGURE_OUTPUTS) == {p.name for p in out.iterdir()}
    for name in FIGURE_OUTPUTS:
        assert (out / name).stat().st_size > 1000, name
    assert (out / "eval_fig5_a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads((out / "eval_results.json").read_text())
    assert set(data["speeds"]) == {"0.5", "1"} and "robustness" in data and "fig4_error" in data
    table = (out / "eval_results.md").read_text()
    assert "Paper vs this replication" in table and "| b | 100% | paper (mean + std) |" in table
    # nothing half-written left behind
    assert not [p for p in out.iterdir() if p.name.endswith(".partial")]
