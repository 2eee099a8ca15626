"""outputs: never destroy what a run did not create.

prepare_output refuses before any work and claims the output (a lock no other run can
take); atomic_output writes next to the target and renames into place only when
complete, marking directory outputs as ours, and removes its staging at once when the
block fails (a full disk included); stale staging directories of killed runs are
cleaned, nothing else is.
"""

import errno
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from egovib_ros.outputs import (
    MARKER,
    PARTIAL_MARKER,
    OutputError,
    atomic_output,
    claim_output,
    clean_stale_partials,
    json_holding,
    prepare_output,
    prepare_outputs_in,
    process_start_time,
    release_outputs,
    text_starting_with,
)


def write_dir_output(path, files=("metadata.yaml", "data.mcap"), kind="bag"):
    with atomic_output(path, directory=True, kind=kind) as tmp:
        tmp.mkdir()
        for name in files:
            (tmp / name).write_text(name)


def state(root):
    return sorted(
        (str(p.relative_to(root)), p.stat().st_mtime_ns, p.stat().st_size) for p in root.rglob("*")
    )


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    release_outputs()  # what the CLI does when a command ends


# --- prepare_output ------------------------------------------------------------------------


@pytest.mark.parametrize("path", [".", "..", "./", "../", "sub/..", "/"])
def test_dot_and_dotdot_refused(cwd, path):
    with pytest.raises(OutputError, match=r"^--out .*(\.|working directory)"):
        prepare_output(path, force=True, kind="bag")


def test_working_directory_and_its_parents_refused(cwd):
    for path in (cwd, cwd.parent, cwd / "a" / ".." / ".."):
        with pytest.raises(OutputError):
            prepare_output(path, force=True, kind="directory")


def test_existing_output_needs_force(cwd):
    (cwd / "out.json").write_text("{}")
    with pytest.raises(OutputError, match=r"^--json out.json: already exists \(use --force"):
        prepare_output("out.json", kind="json", option="--json")
    assert prepare_output("out.json", force=True, kind="json", option="--json").name == "out.json"


@pytest.mark.parametrize(
    "relation,path",
    [
        ("is", "outer/bag"),
        ("lies inside", "outer/bag/sub"),
        ("holds", "outer"),
        ("is", "outer/./bag/"),
    ],
)
def test_output_overlapping_an_input_refused_even_with_force(cwd, relation, path):
    (cwd / "outer" / "bag").mkdir(parents=True)
    with pytest.raises(OutputError, match=f"^--out {path}: {relation} outer/bag, an input"):
        prepare_output(path, force=True, inputs=["outer/bag"], kind="bag")


def test_input_given_through_a_symlink_or_hard_link_is_still_the_input(cwd):
    (cwd / "model.npz").write_bytes(b"x")
    os.link(cwd / "model.npz", cwd / "hard.npz")
    os.symlink(cwd / "model.npz", cwd / "soft.npz")
    for alias in ("hard.npz", "soft.npz"):
        with pytest.raises(OutputError, match="input"):
            prepare_output(alias, force=True, inputs=["model.npz"], kind="model")


def test_force_replaces_only_our_own_directories(cwd):
    write_dir_output(cwd / "ours")
    assert prepare_output("ours", force=True, kind="bag")
    (cwd / "theirs").mkdir()
    (cwd / "theirs" / "thesis.tex").write_text("years of work")
    with pytest.raises(
        OutputError, match="not an egovib output.*thesis.tex.*not replaced, even with --force"
    ):
        prepare_output("theirs", force=True, kind="bag")
    # ours, but someone added a file since: not replaced either
    (cwd / "ours" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="did not write.*notes.txt"):
        prepare_output("ours", force=True, kind="bag")


