"""`egovib gap validate` (research/: commands/gap_validate.py): its own options under
`egovib gap`, apart from the diagnosis's. The validation itself runs in
test_experiments_gap_validation."""

from egovib_ros.cli import main


def test_validate_has_its_own_options_apart_from_the_diagnosis(capsys):
    assert main(["gap", "--help"]) == 0
    gap = capsys.readouterr().out
    assert "ACTION ...\n" in gap and "validate  " in gap
    assert "--model" in gap and "--reality" not in gap
    assert main(["gap", "validate", "--help"]) == 0
    validate = capsys.readouterr().out
    assert "--reality" in validate and "--seeds" in validate and "--model" not in validate


def test_a_cluster_address_is_refused_not_ignored(tmp_path, capsys):
    """The validation runs on local processes (--jobs): --scheduler is the diagnosis's."""
    out = tmp_path / "out"
    assert main(["gap", "validate", "--scheduler", "tcp://127.0.0.1:1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--scheduler" in err, err
    assert not out.exists()