def test_a_bag_egovib_wrote_is_replaced_only_by_a_bag(cwd):
    """`egovib model show M --out SWEEP --force` deleted the calibration sweep egovib had
    written (a probe's, with the model's own bag): a report never replaces a bag, nor a bag
    a report, even with --force; a bag_recorder's bag is marked by its metadata.yaml."""
    write_dir_output(cwd / "sweep")
    write_dir_output(cwd / "recorded", kind=None)  # an older bag_recorder's marker
    write_dir_output(cwd / "figures", files=("summary.md",), kind="directory")
    for bag in ("sweep", "recorded"):
        for kind in ("directory", "report"):
            with pytest.raises(OutputError, match="is a bag egovib wrote.*even with --force"):
                prepare_output(bag, force=True, kind=kind)
        assert prepare_output(bag, force=True, kind="bag")
    with pytest.raises(OutputError, match="not a bag.*even with --force"):
        prepare_output("figures", force=True, kind="bag")
    assert prepare_output("figures", force=True, kind="report")
    # and at the end of the run, whatever its checks before
    with (
        pytest.raises(OutputError, match="is a bag egovib wrote"),
        atomic_output("sweep", directory=True, kind="report") as tmp,
    ):
        tmp.mkdir()
    assert (cwd / "sweep" / "data.mcap").read_text() == "data.mcap"


def test_directory_never_replaced_by_a_file_and_back(cwd):
    write_dir_output(cwd / "bag")
    with pytest.raises(OutputError, match="is a directory"):
        prepare_output("bag", force=True, kind="json")
    (cwd / "model.npz").write_bytes(b"x")
    with pytest.raises(OutputError, match="not a directory"):
        prepare_output("model.npz", force=True, kind="bag")


def test_force_replaces_a_model_file_only_if_it_is_a_noise_model(cwd):
    (cwd / "notes.npz").write_text("not a model")
    with pytest.raises(OutputError, match="not an egovib noise model"):
        prepare_output("notes.npz", force=True, kind="model")
    np.savez(cwd / "other.npz", schema=np.array("someone.else"))
    with pytest.raises(OutputError, match="not an egovib noise model"):
        prepare_output("other.npz", force=True, kind="model")
    np.savez(cwd / "ours.npz", schema=np.array("egovib.noise_model"), schema_version=np.array(1))
    assert prepare_output("ours.npz", force=True, kind="model")


def test_force_replaces_a_json_or_text_file_only_if_this_command_wrote_it(cwd):
    """A JSON or CSV of the user's is not replaced, even with --force; one this command
    wrote (recognised by its keys, schema or first line) is."""
    (cwd / "settings.json").write_text('{"my": "settings"}')
    (cwd / "list.json").write_text("[1, 2, 3]")
    (cwd / "report.json").write_text('{"noise_reduction_db": 20.0, "n_taps": 3, "x": 1}')
    (cwd / "events.json").write_text('{"schema": "egovib.events/1", "events": []}')
    (cwd / "notes.csv").write_text("a,b\n1,2\n")
    (cwd / "events.csv").write_text("onset_ns,peak\n1,2\n")
    (cwd / "broken.json").write_bytes(b"\xff{")
    report = json_holding(("noise_reduction_db", "n_taps"))
    events = json_holding(schema="egovib.events/1")
    for name, ours in (("settings.json", report), ("list.json", events), ("broken.json", events)):
        with pytest.raises(
            OutputError, match=f"{name}: .*not an output of this command|not a JSON"
        ):
            prepare_output(name, force=True, kind="json", ours=ours)
    assert prepare_output("report.json", force=True, kind="json", ours=report)
    assert prepare_output("events.json", force=True, kind="json", ours=events)
    csv = text_starting_with("onset_ns,peak")
    with pytest.raises(OutputError, match="notes.csv: is not an output of this command"):
        prepare_output("notes.csv", force=True, kind="file", ours=csv)
    assert prepare_output("events.csv", force=True, kind="file", ours=csv)


def test_directories_without_our_marker_are_not_ours(cwd):
    """A bag or report directory without the marker is refused even with --force, whatever
    topics or files it holds: only what egovib marked is replaced."""
    bag = cwd / "denoised"
    bag.mkdir()
    (bag / "denoised_0.mcap").write_bytes(b"mcap")
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  relative_file_paths: [denoised_0.mcap]\n"
        "  topics_with_message_count:\n  - topic_metadata: {name: /accelerometer/denoised}\n"
    )
    with pytest.raises(OutputError, match="denoised: .*not an egovib output"):
        prepare_output("denoised", force=True, kind="bag")
    report = cwd / "report"
    report.mkdir()
    (report / "report.json").write_text(json.dumps({"schema": "egovib.gap/1"}))
    with pytest.raises(OutputError, match="report: .*not an egovib output"):
        prepare_output("report", force=True, kind="report")


def test_unwritable_parent_detected_before_work(cwd):
    (cwd / "file").write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        prepare_output("file/out.json", kind="json")
    if os.geteuid() != 0:
        (cwd / "ro").mkdir()
        (cwd / "ro").chmod(0o555)
        try:
            with pytest.raises(OutputError, match="cannot write in"):
                prepare_output("ro/new/out.json", kind="json")
        finally:
            (cwd / "ro").chmod(0o755)
    assert not any(p.name.endswith(".probe") for p in cwd.rglob("*"))


def test_missing_parent_directories_are_fine(cwd):
    """They are made to hold the lock file beside the output, and go with it when the run
    ends without output."""
    assert prepare_output("a/b/c.json", kind="json")
    assert sorted(os.listdir(cwd / "a" / "b")) == [".c.json.egovib-lock"]
    release_outputs()
    assert list(cwd.iterdir()) == []


# --- one run per output --------------------------------------------------------------------

# Claims an output in another process, says so, and holds it until stdin closes.
_HOLDER = """
import sys
from egovib_ros.outputs import prepare_output
prepare_output(sys.argv[1], kind="bag")
print("claimed", flush=True)
sys.stdin.read()
"""


def test_an_output_claimed_by_another_run_is_refused_until_that_run_ends(cwd):
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, "den"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "claimed"
        for force in (False, True):
            with pytest.raises(
                OutputError, match=rf"^--out den: another egovib run \(pid {holder.pid}\)"
            ):
                prepare_output("den", force=force, kind="bag")
    finally:
        holder.communicate("", timeout=60)
    assert sorted(os.listdir(cwd)) == []  # the holder removed its lock file as it ended
    assert prepare_output("den", kind="bag")


def test_the_lock_file_of_a_killed_run_does_not_block(cwd):
    """A run killed with SIGKILL leaves its lock file, but the kernel dropped its lock."""
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, "den"], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )
    assert holder.stdout.readline().strip() == b"claimed"
    holder.kill()
    holder.communicate(timeout=60)
    assert (cwd / ".den.egovib-lock").is_file()
    assert prepare_output("den", kind="bag")
    release_outputs()
    assert sorted(os.listdir(cwd)) == []


def test_a_claim_is_kept_until_released_and_taken_once_per_process(cwd):
    prepare_output("den", kind="bag")
    claim_output("den")  # the same process again: kept, not refused
    (cwd / "den").mkdir()  # its own output appeared meanwhile: the claim still holds
    release_outputs("den")
    assert sorted(os.listdir(cwd)) == ["den"]


def test_prepare_outputs_in_adds_to_a_directory_but_replaces_files_only_with_force(cwd):
    docs = cwd / "docs"
    docs.mkdir()
    (docs / "README.md").write_text("keep")
    assert prepare_outputs_in("docs", ["eval.json", "eval.md"]) == docs.relative_to(cwd)
    (docs / "eval.json").write_text("{}")
    with pytest.raises(OutputError, match="already holds eval.json"):
        prepare_outputs_in("docs", ["eval.json", "eval.md"])
    assert prepare_outputs_in("docs", ["eval.json", "eval.md"], force=True)
    (docs / "eval.json").write_text("not json")
    with pytest.raises(OutputError, match="eval.json: is not a JSON file"):
        prepare_outputs_in("docs", ["eval.json"], force=True)


# --- atomic_output -------------------------------------------------------------------------


def test_directory_output_is_marked_and_appears_only_when_complete(cwd):
    with pytest.raises(RuntimeError), atomic_output("bag", directory=True, kind="bag") as tmp:
        tmp.mkdir()
        (tmp / "metadata.yaml").write_text("half")
        raise RuntimeError("killed")
    assert sorted(os.listdir(cwd)) == []  # no output, no staging left
    write_dir_output(cwd / "bag")
    marker = json.loads((cwd / "bag" / MARKER).read_text())
    assert marker["schema"] == "egovib.output/1" and marker["kind"] == "bag"
    assert marker["files"] == ["data.mcap", "metadata.yaml"]
    assert sorted(os.listdir(cwd)) == ["bag"]


def test_replacing_our_directory_keeps_the_old_one_until_the_new_one_is_complete(cwd):
    write_dir_output(cwd / "bag", files=("old.mcap",))
    with pytest.raises(RuntimeError), atomic_output("bag", directory=True) as tmp:
        tmp.mkdir()
        raise RuntimeError("killed")
    assert (cwd / "bag" / "old.mcap").is_file()
    write_dir_output(cwd / "bag", files=("new.mcap",))
    assert sorted(os.listdir(cwd / "bag")) == [MARKER, "new.mcap"]
    assert sorted(os.listdir(cwd)) == ["bag"]


def test_atomic_output_never_replaces_a_foreign_directory(cwd):
    """Even a caller that skipped prepare_output cannot destroy someone's directory."""
    (cwd / "stuff").mkdir()
    (cwd / "stuff" / "a.txt").write_text("precious")
    before = state(cwd)
    with pytest.raises(OutputError, match="stuff: .*not replaced"):
        write_dir_output(cwd / "stuff")
    with pytest.raises(OutputError, match="is a directory"), atomic_output(cwd / "stuff") as tmp:
        tmp.write_text("{}")
    assert state(cwd) == before


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT, errno.EFBIG])
def test_a_full_disk_is_one_line_naming_the_output_and_the_staging_goes_at_once(cwd, code):
    with (
        pytest.raises(OutputError, match=r"^bag: not written: .* in .*\(.* MB free\)$"),
        atomic_output("bag", directory=True, kind="bag") as tmp,
    ):
        tmp.mkdir()
        (tmp / "data.mcap").write_bytes(b"\0" * 4096)
        raise OSError(code, os.strerror(code))
    assert sorted(os.listdir(cwd)) == []
    with (
        pytest.raises(PermissionError),  # other OS errors are not the disk's: unchanged
        atomic_output("bag", directory=True, kind="bag") as tmp,
    ):
        raise PermissionError(errno.EACCES, "denied")
    assert sorted(os.listdir(cwd)) == []


def test_file_output_replaces_atomically(cwd):
    (cwd / "out.json").write_text("old")
    with pytest.raises(RuntimeError), atomic_output("out.json") as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert (cwd / "out.json").read_text() == "old"
    with atomic_output("out.json") as tmp:
        tmp.write_text("new")
    assert (cwd / "out.json").read_text() == "new"
    assert sorted(os.listdir(cwd)) == ["out.json"]


# --- stale staging directories ------------------------------------------------------------


def _staging(cwd, name, pid, created):
    path = cwd / f".{name}.{pid}.0badc0de.partial"
    (path / name).mkdir(parents=True)
    (path / name / "big.mcap").write_bytes(b"\0" * 4096)
    (path / PARTIAL_MARKER).write_text(json.dumps({"pid": pid, "created": created}))
    return path


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_stale_partials_of_dead_runs_are_cleaned_and_nothing_else(cwd):
    old = process_start_time() - 60
    dead = _staging(cwd, "bag", dead_pid(), old)
    alive_other_run = _staging(cwd, "bag2", os.getppid(), old)  # a run still going
    newer = _staging(cwd, "bag3", dead_pid(), time.time() + 60)  # not older than this process
    unmarked = cwd / ".model.npz.ab12cd34.partial"  # a staging-like name without our marker
    unmarked.mkdir()
    (unmarked / "model.npz").write_bytes(b"x")
    os.utime(unmarked, (old, old))
    no_marker = cwd / ".bag.12345.0badc0de.partial"  # our name, no marker
    no_marker.mkdir()
    removed = clean_stale_partials(cwd)
    assert [p.name for p in removed] == [dead.name]
    for kept in (alive_other_run, newer, unmarked, no_marker):
        assert kept.exists()


def test_the_next_run_cleans_leftovers_next_to_its_output(cwd):
    dead = _staging(cwd, "bag", dead_pid(), process_start_time() - 60)
    prepare_output("bag", kind="bag")
    assert not dead.exists()
