"""Fault injection: broken bags, models, options and outputs, as a careless
user and a broken robot produce them.

One table, one row per case. Every input is generated here, on the fly, from small
simulated bags (shared by module-scoped fixtures). Each "error" row asserts exit status
2, exactly one line on stderr naming the file or option, and that nothing that existed
before was changed and nothing was left behind. "handled" rows (bad samples the tools
treat as missing) assert exit 0, the counts printed and finite, in-range results.

Rows that need work of other helpers (bag reader, gap pipeline) are xfail(strict=True)
with the reason: they turn into failures when that work lands, and are then un-xfailed.

The commands run in-process (`egovib_ros.cli.main`, the console script's entry point)
to keep the suite fast, internal errors too (a core function patched to raise, then the
entry point); the read-only file-system rows run in a child process, and so do the cases
that need a process of their own: a full file system (a 5 MB tmpfs in a private mount
namespace), the first of two runs claiming one output (frozen while the others try),
SIGTERM, SIGKILL (and the run after it) and Ctrl-C (real signals). Warnings logged along
the way (e.g. about the model's filled cells) are not counted as error lines in those.
The last tests run the denoiser and calibrator nodes on real DDS (a stream whose rate
halves, a burst)."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import simbags

from egovib_ros import cli
from egovib_ros.bag import BagWriter, read_recording, write_recording
from egovib_ros.bag.codec import encode_imu_batch, imu_field_offset
from egovib_ros.sim import simulate_motion

BAG_READER = (
    "bag reader (helper 'bags'): MCAP records lost to corruption are skipped silently; "
    "they must be detected (e.g. against the summary's message counts)"
)
SENSOR_RANGE = 78.5  # the PR2 profile's accelerometer range (config/robots/pr2_right_hand.yaml)
FS = 3000


# --- running commands ----------------------------------------------------------------------


@pytest.fixture(autouse=True)
def state_home(tmp_path_factory, monkeypatch) -> Path:
    """Where the traceback logs of internal errors go (here and in child processes)."""
    path = tmp_path_factory.mktemp("state")
    monkeypatch.setenv("XDG_STATE_HOME", str(path))
    return path


@dataclasses.dataclass
class Result:
    code: int
    out: str
    err: str
    log: str = ""  # warnings logged in-process (the console script prints them on stderr)

    @property
    def err_lines(self) -> list[str]:
        return [line for line in self.err.splitlines() if line.strip()]


def egovib(*args) -> Result:
    """`egovib ARGS` in this process (the console script's entry point)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main([str(a) for a in args])
    return Result(code, out.getvalue(), err.getvalue())


def _child_env() -> dict:
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


def egovib_subprocess(*args, cwd: Path) -> Result:
    """The real console command, in its own process."""
    command = [sys.executable, "-m", "egovib_ros.cli", *map(str, args)]
    proc = subprocess.run(
        command, cwd=cwd, env=_child_env(), capture_output=True, text=True, timeout=300
    )
    return Result(proc.returncode, proc.stdout, proc.stderr)


# Runs each command (a JSON list of argv lists) and prints [[exit status, stderr], ...].
_DRIVER = """
import contextlib, io, json, sys
from egovib_ros import cli
results = []
for argv in json.loads(sys.argv[1]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(argv)
    results.append([code, err.getvalue()])
print(json.dumps(results))
"""


def run_on_readonly(
    commands: list[list[str]], *, cwd: Path, readonly: Path, populate: str
) -> list[Result]:
    """Run the commands with `readonly` a read-only file system, populated first by the
    shell command `populate`. As root: a read-only tmpfs in a private mount namespace
    (nothing stays mounted); otherwise the directory made read-only with chmod."""
    readonly.mkdir(parents=True, exist_ok=True)
    driver = [sys.executable, "-c", _DRIVER, json.dumps(commands)]
    run = dict(cwd=cwd, env=_child_env(), capture_output=True, text=True, timeout=600)
    if os.geteuid() == 0:
        script = (
            f"mount -t tmpfs -o size=4m tmpfs {readonly} && cd {readonly} && {populate} && "
            f'mount -o remount,ro {readonly} && cd {cwd} && exec "$@"'
        )
        proc = subprocess.run(
            ["unshare", "-m", "--propagation", "private", "sh", "-c", script, "sh", *driver], **run
        )
    else:
        subprocess.run(["sh", "-c", populate], cwd=readonly, check=True)
        readonly.chmod(0o555)
        try:
            proc = subprocess.run(driver, **run)
        finally:
            readonly.chmod(0o755)
    assert proc.returncode == 0, proc.stderr
    return [Result(code, "", err) for code, err in json.loads(proc.stdout.splitlines()[-1])]


def readonly_supported() -> bool:
    if os.geteuid() != 0:
        return True
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(
        [
            "unshare",
            "-m",
            "--propagation",
            "private",
            "sh",
            "-c",
            "mount -t tmpfs -o size=1m,ro tmpfs /mnt",
        ],
        capture_output=True,
    )
    return probe.returncode == 0


def snapshot(*roots: Path) -> dict:
    """Every path under `roots` (hidden ones too) with type, size, mtime and inode."""
    state = {}
    for root in roots:
        for dirpath, dirnames, filenames in os.walk(root):
            for name in dirnames + filenames:
                path = os.path.join(dirpath, name)
                st = os.lstat(path)
                state[path] = (st.st_mode, st.st_size, st.st_mtime_ns, st.st_ino)
    return state


def tree_digest(path: Path) -> dict:
    """Content of a small tree (for the rows that must leave a bag bit-identical)."""
    return {
        str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(path.rglob("*"))
        if p.is_file()
    }


# --- generated inputs ----------------------------------------------------------------------


def _raw_only_bag(path: Path, rec) -> None:
    """A bag with only /accelerometer/raw (no joint states)."""
    with BagWriter(path) as bag:
        bag.add_topic("/accelerometer/raw", "sensor_msgs/msg/Imu")
        bag.write_batch(
            "/accelerometer/raw",
            rec.sensor_stamps_ns,
            encode_imu_batch(rec.sensor_stamps_ns, rec.sensor),
        )


def _mcap(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def _frame_id(message: bytes) -> bytes:
    """frame_id of a CDR Imu message (after the 4-byte header and the 8-byte stamp)."""
    length = int.from_bytes(message[12:16], "little")
    return message[16 : 16 + length - 1]


def _flip_value_bytes(bag: Path, rec, first: int, count: int) -> None:
    """Flip the exponent byte of x in `count` raw messages: values of ~1e126 m/s^2."""
    mcap = _mcap(bag)
    data = bytearray(mcap.read_bytes())
    part = slice(first, first + count)
    pos = 0
    for message in encode_imu_batch(rec.sensor_stamps_ns[part], rec.sensor[part]):
        at = data.find(message, pos)
        assert at >= 0
        data[at + imu_field_offset(len(_frame_id(message))) + 7] ^= 0x65
        pos = at
    mcap.write_bytes(bytes(data))


def _drop_records(bag: Path, rec, first: int, count: int) -> None:
    """Flip the opcode of the MCAP message records of samples first .. first+count on the
    raw and ground-truth topics: a reader that skips unknown records loses them silently."""
    mcap = _mcap(bag)
    data = bytearray(mcap.read_bytes())
    part = slice(first, first + count)
    for values in (rec.sensor, rec.contact, rec.ego):
        pos = 0
        for message in encode_imu_batch(rec.sensor_stamps_ns[part], values[part]):
            at = data.find(message, pos)
            assert at >= 31 and data[at - 31] == 0x05  # opcode 0x05: a Message record
            data[at - 31] = 0xFA
            pos = at
    mcap.write_bytes(bytes(data))


def _bag_of_streams(path: Path, rec, *, shift_ns: int = 0, repeat: int = 1) -> None:
    """The recording's topics with header stamps moved `shift_ns` earlier (log times as
    recorded: a bag restamped afterwards) and each message written `repeat` times in a row
    (a recorder that wrote every message twice)."""
    from egovib_ros.bag.recording import bag_topic_names, recording_streams

    moved = _with(
        rec,
        sensor_stamps_ns=rec.sensor_stamps_ns - shift_ns,
        joint_stamps_ns=rec.joint_stamps_ns - shift_ns,
        command_stamps_ns=None,
        commands=None,
    )
    with BagWriter(path) as bag:
        for topic, msgtype, stamps, encode in recording_streams(
            moved, bag_topic_names(), "linear_acceleration"
        ):
            bag.add_topic(topic, msgtype)
            messages = [m for m in encode(0, len(stamps)) for _ in range(repeat)]
            bag.write_batch(topic, np.repeat(stamps + shift_ns, repeat), messages)


def _joint_states_bag(path: Path, rec, position, velocity, effort) -> None:
    """The recording's topics with JointStates whose arrays are `position(row)`,
    `velocity(row)`, `effort(row)` (any lengths)."""
    from egovib_ros.bag import codec
    from egovib_ros.bag.recording import bag_topic_names, recording_streams

    ts = codec.typestore()
    with BagWriter(path) as bag:
        for topic, msgtype, stamps, encode in recording_streams(
            rec, bag_topic_names(), "linear_acceleration"
        ):
            bag.add_topic(topic, msgtype)
            if msgtype != codec.JOINT_STATE_TYPE:
                bag.write_batch(topic, stamps, encode(0, len(stamps)))
                continue
            for i, stamp in enumerate(stamps.tolist()):
                msg = codec.rosbags_joint_state(stamp, rec.joint_names, position(i), velocity(i))
                msg.effort = effort(i)
                bag.write(topic, stamp, bytes(ts.serialize_cdr(msg, codec.JOINT_STATE_TYPE)))


def _cut_after_chunks(bag: Path, keep: int | None = None) -> int:
    """Cut the bag's MCAP file after its `keep`-th complete chunk and that chunk's message
    indexes (None: after the last one, before the summary): a recorder killed between two
    chunks. Returns the number of chunks left."""
    import struct

    mcap = _mcap(bag)
    data = mcap.read_bytes()
    pos, ends = 8, []
    while pos < len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == 15:  # DataEnd: the summary follows
            break
        if op == 6:  # a chunk ...
            ends.append(pos + 9 + length)
        elif op == 7 and ends:  # ... and its message indexes
            ends[-1] = pos + 9 + length
        pos += 9 + length
    keep = len(ends) if keep is None else keep
    mcap.write_bytes(data[: ends[keep - 1]])
    return keep


def _with_bad_samples(accel: np.ndarray, start: int, length: int) -> np.ndarray:
    """NaN, then +/-inf, then beyond-range values over `length` samples from `start`."""
    out = accel.copy()
    third = length // 3
    out[start : start + third] = np.nan
    out[start + third : start + 2 * third, 0] = np.inf
    out[start + third : start + 2 * third, 2] = -np.inf
    out[start + 2 * third : start + length, 1] = 1e181
    return out


def _with(rec, **changes):
    return dataclasses.replace(rec, **changes)


def _model_variant(source: Path, path: Path, *, drop: tuple[str, ...] = (), **fields) -> Path:
    """A copy of the model file with some arrays replaced or dropped."""
    with np.load(source, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files if k not in drop}
    for key, value in fields.items():
        if key == "joint_names" and "profile" in arrays:
            # the model carries its robot profile: rename the joints there too
            text = str(arrays["profile"])
            for old, new in zip(("r_wrist_roll_joint", "r_gripper_joint"), value):
                text = text.replace(old, str(new))
            arrays["profile"] = np.array(text)
            for name in arrays:  # and in the methods' maps (harmonic.joint_names, ...)
                if name != key and name.endswith(".joint_names"):
                    arrays[name] = value
        arrays[key] = value
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path


@dataclasses.dataclass
class Lab:
    root: Path
    paths: dict

    def __getitem__(self, key: str) -> Path:
        return self.paths[key]


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Lab:
    """Small simulated bags, a model calibrated from them, and broken variants of both."""
    root = tmp_path_factory.mktemp("faults")
    p = {"lab": root}

    # the sweep of test/simbags.py (no ground truth, as a real calibration bag): its model's
    # harmonic fit (~8 s) is made once a test session for every module calibrating it
    sweep = simbags.sim_sweep()
    p["sweep"] = root / "sweep"
    write_recording(p["sweep"], sweep)
    p["model"] = root / "model.npz"
    result = egovib("calibrate", p["sweep"], "--out", p["model"], "--quiet")
    assert result.code == 0, result.err

    motion, _ = simulate_motion(duration_s=3.0, max_speed=0.5, tap_rate_hz=2.0, seed=4)
    p["motion"] = root / "motion"
    # without chunk CRCs (as rosbags and many recorders write bags): the bytes flipped below
    # must reach the decoder; with CRCs the damage is refused as a whole (test_bag_mcapfile)
    write_recording(p["motion"], motion, crc=False)

    # bags broken the ways the issue found them
    p["truncated"] = root / "truncated"
    shutil.copytree(p["motion"], p["truncated"])
    data = _mcap(p["truncated"]).read_bytes()
    _mcap(p["truncated"]).write_bytes(data[: len(data) * 6 // 10])
    p["flipped_values"] = root / "flipped_values"
    shutil.copytree(p["motion"], p["flipped_values"])
    _flip_value_bytes(p["flipped_values"], motion, 4000, 60)
    p["dropped_records"] = root / "dropped_records"
    shutil.copytree(p["motion"], p["dropped_records"])
    _drop_records(p["dropped_records"], motion, 3000, 2160)  # 0.72 s, as in the issue
    p["no_contact_topic"] = root / "no_contact_topic"
    write_recording(p["no_contact_topic"], _with(motion, contact=None, ego=None))
    p["no_joint_states"] = root / "no_joint_states"
    _raw_only_bag(p["no_joint_states"], motion)
    p["stamps_zero"] = root / "stamps_zero"
    write_recording(p["stamps_zero"], _with(motion, sensor_stamps_ns=0 * motion.sensor_stamps_ns))
    p["stuck_joint_clock"] = root / "stuck_joint_clock"  # the first 10 s of the sweep
    n = 10 * FS
    m = int(np.searchsorted(sweep.joint_stamps_ns, sweep.sensor_stamps_ns[n]))
    write_recording(
        p["stuck_joint_clock"],
        _with(
            sweep,
            sensor_stamps_ns=sweep.sensor_stamps_ns[:n],
            sensor=sweep.sensor[:n],
            joint_stamps_ns=np.full(m, sweep.joint_stamps_ns[0]),
            joint_position=sweep.joint_position[:m],
            joint_velocity=sweep.joint_velocity[:m],
            commands=None,
            command_stamps_ns=None,
        ),
    )

    # the sensor rate halves in the middle: every other sample kept after 1.5 s (calibrate:
    # the first 10 s of the sweep, halved after 5 s)
    index = np.arange(len(motion.sensor_stamps_ns))
    keep = (index < 1.5 * FS) | (index % 2 == 0)
    p["rate_halves"] = root / "rate_halves"
    write_recording(
        p["rate_halves"],
        _with(
            motion,
            sensor_stamps_ns=motion.sensor_stamps_ns[keep],
            sensor=motion.sensor[keep],
            contact=motion.contact[keep],
            ego=motion.ego[keep],
        ),
    )
    keep = np.flatnonzero((np.arange(n) < 5 * FS) | (np.arange(n) % 2 == 0))
    p["sweep_rate_halves"] = root / "sweep_rate_halves"
    write_recording(
        p["sweep_rate_halves"],
        _with(
            sweep,
            sensor_stamps_ns=sweep.sensor_stamps_ns[keep],
            sensor=sweep.sensor[keep],
            joint_stamps_ns=sweep.joint_stamps_ns[:m],
            joint_position=sweep.joint_position[:m],
            joint_velocity=sweep.joint_velocity[:m],
            commands=None,
            command_stamps_ns=None,
        ),
    )

    bad12 = motion.sensor.copy()  # 12 scattered bad samples, as in the issue
    rows = np.linspace(1000, 8000, 12).astype(int)
    bad12[rows[:4], 0] = np.nan
    bad12[rows[4:8], 1] = np.inf
    bad12[rows[8:], 2] = -np.inf
    p["nan12"] = root / "nan12"
    write_recording(p["nan12"], _with(motion, sensor=bad12))
    p["nan_burst"] = root / "nan_burst"  # 0.2 s: 6.7 % of the samples
    write_recording(
        p["nan_burst"], _with(motion, sensor=_with_bad_samples(motion.sensor, 4500, 600))
    )
    p["mostly_nan"] = root / "mostly_nan"  # 1 s of 3 s: above the 10 % refused
    write_recording(
        p["mostly_nan"], _with(motion, sensor=_with_bad_samples(motion.sensor, 3000, 3000))
    )
    # a dead sensor, or a profile naming a field the messages leave at zero: refused
    p["flat"] = root / "flat"
    flat = np.broadcast_to([0.0, 0.0, 9.81], motion.sensor.shape)
    write_recording(p["flat"], _with(motion, sensor=np.array(flat)))
    # 5 % of the samples bad, scattered: the blocks around them leave nothing to measure
    scattered = motion.sensor.copy()
    scattered[np.random.default_rng(3).random(len(scattered)) < 0.05, 0] = np.nan
    p["nan_scattered"] = root / "nan_scattered"
    write_recording(p["nan_scattered"], _with(motion, sensor=scattered))
    # a driver that stamps every joint state zero
    p["joints_stamped_zero"] = root / "joints_stamped_zero"
    write_recording(
        p["joints_stamped_zero"],
        _with(motion, joint_stamps_ns=np.zeros_like(motion.joint_stamps_ns)),
    )
    p["sweep_nan"] = root / "sweep_nan"  # 1 s of bad samples in the sweep
    write_recording(
        p["sweep_nan"], _with(sweep, sensor=_with_bad_samples(sweep.sensor, 30000, 3000))
    )

    gap_rec, _ = simulate_motion(duration_s=8.0, max_speed=0.5, tap_rate_hz=0.5, seed=7)
    gap_rec = _with(gap_rec, contact=None, ego=None)
    velocity = gap_rec.joint_velocity.copy()
    velocity[3000:3500] = np.nan
    p["gap_nan_velocity"] = root / "gap_nan_velocity"
    write_recording(p["gap_nan_velocity"], _with(gap_rec, joint_velocity=velocity))
    p["gap_nan_accel"] = root / "gap_nan_accel"
    write_recording(
        p["gap_nan_accel"], _with(gap_rec, sensor=_with_bad_samples(gap_rec.sensor, 9000, 1500))
    )

    # issue 34: a bag restamped to start at -2 s (header stamps before 1970, log times as
    # recorded), every message recorded twice, JointStates with efforts only or with fewer
    # velocities than names, an MCAP file a recorder left without summary
    before_zero = int(motion.sensor_stamps_ns[0]) + 2_000_000_000
    p["negative_stamps"] = root / "negative_stamps"
    _bag_of_streams(p["negative_stamps"], motion, shift_ns=before_zero)
    p["sweep_negative_stamps"] = root / "sweep_negative_stamps"
    _bag_of_streams(
        p["sweep_negative_stamps"], sweep, shift_ns=int(sweep.sensor_stamps_ns[0]) + 2_000_000_000
    )
    p["duplicated"] = root / "duplicated"
    _bag_of_streams(p["duplicated"], motion, repeat=2)
    p["sweep_duplicated"] = root / "sweep_duplicated"
    _bag_of_streams(p["sweep_duplicated"], sweep, repeat=2)
    none = np.zeros(0)
    p["effort_only"] = root / "effort_only"
    _joint_states_bag(
        p["effort_only"], motion, lambda i: none, lambda i: none, lambda i: np.array([0.1, 0.2])
    )
    p["short_velocity"] = root / "short_velocity"
    _joint_states_bag(
        p["short_velocity"],
        motion,
        lambda i: motion.joint_position[i],
        lambda i: motion.joint_velocity[i, :1],
        lambda i: none,
    )
    p["crashed_recording"] = root / "crashed_recording"  # several chunks, the summary cut off
    write_recording(p["crashed_recording"], motion, chunk_bytes=256 << 10)
    _cut_after_chunks(p["crashed_recording"])
    p["crashed_file"] = _mcap(p["crashed_recording"])  # the same, given as its bare .mcap file
    p["crashed_at_start"] = root / "crashed_at_start"  # not one complete chunk
    shutil.copytree(p["motion"], p["crashed_at_start"])
    _mcap(p["crashed_at_start"]).write_bytes(_mcap(p["motion"]).read_bytes()[:5000])
    # the gap: 8 s of data with a pause of 90 s in the middle (a budget of 1 minute)
    paused = gap_rec.sensor_stamps_ns[0] + 4_000_000_000
    later = lambda t: np.where(t >= paused, t + 90_000_000_000, t)  # noqa: E731
    p["gap_paused"] = root / "gap_paused"
    write_recording(
        p["gap_paused"],
        _with(
            gap_rec,
            sensor_stamps_ns=later(gap_rec.sensor_stamps_ns),
            joint_stamps_ns=later(gap_rec.joint_stamps_ns),
            command_stamps_ns=None,
            commands=None,
        ),
    )

    # models broken the ways the issue found them
    model = p["model"]
    p["model_text"] = root / "model_text.npz"
    p["model_text"].write_text("this is not a noise model\n")
    p["model_empty"] = root / "model_empty.npz"
    p["model_empty"].write_bytes(b"")
    p["model_truncated"] = root / "model_truncated.npz"
    p["model_truncated"].write_bytes(model.read_bytes()[:300])
    variants = {
        "model_wrong_schema": {"schema": np.array("someone.else/1")},
        "model_schema_text": {"schema_version": np.array("one")},
        "model_schema_float": {"schema_version": np.array(1.5)},
        "model_n_joints": {"n_joints": np.array("two")},
        "model_mean_shape": {"mean": np.zeros((3, 3))},
        "model_rate_nan": {"sample_rate_hz": np.array(np.nan)},
        "model_cells_off_grid": {"cells": np.full((41, 2), 99, np.int32)},
        "model_profile_garbage": {"profile": np.array("{{{ not a robot profile")},
        "model_other_joints": {"joint_names": np.array(["l_wrist_roll_joint", "l_gripper_joint"])},
    }
    for name, fields in variants.items():
        p[name] = _model_variant(model, root / f"{name}.npz", **fields)
    p["model_missing_field"] = _model_variant(
        model, root / "model_missing_field.npz", drop=("hop",)
    )
    with np.load(model) as data:  # issue 34's models
        mean, window = data["mean"], data["window"]
    p["model_no_profile"] = _model_variant(model, root / "model_no_profile.npz", drop=("profile",))
    p["model_mean_int8"] = _model_variant(
        model, root / "model_mean_int8.npz", mean=mean.astype(np.int8)
    )
    p["model_mean_complex"] = _model_variant(
        model, root / "model_mean_complex.npz", mean=mean.astype(np.complex128)
    )
    p["model_window_nan"] = _model_variant(
        model, root / "model_window_nan.npz", window=np.full_like(window, np.nan)
    )
    p["model_object_array"] = root / "model_object_array.npz"  # a valid zip, pickled inside
    with np.load(model) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["provenance_values"] = np.array([{"who": "me"}, "x"], dtype=object)
    np.savez_compressed(p["model_object_array"], **arrays)
    return Lab(root, {k: Path(v) for k, v in p.items()})


# --- the table -----------------------------------------------------------------------------

Check = Callable[["Result", Path, Lab], None]


@dataclasses.dataclass
class Row:
    id: str
    args: tuple[str, ...]  # {name}: a path of the lab; relative: this row's directory
    names: tuple[str, ...] = ()  # what the one error line must name
    expect: str = "error"  # "error" (exit 2, one line) | "ok" (exit 0) | "either"
    setup: Callable[[Path, Lab], None] | None = None
    check: Check | None = None
    xfail: str | None = None
    unchanged: bool = True  # nothing that existed before may change (else: the lab only)


def unrelated_dir(name: str = "stuff") -> Callable[[Path, Lab], None]:
    def setup(work: Path, lab: Lab) -> None:
        (work / name).mkdir()
        (work / name / "thesis.tex").write_text("years of work\n")
        (work / name / "data.csv").write_text("1,2,3\n")

    return setup


def existing_file(name: str, text: str = "{}\n") -> Callable[[Path, Lab], None]:
    def setup(work: Path, lab: Lab) -> None:
        (work / name).parent.mkdir(parents=True, exist_ok=True)
        (work / name).write_text(text)

    return setup


def no_output(*names: str) -> Check:
    def check(result: Result, work: Path, lab: Lab) -> None:
        for name in names:
            assert not (work / name).exists(), f"{name} was written"

    return check


def counted(
    count: int | None = None, *, output: str | None = None, json_file: str | None = None
) -> Check:
    """A handled case: the bad samples counted and printed; results finite and in range."""

    def check(result: Result, work: Path, lab: Lab) -> None:
        assert "bad" in result.err, f"no count of bad samples printed: {result.err!r}"
        if count is not None:
            said = (f"{count} sensor samples", f"{count} bad samples")
            assert any(text in result.err for text in said), result.err
        if json_file:
            report = json.loads((work / json_file).read_text())
            bad = report["bad_samples"]
            assert bad["bad"] > 0 and bad["raw_nonfinite"] + bad["raw_beyond_range"] == bad["bad"]
            assert f"{bad['bad']} bad samples" in result.err, result.err
            for key in (
                "noise_mean_raw",
                "noise_mean_denoised",
                "noise_reduction_db",
                "peak_snr_raw_db",
                "peak_snr_denoised_db",
                "segsnr_contact_raw_db",
                "segsnr_contact_denoised_db",
                "f1_raw",
                "f1_denoised",
                "tap_retention",
            ):
                assert isinstance(report[key], float) and np.isfinite(report[key]), key
        if output:
            rec = read_recording(work / output)
            assert len(rec.denoised) >= 0.9 * len(rec.sensor)
            assert np.all(np.isfinite(rec.denoised))
            assert np.max(np.abs(rec.denoised)) <= SENSOR_RANGE

    return check


def f1_close_to_clean(result: Result, work: Path, lab: Lab) -> None:
    """12 bad samples of 9,000 move raw F1 by at most 0.1 (it fell from 0.95 to 0.48)."""
    counted(12, json_file="eval.json")(result, work, lab)
    bad = json.loads((work / "eval.json").read_text())
    clean = egovib(*_format(ev("motion", out="clean.json"), lab))
    assert clean.code == 0, clean.err
    clean = json.loads((work / "clean.json").read_text())
    assert abs(bad["f1_raw"] - clean["f1_raw"]) <= 0.1
    assert abs(bad["noise_reduction_db"] - clean["noise_reduction_db"]) <= 0.5


def replaced_own_output(result: Result, work: Path, lab: Lab) -> None:
    marker = json.loads((work / "den" / ".egovib-output").read_text())
    assert marker["kind"] == "bag" and "metadata.yaml" in marker["files"]
    assert len(read_recording(work / "den").denoised) == len(read_recording(lab["motion"]).sensor)
    assert not list(work.glob(".*.partial"))


def stale_partials(work: Path, lab: Lab) -> None:
    """Leftovers of killed runs: ours (marker, dead pid), and foreign hidden directories
    that only look similar (no marker)."""
    dead = work / ".den.999999999.0badc0de.partial"
    (dead / "den").mkdir(parents=True)
    (dead / "den" / "den.mcap").write_bytes(b"\0" * 1000)
    (dead / ".egovib-partial").write_text(json.dumps({"pid": 999999999, "created": 1.0}))
    unmarked = work / ".den.k2j4h5g6.partial"
    (unmarked / "den").mkdir(parents=True)
    os.utime(unmarked, (1.0, 1.0))
    foreign = work / ".notes.partial"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("not ours\n")


def partials_cleaned(result: Result, work: Path, lab: Lab) -> None:
    assert not (work / ".den.999999999.0badc0de.partial").exists()
    assert (work / ".den.k2j4h5g6.partial" / "den").is_dir()  # no marker: not ours
    assert (work / ".notes.partial" / "keep.txt").read_text() == "not ours\n"
    assert (work / "den" / "metadata.yaml").is_file()


def first_denoise(work: Path, lab: Lab) -> None:
    result = egovib(*_format(den("motion"), lab))
    assert result.code == 0, result.err


def mentions(*words: str) -> Check:
    """For "either" rows that end in exit 0: what the output (stdout or stderr) must say."""

    def check(result: Result, work: Path, lab: Lab) -> None:
        if result.code == 0:
            said = (result.out + result.err + result.log).lower()
            assert all(word.lower() in said for word in words), (words, said)

    return check


def robot_profile(name: str, **changes: str) -> Callable[[Path, Lab], None]:
    """The shipped PR2 profile written to `name` with lines changed: `key=new text` replaces
    the line starting with `key:` (indentation kept)."""

    def setup(work: Path, lab: Lab) -> None:
        from egovib_ros.robot import config_dir

        lines = (config_dir() / "robots" / "pr2_right_hand.yaml").read_text().splitlines()
        for key, text in changes.items():
            at = next(i for i, line in enumerate(lines) if line.strip().startswith(f"{key}:"))
            indent = lines[at][: len(lines[at]) - len(lines[at].lstrip())]
            lines[at] = indent + text
        (work / name).write_text("\n".join(lines) + "\n")

    return setup


def no_pickle_advice(result: Result, work: Path, lab: Lab) -> None:
    assert "pickle" not in result.err.lower(), result.err


def den(bag: str, *extra: str, out: str = "den", model: str = "model") -> tuple[str, ...]:
    return ("denoise", f"{{{bag}}}", "--model", f"{{{model}}}", "--out", out, "--quiet", *extra)


def ev(bag: str, *extra: str, out: str = "eval.json", model: str = "model") -> tuple[str, ...]:
    return (
        "evaluate",
        f"{{{bag}}}",
        "--model",
        f"{{{model}}}",
        "--json",
        out,
        "--methods",
        "paper",
        "--quiet",
        *extra,
    )


def gap(bag: str, *extra: str, out: str = "report", model: str = "model") -> tuple[str, ...]:
    return (
        "gap",
        "--model",
        f"{{{model}}}",
        "--real",
        f"{{{bag}}}",
        "--out",
        out,
        "--reference-lag",
        "0",
        *extra,
    )


def cal(bag: str, *extra: str, out: str = "m.npz") -> tuple[str, ...]:
    return ("calibrate", f"{{{bag}}}", "--out", out, "--quiet", *extra)


SIM = ("simulate", "motion", "--duration", "1", "--max-speed", "0.5", "--taps", "1", "--quiet")


def sim(*extra: str, out: str = "bag") -> tuple[str, ...]:
    return SIM + ("--out", out, *extra)


# --- checks of issue 34's rows ----------------------------------------------------------------


def killed_at_staging(work: Path, lab: Lab) -> None:
    """What SIGKILL leaves the instant a staging directory appears: its marker created but
    still empty (the pid of the dead run only in the directory's name)."""
    dead = work / ".den.999999998.0badcafe.partial"
    dead.mkdir()
    (dead / ".egovib-partial").write_text("")
    os.utime(dead, (1.0, 1.0))


def killed_run_cleaned(result: Result, work: Path, lab: Lab) -> None:
    assert not (work / ".den.999999998.0badcafe.partial").exists()
    assert (work / "den" / "metadata.yaml").is_file()


def duplicates_counted(output: str | None = None, json_file: str | None = None) -> Check:
    """Every message recorded twice: read once, said as such, never "bad"."""

    def check(result: Result, work: Path, lab: Lab) -> None:
        said = result.out + result.err + result.log
        assert "recorded twice" in said, said
        assert "are bad" not in said, said
        if output:
            out = read_recording(work / output)
            assert len(out.denoised) == len(read_recording(lab["motion"]).sensor)
        if json_file:  # evaluated on each sample once
            bad = json.loads((work / json_file).read_text())["bad_samples"]
            assert bad["samples"] == len(read_recording(lab["motion"]).sensor) and bad["bad"] == 0

    return check


def truncated_read(output: str | None = None) -> Check:
    """The MCAP cut by a crash: what is complete read, said truncated."""

    def check(result: Result, work: Path, lab: Lab) -> None:
        said = result.err + result.log
        assert "truncated" in said and "ros2 bag reindex" in said, said
        # said once (a run says each message once), whatever reads the bag again: calibrate's
        # fingerprint once named it anew by its absolute path, a second warning
        warnings = {line for line in said.splitlines() if "without summary and footer" in line}
        assert len(warnings) == 1, warnings
        if output:
            out = read_recording(work / output)
            whole = read_recording(lab["motion"])
            assert 0.5 * len(whole.sensor) < len(out.denoised) <= len(whole.sensor)

    return check


def not_thinned(result: Result, work: Path, lab: Lab) -> None:
    """8 s of data spanning 98 s of stamps: within a 1-minute budget, nothing thinned."""
    if result.code == 0:
        report = json.loads((work / "report" / "report.json").read_text())
        assert report["inputs"]["bad_input"]["kept_share"] == 1.0, report["inputs"]
        assert not any("budget" in n for n in report["inputs"]["notices"])
    else:  # too little data for a diagnosis is fine; thinned it must not be
        assert "too few" in result.err, result.err


def det(bag: str, *extra: str, out: str = "events.json", model: str = "model") -> tuple[str, ...]:
    return ("detect", f"{{{bag}}}", "--model", f"{{{model}}}", "--out", out, "--quiet", *extra)


ROWS = [
    # --- outputs: data loss (exit 0 before) ------------------------------------------------
    Row("calibrate_out_is_the_input_bag", cal("motion", out="{motion}"), ("--out", "motion")),
    Row(
        "calibrate_out_is_the_input_bag_force",
        cal("motion", "--force", out="{motion}"),
        ("--out", "input"),
    ),
    Row(
        "calibrate_out_unrelated_dir",
        cal("sweep", out="stuff"),
        ("--out stuff", "exists"),
        setup=unrelated_dir(),
    ),
    Row(
        "calibrate_out_unrelated_dir_force",
        cal("sweep", "--force", out="stuff"),
        ("--out stuff", "not replaced"),
        setup=unrelated_dir(),
    ),
    Row(
        "calibrate_out_replaces_a_bag_force",
        cal("sweep", "--force", out="{motion}"),
        ("--out", "motion"),
    ),
    Row(
        "calibrate_out_is_not_a_model_force",
        cal("sweep", "--force", out="{model_text}"),
        ("--out", "model_text.npz", "not an egovib noise model"),
    ),
    Row(
        "denoise_out_unrelated_dir_force",
        den("motion", "--force", out="stuff"),
        ("--out stuff", "not replaced"),
        setup=unrelated_dir(),
    ),
    Row(
        "denoise_out_existing_bag_no_force",
        den("motion"),
        ("--out den", "--force"),
        setup=first_denoise,
    ),
    Row(
        "denoise_out_is_the_input_force",
        den("motion", "--force", out="{motion}"),
        ("--out", "input"),
    ),
    Row(
        "denoise_out_is_the_model_force",
        den("motion", "--force", out="{model}"),
        ("--out", "model.npz"),
    ),
    Row("denoise_out_inside_the_input", den("motion", out="{motion}/den"), ("--out", "inside")),
    Row(
        "denoise_out_holds_the_input_force",
        den("motion", "--force", out="{lab}"),
        ("--out", "holds"),
    ),
    Row(
        "evaluate_json_unrelated_dir_force",
        ev("motion", "--force", out="stuff"),
        ("--json stuff", "is a directory"),
        setup=unrelated_dir(),
    ),
    Row(
        "evaluate_json_is_the_bag_force",
        ev("motion", "--force", out="{motion}"),
        ("--json", "input"),
    ),
    Row(
        "evaluate_json_exists",
        ev("motion"),
        ("--json eval.json", "exists"),
        setup=existing_file("eval.json"),
    ),
    Row(
        "evaluate_json_not_json_force",
        ev("motion", "--force"),
        ("--json eval.json", "not a JSON"),
        setup=existing_file("eval.json", "my notes\n"),
    ),
    Row(
        "gap_out_unrelated_dir_force",
        gap("motion", "--force", out="stuff"),
        ("--out stuff", "not replaced"),
        setup=unrelated_dir(),
    ),
    Row("gap_out_is_the_input_force", gap("motion", "--force", out="{motion}"), ("--out", "input")),
    Row(
        "simulate_truth_is_a_dir_force",
        sim("--truth", "stuff", "--force"),
        ("--truth stuff", "directory"),
        setup=unrelated_dir(),
        check=no_output("bag"),
    ),
    Row(
        "simulate_out_unrelated_dir_force",
        sim("--force", out="stuff"),
        ("--out stuff", "not replaced"),
        setup=unrelated_dir(),
    ),
    Row(
        "simulate_out_is_the_params_file",
        sim("--params", "sim.yaml", "--force", out="sim.yaml"),
        ("--out sim.yaml", "input"),
        setup=existing_file("sim.yaml", "sim: {}\n"),
    ),
    Row(
        "figures_out_holds_previous_results",
        ("figures", "--out", "docs", "--quick", "--quiet"),
        ("--out docs", "eval_results.json", "--force"),
        setup=existing_file("docs/eval_results.json"),
    ),
    Row(
        "bench_json_exists",
        ("bench", "--json", "bench.json", "--quick", "--quiet"),
        ("--json bench.json", "exists"),
        setup=existing_file("bench.json"),
    ),
    Row(
        "gap_validate_out_holds_previous_results",
        ("gap", "validate", "--out", "docs"),
        ("--out docs", "gap_validation.md"),
        setup=existing_file("docs/gap_validation.md"),
    ),
    # --- outputs: '.' and '..' --------------------------------------------------------------
    Row("calibrate_out_dot", cal("sweep", "--force", out="."), ("--out .",)),
    Row("denoise_out_dotdot", den("motion", "--force", out=".."), ("--out ..",)),
    Row("simulate_out_dot", sim("--force", out="."), ("--out .",)),
    Row("gap_out_dot", gap("motion", "--force", out="."), ("--out .",)),
    Row("evaluate_json_dotdot", ev("motion", "--force", out=".."), ("--json ..",)),
    Row("figures_out_dotdot", ("figures", "--out", "..", "--quick", "--force"), ("--out ..",)),
    Row("bench_json_dot", ("bench", "--json", ".", "--quick", "--force"), ("--json .",)),
    # --- outputs that work: our own output replaced with --force; stale leftovers cleaned --
    Row(
        "denoise_force_replaces_own_output",
        den("motion", "--force"),
        expect="ok",
        setup=first_denoise,
        check=replaced_own_output,
        unchanged=False,
    ),
    Row(
        "stale_partials_of_killed_runs_cleaned",
        den("motion"),
        expect="ok",
        setup=stale_partials,
        check=partials_cleaned,
        unchanged=False,
    ),
    # --- options: checked before any work ---------------------------------------------------
    Row(
        "denoise_oversubtraction_nan",
        den("motion", "--oversubtraction", "nan"),
        ("--oversubtraction", "nan"),
        check=no_output("den"),
    ),
    Row(
        "denoise_oversubtraction_negative",
        den("motion", "--oversubtraction", "-1"),
        ("--oversubtraction",),
    ),
    Row(
        "denoise_floor_inf",
        den("motion", "--floor", "inf"),
        ("--floor", "inf"),
        check=no_output("den"),
    ),
    Row(
        "simulate_duration_nan",
        SIM[:3] + ("nan",) + SIM[4:] + ("--out", "bag"),
        ("--duration", "nan"),
        check=no_output("bag"),
    ),
    Row(
        "simulate_duration_inf",
        SIM[:3] + ("inf",) + SIM[4:] + ("--out", "bag"),
        ("--duration", "inf"),
    ),
    Row("simulate_duration_zero", SIM[:3] + ("0",) + SIM[4:] + ("--out", "bag"), ("--duration",)),
    Row(
        "simulate_dwell_nan",
        ("simulate", "sweep", "--dwell", "nan", "--out", "bag"),
        ("--dwell", "nan"),
    ),
    Row("simulate_seed_negative", sim("--seed", "-1"), ("--seed", "-1")),
    Row(
        "simulate_max_speed_above_one",
        SIM[:5] + ("1.5",) + SIM[6:] + ("--out", "bag"),
        ("--max-speed", "1.5"),
    ),
    Row("simulate_taps_nan", SIM[:7] + ("nan",) + SIM[8:] + ("--out", "bag"), ("--taps", "nan")),
    Row(
        "simulate_effects_timing_minus_5", sim("--effects", "timing=-5"), ("--effects", "timing=-5")
    ),
    Row(
        "simulate_effects_timing_leading",
        sim("--effects", "timing=-0.03"),
        ("--effects", "timing=-0.03"),
    ),
    Row(
        "simulate_effects_strength_nan", sim("--effects", "position=nan"), ("--effects", "position")
    ),
    Row("simulate_effects_unknown", sim("--effects", "wobble=1"), ("--effects", "wobble")),
    Row(
        "gap_reference_lag_nan", gap("motion", "--reference-lag", "nan"), ("--reference-lag", "nan")
    ),
    Row(
        "gap_train_fraction_out_of_range",
        gap("motion", "--train-fraction", "1.5"),
        ("--train-fraction", "1.5"),
    ),
    Row(
        "gap_train_fraction_nan",
        gap("motion", "--train-fraction", "nan"),
        ("--train-fraction", "nan"),
    ),
    Row(
        "gap_validate_seeds_zero",
        ("gap", "validate", "--seeds", "0", "--out", "docs"),
        ("--seeds", "0"),
    ),
    Row(
        "evaluate_max_bad_fraction_above_one",
        ev("motion", "--max-bad-fraction", "2"),
        ("--max-bad-fraction",),
    ),
    Row("figures_seed_negative", ("figures", "--out", "docs", "--seed", "-1"), ("--seed", "-1")),
    # --- broken bags -------------------------------------------------------------------------
    # cut mid-chunk by a crash: its complete chunks read, said truncated (issue 34; was refused)
    Row(
        "denoise_truncated_bag",
        den("truncated"),
        expect="ok",
        check=truncated_read("den"),
        unchanged=False,
    ),
    Row(
        "calibrate_truncated_bag",
        cal("truncated"),
        ("truncated",),
        expect="either",  # 1.8 s of motion may hold too little to calibrate on
        check=truncated_read(),
        unchanged=False,
    ),
    Row(
        "evaluate_truncated_bag",
        ev("truncated"),
        expect="ok",
        check=truncated_read(),
        unchanged=False,
    ),
    Row(
        "evaluate_missing_ground_truth_topic",
        ev("no_contact_topic"),
        ("no_contact_topic", "/accelerometer/contact"),
    ),
    Row(
        "denoise_missing_joint_states_topic",
        den("no_joint_states"),
        ("no_joint_states", "/joint_states"),
    ),
    Row(
        "denoise_no_such_bag",
        ("denoise", "{lab}/nothing", "--model", "{model}", "--out", "den"),
        ("nothing",),
    ),
    Row(
        "evaluate_flipped_value_bytes_counted",
        ev("flipped_values"),
        expect="ok",
        check=counted(60, json_file="eval.json"),
        unchanged=False,
    ),
    Row(
        "denoise_flipped_value_bytes_counted",
        den("flipped_values"),
        expect="ok",
        check=counted(60, output="den"),
        unchanged=False,
    ),
    Row(
        "denoise_records_lost_to_flipped_bytes",
        den("dropped_records"),
        ("dropped_records",),
        expect="either",
        check=mentions("2160"),
        unchanged=False,
    ),
    Row(
        "calibrate_records_lost_to_flipped_bytes",
        cal("dropped_records"),
        ("dropped_records",),
        expect="either",
        check=mentions("2160"),
        unchanged=False,
    ),
    Row("denoise_all_accel_stamps_zero", den("stamps_zero"), ("stamps_zero", "out of order")),
    Row(
        "calibrate_stuck_joint_clock",
        cal("stuck_joint_clock"),
        ("stuck_joint_clock", "joint states"),
    ),
    Row(
        "evaluate_12_nonfinite_samples",
        ev("nan12"),
        expect="ok",
        check=f1_close_to_clean,
        unchanged=False,
    ),
    Row(
        "evaluate_nan_burst_counted",
        ev("nan_burst"),
        expect="ok",
        check=counted(600, json_file="eval.json"),
        unchanged=False,
    ),
    Row(
        "evaluate_mostly_bad_samples_refused",
        ev("mostly_nan"),
        ("mostly_nan", "bad"),
        check=no_output("eval.json"),
    ),
    Row(
        "evaluate_scattered_bad_samples_leave_nothing_to_measure",
        ev("nan_scattered"),
        ("nan_scattered", "too little left to measure"),
        check=no_output("eval.json"),
    ),
    Row(
        "evaluate_joint_states_all_stamped_zero_refused",
        ev("joints_stamped_zero"),
        ("joints_stamped_zero: /joint_states", "joint states", "unusable"),
        check=no_output("eval.json"),
    ),
    Row(
        "denoise_nan_burst_counted",
        den("nan_burst"),
        expect="ok",
        check=counted(600, output="den"),
        unchanged=False,
    ),
    Row(
        "denoise_mostly_bad_samples_refused",
        den("mostly_nan"),
        ("mostly_nan", "bad"),
        check=no_output("den"),
    ),
    *(
        Row(f"{command}_flat_sensor_refused", argv, ("flat", "never changes"), check=no_output(out))
        for command, argv, out in (
            ("calibrate", cal("flat"), "m.npz"),
            ("denoise", den("flat"), "den"),
            ("evaluate", ev("flat"), "eval.json"),
            ("gap", gap("flat"), "report"),
        )
    ),
    Row(
        "calibrate_nan_second_counted",
        cal("sweep_nan"),
        expect="ok",
        check=counted(3000),
        unchanged=False,
    ),
    Row(
        # no velocity in 500 joint states, positions there: velocity from positions
        # (profile joints.velocity: auto), diagnosed as any other bag (its figures, two thirds
        # of the run, left out: made from the diagnosis, on bad samples by gap_nan_accel_counted)
        "gap_nan_joint_velocity_from_positions",
        gap("gap_nan_velocity", "--no-figures"),
        expect="ok",
        check=mentions("verdict"),
        unchanged=False,
    ),
    Row(
        "gap_nan_accel_counted",
        gap("gap_nan_accel"),
        expect="ok",
        check=mentions("1500", "bad"),
        unchanged=False,
    ),
    # --- the sensor rate changes in the middle of a bag: refused, not bridged ----------------
    Row(
        "denoise_sensor_rate_halves_mid_bag",
        den("rate_halves"),
        ("rate_halves", "/accelerometer/raw", "rate changed", "1500 Hz"),
        check=no_output("den"),
    ),
    Row(
        "calibrate_sensor_rate_halves_mid_bag",
        cal("sweep_rate_halves"),
        ("sweep_rate_halves", "/accelerometer/raw", "rate changed", "1500 Hz"),
        check=no_output("m.npz"),
    ),
    Row(
        "evaluate_sensor_rate_halves_mid_bag",
        ev("rate_halves"),
        ("rate_halves", "rate changed"),
        check=no_output("eval.json"),
    ),
    # --- robot profiles refused when loaded --------------------------------------------------
    Row(
        "calibrate_profile_denoised_topic_is_the_sensor_topic",
        cal("sweep", "--robot", "arm.yaml"),
        ("arm.yaml", "sensor.denoised_topic", "sensor.topic"),
        setup=robot_profile("arm.yaml", denoised_topic="denoised_topic: /accelerometer/raw"),
    ),
    Row(
        "calibrate_profile_denoised_topic_is_the_joints_topic",
        cal("sweep", "--robot", "arm.yaml"),
        ("arm.yaml", "joints.topic", "sensor.denoised_topic"),
        setup=robot_profile("arm.yaml", denoised_topic="denoised_topic: joint_states"),
    ),
    Row(
        "calibrate_profile_top_level_key_misspelt",
        cal("sweep", "--robot", "arm.yaml"),
        ("arm.yaml", "procesing"),
        setup=robot_profile("arm.yaml", processing="procesing:"),
    ),
    # --- broken models -----------------------------------------------------------------------
    Row(
        "denoise_model_is_a_text_file",
        den("motion", model="model_text"),
        ("model_text.npz",),
        check=no_pickle_advice,
    ),
    Row(
        "evaluate_model_is_a_text_file",
        ev("motion", model="model_text"),
        ("model_text.npz",),
        check=no_pickle_advice,
    ),
    Row("denoise_model_empty_file", den("motion", model="model_empty"), ("model_empty.npz",)),
    Row(
        "evaluate_model_truncated", ev("motion", model="model_truncated"), ("model_truncated.npz",)
    ),
    Row(
        "denoise_model_wrong_schema",
        den("motion", model="model_wrong_schema"),
        ("model_wrong_schema.npz", "schema"),
    ),
    Row(
        "denoise_model_schema_version_text",
        den("motion", model="model_schema_text"),
        ("model_schema_text.npz", "schema"),
    ),
    Row(
        "gap_model_schema_version_text",
        gap("motion", model="model_schema_text"),
        ("model_schema_text.npz", "schema"),
    ),
    Row(
        "evaluate_model_schema_version_float",
        ev("motion", model="model_schema_float"),
        ("model_schema_float.npz", "schema"),
    ),
    Row(
        "denoise_model_n_joints_malformed",
        den("motion", model="model_n_joints"),
        ("model_n_joints.npz",),
    ),
    Row(
        "denoise_model_mean_wrong_shape",
        den("motion", model="model_mean_shape"),
        ("model_mean_shape.npz",),
    ),
    Row("denoise_model_rate_nan", den("motion", model="model_rate_nan"), ("model_rate_nan.npz",)),
    Row(
        "denoise_model_cells_off_grid",
        den("motion", model="model_cells_off_grid"),
        ("model_cells_off_grid.npz",),
    ),
    Row(
        "gap_model_profile_garbage",
        gap("motion", model="model_profile_garbage"),
        ("model_profile_garbage.npz",),
    ),
    Row(
        "evaluate_model_missing_field",
        ev("motion", model="model_missing_field"),
        ("model_missing_field.npz",),
    ),
    Row(
        "evaluate_model_keyed_on_other_joints",
        ev("motion", model="model_other_joints"),
        ("motion", "l_wrist_roll_joint"),
    ),
    Row(
        "denoise_model_keyed_on_other_joints",
        den("motion", model="model_other_joints"),
        ("motion", "l_wrist_roll_joint"),
    ),
]


# --- issue 34: bad inputs a probe of 89 found still wrong ------------------------------------

SIM_ROBOT = ("simulate", "robot", "--robot", "arm.yaml", "--duration", "1", "--quiet")
NEGATIVE = ("/accelerometer/raw", "before 1970")
ROWS += [
    # negative header stamps: refused (rclpy refuses such times too; -1 marks the core's
    # synthetic samples), naming the bag and the topic; never samples silently dropped
    Row("denoise_negative_stamps", den("negative_stamps"), ("negative_stamps", *NEGATIVE)),
    Row("calibrate_negative_stamps", cal("sweep_negative_stamps"), ("negative_stamps", *NEGATIVE)),
    Row("evaluate_negative_stamps", ev("negative_stamps"), ("negative_stamps", *NEGATIVE)),
    Row("detect_negative_stamps", det("negative_stamps"), ("negative_stamps", *NEGATIVE)),
    Row(
        "detect_raw_negative_stamps",
        det("negative_stamps", "--method", "raw"),
        ("negative_stamps", *NEGATIVE),
    ),
    Row("gap_negative_stamps", gap("negative_stamps"), ("negative_stamps", *NEGATIVE)),
    # the gap's budget is held to the seconds of data, not of stamps (the figures left out)
    Row(
        "gap_budget_over_a_pause",
        gap("gap_paused", "--budget-minutes", "1", "--no-figures"),
        ("gap_paused",),
        expect="either",
        check=not_thinned,
        unchanged=False,
    ),
    Row(
        "denoise_joint_states_effort_only",
        den("effort_only"),
        ("effort_only", "/joint_states", "r_wrist_roll_joint", "effort only"),
    ),
    Row(
        "calibrate_joint_states_effort_only",
        cal("effort_only"),
        ("effort_only", "/joint_states", "effort only"),
    ),
    Row(
        "denoise_model_without_profile_key",
        den("motion", model="model_no_profile"),
        ("model_no_profile.npz", "profile"),
    ),
    Row(
        "denoise_model_mean_int8",
        den("motion", model="model_mean_int8"),
        ("model_mean_int8.npz", "'mean'", "int8"),
    ),
    Row(
        "evaluate_model_mean_complex",
        ev("motion", model="model_mean_complex"),
        ("model_mean_complex.npz", "'mean'", "complex"),
    ),
    Row(
        "denoise_model_object_array",
        den("motion", model="model_object_array"),
        ("model_object_array.npz", "'provenance_values'", "Python objects"),
        check=no_pickle_advice,
    ),
    Row(
        "denoise_model_window_all_nan",
        den("motion", model="model_window_nan"),
        ("model_window_nan.npz", "window", "non-finite"),
    ),
    Row(
        "calibrate_profile_topic_with_a_space",
        cal("sweep", "--robot", "arm.yaml"),
        ("arm.yaml", "sensor.topic", "/arm imu/raw data", "not a valid ROS topic name"),
        setup=robot_profile("arm.yaml", topic="topic: /arm imu/raw data"),
    ),
    Row(
        "simulate_profile_topic_with_a_space",
        SIM_ROBOT + ("--out", "bag"),
        ("arm.yaml", "sensor.topic", "not a valid ROS topic name"),
        setup=robot_profile("arm.yaml", topic="topic: /arm imu/raw data"),
        check=no_output("bag"),
    ),
    Row(
        "calibrate_profile_rate_1e308",
        cal("sweep", "--robot", "arm.yaml"),
        ("arm.yaml", "sensor.rate_hz", "1e+308"),
        setup=robot_profile("arm.yaml", rate_hz="rate_hz: 1e308"),
    ),
    Row(
        "simulate_profile_rate_1e9",
        SIM_ROBOT + ("--out", "bag"),
        ("arm.yaml", "sensor.rate_hz", "1e+09"),
        setup=robot_profile("arm.yaml", rate_hz="rate_hz: 1e9"),
        check=no_output("bag"),
    ),
    Row(
        "simulate_profile_rate_1e308",
        SIM_ROBOT + ("--out", "bag"),
        ("arm.yaml", "sensor.rate_hz"),
        setup=robot_profile("arm.yaml", rate_hz="rate_hz: 1e308"),
    ),
    Row(
        "staging_left_by_sigkill_with_an_empty_marker_cleaned",
        den("motion"),
        expect="ok",
        setup=killed_at_staging,
        check=killed_run_cleaned,
        unchanged=False,
    ),
    # --- decided (README "When something is wrong"): handled, said, counted ---------------
    Row(
        "denoise_mcap_cut_by_a_crash_read_to_its_last_chunk",
        den("crashed_recording"),
        expect="ok",
        check=truncated_read("den"),
        unchanged=False,
    ),
    Row(  # a bare .mcap file cut alike: read as in its directory (was refused: no metadata)
        "denoise_bare_mcap_file_cut_by_a_crash_read_to_its_last_chunk",
        den("crashed_file"),
        expect="ok",
        check=truncated_read("den"),
        unchanged=False,
    ),
    Row(
        "evaluate_mcap_cut_by_a_crash_read_to_its_last_chunk",
        ev("crashed_recording"),
        expect="ok",
        check=truncated_read(),
        unchanged=False,
    ),
    Row(
        "denoise_mcap_cut_before_its_first_chunk",
        den("crashed_at_start"),
        ("crashed_at_start", "complete chunk"),
        check=no_output("den"),
    ),
    Row(
        "denoise_every_message_twice",
        den("duplicated"),
        expect="ok",
        check=duplicates_counted("den"),
        unchanged=False,
    ),
    Row(
        "calibrate_every_message_twice",
        cal("sweep_duplicated"),
        expect="ok",
        check=duplicates_counted(),
        unchanged=False,
    ),
    Row(
        "evaluate_every_message_twice",
        ev("duplicated"),
        expect="ok",
        check=duplicates_counted(json_file="eval.json"),
        unchanged=False,
    ),
    Row(
        "denoise_velocity_array_shorter_than_the_names",
        den("short_velocity"),
        expect="ok",
        check=mentions("fewer velocity values than joint names"),
        unchanged=False,
    ),
]


def _params(rows):
    for row in rows:
        marks = [pytest.mark.xfail(strict=True, reason=row.xfail)] if row.xfail else []
        yield pytest.param(row, id=row.id, marks=marks)


def _format(args: tuple[str, ...], lab: Lab) -> list[str]:
    names = {key: str(path) for key, path in lab.paths.items()}
    return [arg.format(**names) for arg in args]


@pytest.mark.parametrize("row", list(_params(ROWS)))
def test_fault(row: Row, lab: Lab, tmp_path: Path, monkeypatch, caplog) -> None:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    if row.setup:
        row.setup(work, lab)
    before = snapshot(lab.root, work)
    with caplog.at_level(logging.WARNING):
        result = egovib(*_format(row.args, lab))
    result.log = caplog.text
    if row.expect == "either":  # refused (as an error row) or handled (exit 0, counted)
        assert result.code in (0, 2), f"exit {result.code}: {result.err}"
    if row.expect == "error" or (row.expect == "either" and result.code == 2):
        assert result.code == 2, f"exit {result.code}: {result.err}"
        assert len(result.err_lines) == 1, f"not one line: {result.err!r}"
        line = result.err_lines[0]
        assert line.startswith("egovib") and "error:" in line, line
        for name in row.names:
            assert name in line, f"{name!r} not named in {line!r}"
    else:
        assert result.code == 0, f"exit {result.code}: {result.err}"
    if row.check:
        row.check(result, work, lab)
    after = snapshot(lab.root, work)
    leftovers = [path for path in after if path.endswith(".partial") and path not in before]
    assert not leftovers, "staging left behind"
    if not row.unchanged and result.code == 0:  # its outputs may appear; the lab never changes
        after = {k: v for k, v in after.items() if k.startswith(str(lab.root))}
        before = {k: v for k, v in before.items() if k.startswith(str(lab.root))}
    assert after == before, f"changed: {sorted(set(after.items()) ^ set(before.items()))[:5]}"


# --- a calibrate onto its own input, as a user typed it ------------------------------


def test_calibrate_motion_out_motion_leaves_the_bag_intact(lab, tmp_path, monkeypatch):
    """`egovib calibrate motion --out motion` removed the bag (exit 0); now: exit 2, bag intact
    (with --force too: row calibrate_out_is_the_input_bag_force). Relative paths, as typed."""
    shutil.copytree(lab["motion"], tmp_path / "motion")
    digest = tree_digest(tmp_path / "motion")
    monkeypatch.chdir(tmp_path)
    result = egovib("calibrate", "motion", "--out", "motion")
    assert result.code == 2, result.err
    assert result.err.strip().count("\n") == 0 and "--out motion" in result.err
    assert tree_digest(tmp_path / "motion") == digest
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion"]


# --- unwritable outputs: detected before the work starts -----------------------------------

READONLY_ROWS = [
    ("calibrate", cal("sweep", out="ro/model.npz")),
    ("calibrate_input_missing_too", ("calibrate", "{lab}/no_such_bag", "--out", "ro/model.npz")),
    ("denoise", den("motion", out="ro/new")),
    ("denoise_existing_own_output_force", den("motion", "--force", out="ro/den")),
    ("evaluate", ev("motion", out="ro/eval.json")),
    ("simulate", sim(out="ro/bag")),
    ("simulate_truth", sim("--truth", "ro/truth.json")),
    ("gap", gap("motion", out="ro/report")),
    ("bench", ("bench", "--json", "ro/bench.json", "--quick")),
    ("figures", ("figures", "--out", "ro/docs", "--quick")),
]
# ro/den: a previous output of ours, which --force could replace were the file system writable
READONLY_POPULATE = (
    'mkdir den && echo \'{"schema": "egovib.output/1", "files": []}\' > den/.egovib-output'
)


@pytest.fixture(scope="module")
def readonly_results(lab, tmp_path_factory):
    """All read-only rows in one child process (one interpreter start, one mount)."""
    work = tmp_path_factory.mktemp("readonly")
    before = snapshot(lab.root)
    results = run_on_readonly(
        [_format(args, lab) for _, args in READONLY_ROWS],
        cwd=work,
        readonly=work / "ro",
        populate=READONLY_POPULATE,
    )
    return {
        "results": dict(zip([name for name, _ in READONLY_ROWS], results)),
        "work": work,
        "lab_unchanged": snapshot(lab.root) == before,
    }


@pytest.mark.skipif(not readonly_supported(), reason="no way to make a read-only file system")
@pytest.mark.parametrize("name", [name for name, _ in READONLY_ROWS])
def test_unwritable_output_refused_before_work(name, readonly_results):
    """Read-only file system: one line naming the output, exit 2, before any input is read
    (the 'input_missing_too' row: the output is named, not the missing bag)."""
    result = readonly_results["results"][name]
    assert result.code == 2, result.err
    assert len(result.err_lines) == 1, result.err
    line = result.err_lines[0]
    assert "ro/" in line and ("read-only file system" in line or "cannot write" in line), line
    assert readonly_results["lab_unchanged"]
    assert sorted(p.name for p in readonly_results["work"].iterdir()) == ["ro"]


# --- must show: 1 s of bad samples moves nothing by more than 0.5 dB -----------------------


@pytest.fixture(scope="module")
def bad_second(tmp_path_factory):
    """A 30 s motion bag, clean and with 1 s of NaN/inf/beyond-range samples. 30 s with 3
    taps/s: the taps and the no-contact time lost with the bad second move the figures by
    sampling alone by 0.1-0.4 dB (seeds 21-26; 0.3-0.7 dB with 15-20 s)."""
    root = tmp_path_factory.mktemp("bad_second")
    rec, _ = simulate_motion(duration_s=30.0, max_speed=0.5, tap_rate_hz=3.0, seed=21)
    rec = _with(rec, ego=None)  # evaluate needs only the contact truth
    write_recording(root / "clean", rec)
    write_recording(root / "bad", _with(rec, sensor=_with_bad_samples(rec.sensor, 8 * FS, FS)))
    return root


def db(a: float, b: float) -> float:
    return abs(20 * np.log10(a / b))


def test_bad_second_metrics_within_half_db(lab, bad_second, tmp_path):
    """evaluate: every dB figure and every level within 0.5 dB of the clean bag's; counts
    printed."""
    reports = {}
    for name in ("clean", "bad"):
        result = egovib(
            "evaluate",
            bad_second / name,
            "--model",
            lab["model"],
            "--json",
            tmp_path / f"{name}.json",
            "--methods",
            "paper",
        )
        assert result.code == 0, result.err
        reports[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert "3000 bad samples" in result.err, result.err
    clean, bad = reports["clean"], reports["bad"]
    assert bad["bad_samples"]["bad"] == 3000 and bad["bad_samples"]["raw_beyond_range"] == 1000
    for key in (
        "noise_reduction_db",
        "peak_snr_raw_db",
        "peak_snr_denoised_db",
        "segsnr_contact_raw_db",
        "segsnr_contact_denoised_db",
    ):
        assert abs(bad[key] - clean[key]) <= 0.5, (key, bad[key], clean[key])
    for key in ("noise_mean_raw", "noise_mean_denoised", "tap_peak_raw", "tap_peak_denoised"):
        assert db(bad[key], clean[key]) <= 0.5, (key, bad[key], clean[key])
    assert abs(bad["f1_denoised"] - clean["f1_denoised"]) <= 0.05


def test_bad_second_model_within_half_db(lab, tmp_path):
    """calibrate on the sweep with 1 s of bad samples: every cell the clean sweep measured
    is measured, its in-band mean spectrum within 0.5 dB of the clean model's; the count
    printed. (The framing after the bad second is shifted, so a block may fall into a cell
    the clean run had none in: seen once, 1 block, at a cell transition.)"""
    from egovib_ros.core import NoiseModel

    result = egovib("calibrate", lab["sweep_nan"], "--out", tmp_path / "bad.npz", "--quiet")
    assert result.code == 0, result.err
    assert "3000 sensor samples" in result.err, result.err
    clean, bad = NoiseModel.load(lab["model"]), NoiseModel.load(tmp_path / "bad.npz")
    assert np.all(bad.counts[clean.counts > 0] > 0)
    band = (clean.freqs_hz >= clean.band_hz[0]) & (clean.freqs_hz <= clean.band_hz[1])
    measured = clean.counts > 0
    level_clean = clean.mean[measured][:, 0, band].mean(axis=1)
    level_bad = bad.mean[measured][:, 0, band].mean(axis=1)
    assert np.max(np.abs(20 * np.log10(level_bad / level_clean))) <= 0.5


def test_bad_second_denoised_within_half_db(lab, bad_second, tmp_path):
    """denoise: the output outside the bad second has the clean run's level (0.5 dB), holds
    no non-finite or beyond-range value, and the count is printed. (The clean run's output
    comes from the same core in-process: `egovib denoise` equals it, test_cli_denoise.)"""
    from egovib_ros.core import NoiseModel, denoise_batch

    result = egovib(
        "denoise", bad_second / "bad", "--model", lab["model"], "--out", tmp_path / "bad", "--quiet"
    )
    assert result.code == 0, result.err
    assert "3000 sensor samples" in result.err, result.err
    bad = read_recording(tmp_path / "bad")
    clean = read_recording(bad_second / "clean")
    stamps, values, _ = denoise_batch(
        clean.sensor_stamps_ns,
        clean.sensor,
        clean.joint_stamps_ns,
        clean.joint_velocity,
        NoiseModel.load(lab["model"]),
    )
    assert np.all(np.isfinite(bad.denoised)) and np.max(np.abs(bad.denoised)) <= SENSOR_RANGE
    assert len(bad.denoised_stamps_ns) >= 0.9 * len(stamps)
    # compared outside the bad second and a second either side of it
    around = (stamps >= clean.sensor_stamps_ns[7 * FS]) & (stamps < clean.sensor_stamps_ns[10 * FS])
    chosen = ~around & np.isin(stamps, bad.denoised_stamps_ns)
    assert np.count_nonzero(chosen) >= 0.8 * len(stamps)
    level_clean = np.sqrt(np.mean(values[chosen] ** 2))
    index = np.searchsorted(bad.denoised_stamps_ns, stamps[chosen])
    level_bad = np.sqrt(np.mean(bad.denoised[index] ** 2))
    assert db(level_bad, level_clean) <= 0.5


# --- writes that run out of space: one line, exit 2, staging removed at once ---------------

# In a private mount namespace with a 5 MB tmpfs at argv[1]: for each [free bytes, argv],
# fill the file system to leave that much (null: leave it empty), run the command, list
# what is left on the file system, empty it. Prints [[exit status, stderr, left], ...].
_FULL_DRIVER = """
import contextlib, io, json, os, shutil, sys
from egovib_ros import cli
mount = sys.argv[1]
results = []
for free, argv in json.loads(sys.argv[2]):
    if free is not None:
        fd = os.open(os.path.join(mount, "fill"), os.O_WRONLY | os.O_CREAT)
        block = bytes(4096)
        try:
            while True:
                st = os.statvfs(mount)
                if st.f_bavail * st.f_frsize <= free:
                    break
                os.write(fd, block)
        except OSError:  # full: 0 bytes free
            pass
        os.close(fd)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(argv)
    left = sorted(
        os.path.relpath(os.path.join(d, n), mount)
        for d, dirs, files in os.walk(mount) for n in dirs + files
    )
    results.append([code, err.getvalue(), left])
    for name in os.listdir(mount):
        path = os.path.join(mount, name)
        shutil.rmtree(path) if os.path.isdir(path) else os.unlink(path)
print(json.dumps(results))
"""


def _namespace_command() -> list[str] | None:
    """How to mount a small tmpfs here: a private mount namespace as root, or (unprivileged)
    in a user namespace; None if neither works."""
    if shutil.which("unshare") is None:
        return None
    candidates = [["unshare", "-m", "--propagation", "private"]] if os.geteuid() == 0 else []
    candidates.append(["unshare", "-r", "-m", "--propagation", "private"])
    for command in candidates:
        probe = subprocess.run(
            [*command, "sh", "-c", 'd=$(mktemp -d) && mount -t tmpfs -o size=1m tmpfs "$d"'],
            capture_output=True,
        )
        if probe.returncode == 0:
            return command
    return None


NAMESPACE = _namespace_command()
NO_TMPFS = "cannot mount a small tmpfs here (needs root or unprivileged user namespaces)"


def error_lines(err: str) -> list[str]:
    """stderr without warnings logged along the way (e.g. about the model's filled cells)."""
    return [line for line in err.splitlines() if line.strip() and ": WARNING: " not in line]


FULL_ROWS = [
    # (id, bytes left free (None: the 5 MB file system empty), argv; output under full/)
    ("denoise_onto_5_mb", None, den("motion", out="full/den")),
    ("denoise_nearly_full", 16 << 10, den("motion", out="full/den")),
    ("denoise_0_bytes_free", 0, den("motion", out="full/den")),
    # mid-write: the paper's table only (--methods paper: a 53 kB model, more than the 16 kB
    # left); the methods' harmonic fit would add ~8 s in a child that never reaches the cache
    ("calibrate_nearly_full", 16 << 10, cal("sweep", "--methods", "paper", out="full/model.npz")),
    ("calibrate_0_bytes_free", 0, cal("sweep", out="full/model.npz")),
    ("evaluate_0_bytes_free", 0, ev("motion", out="full/eval.json")),
]


@pytest.fixture(scope="module")
def full_results(lab, tmp_path_factory):
    """All rows in one child process, on one 5 MB tmpfs mounted at work/full."""
    work = tmp_path_factory.mktemp("full")
    (work / "full").mkdir()
    commands = [[free, _format(args, lab)] for _, free, args in FULL_ROWS]
    script = f'mount -t tmpfs -o size=5m tmpfs {work / "full"} && exec "$@"'
    proc = subprocess.run(
        [*NAMESPACE, "sh", "-c", script, "sh", sys.executable, "-c", _FULL_DRIVER]
        + [str(work / "full"), json.dumps(commands)],
        cwd=work,
        env=_child_env(),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    results = json.loads(proc.stdout.splitlines()[-1])
    return {"results": dict(zip([row[0] for row in FULL_ROWS], results)), "work": work}


@pytest.mark.skipif(NAMESPACE is None, reason=NO_TMPFS)
@pytest.mark.parametrize("row", FULL_ROWS, ids=[row[0] for row in FULL_ROWS])
def test_output_file_system_full(row, full_results):
    """A full file system: one line naming the output and 'no space', exit 2; nothing left
    on it but what filled it: the staging directory removed at once (with 0 bytes free the
    run is refused before any work; mid-write, when the write fails)."""
    name, free, args = row
    code, err, left = full_results["results"][name]
    assert code == 2, err
    lines = error_lines(err)
    assert len(lines) == 1, err
    output = args[args.index("--out") + 1] if "--out" in args else args[args.index("--json") + 1]
    assert lines[0].startswith("egovib: error:") and output in lines[0], lines[0]
    assert "no space left on device" in lines[0].lower(), lines[0]
    assert left == ([] if free is None else ["fill"]), left
    assert sorted(p.name for p in full_results["work"].iterdir()) == ["full"]


# --- real processes, real signals: two runs, SIGTERM, Ctrl-C ------------------------------

# The console script's entry, after one line on stdout that says main() is about to run.
_ENTRY = "import sys\nfrom egovib_ros.cli import main\nprint('main', flush=True)\nsys.exit(main())"


def _default_signals() -> None:
    # a test runner started in the background may ignore SIGINT; its children would too
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def start_egovib(*args, cwd: Path) -> subprocess.Popen:
    """`egovib ARGS` started in its own process; returns once main() is about to run."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _ENTRY, *map(str, args)],
        cwd=cwd,
        env=_child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_signals,
    )
    assert proc.stdout.readline().strip() == "main"
    return proc


def wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError):  # a file vanishing while looked at
            if predicate():
                return True
        time.sleep(0.002)
    return False


def _denoise_long(lab, bad_second, out: str = "den", *extra) -> list[str]:
    """A denoise that runs a few seconds: the 30 s bag."""
    return ["denoise", bad_second / "clean", "--model", lab["model"], "--out", out, "--quiet"] + [
        *extra
    ]


def test_two_runs_cannot_both_claim_one_output(lab, bad_second, tmp_path, monkeypatch):
    """The first run locks the output (flock on .den.egovib-lock) for its whole run; a second
    one is refused at once, with one line naming the output and the first run's pid, exit 2
    (with --force too): waiting would only end in 'already exists', or with --force in the
    first result silently replaced. The first run is frozen (SIGSTOP) while the others try,
    so the test does not depend on timing. The others run in this process (a run of its own,
    its own open lock file: flock keeps them apart as it keeps two processes apart)."""
    first = start_egovib(*_denoise_long(lab, bad_second), cwd=tmp_path)
    lock = tmp_path / ".den.egovib-lock"
    monkeypatch.chdir(tmp_path)
    try:
        assert wait_for(lambda: lock.read_text().strip() == str(first.pid), 60)
        first.send_signal(signal.SIGSTOP)
        second = egovib(*_denoise_long(lab, bad_second))
        forced = egovib(*_denoise_long(lab, bad_second, "den", "--force"))
    finally:
        first.send_signal(signal.SIGCONT)
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    for result in (second, forced):
        assert result.code == 2, result.err
        lines = error_lines(result.err)
        assert len(lines) == 1, result.err
        assert "--out den" in lines[0] and f"another egovib run (pid {first.pid})" in lines[0]
    assert len(read_recording(tmp_path / "den").denoised) == 30 * FS  # the first run's, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["den"]  # no lock file, no staging


def test_the_next_run_takes_the_output_once_the_first_has_ended(lab, tmp_path, monkeypatch):
    """The lock is the run's, not the output's: once the first run has ended, the output is
    free again (refused without --force because it exists, replaced with --force)."""
    monkeypatch.chdir(tmp_path)
    assert egovib(*_format(den("motion"), lab)).code == 0
    again = egovib(*_format(den("motion"), lab))
    assert again.code == 2 and "already exists" in again.err
    assert egovib(*_format(den("motion", "--force"), lab)).code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["den"]


def test_sigterm_mid_denoise_one_line_exit_143_staging_removed(lab, bad_second, tmp_path):
    """SIGTERM while the output bag is being written: one line, exit 143 (128 + 15, what a
    shell reports for a process ended by SIGTERM, so scripts see 'stopped', not 'bad input'),
    and the staging directory is gone at once, not at the next run."""
    run = start_egovib(*_denoise_long(lab, bad_second), cwd=tmp_path)

    def writing() -> bool:
        return any(mcap.stat().st_size > 0 for mcap in tmp_path.glob(".den.*.partial/den/*.mcap"))

    assert wait_for(writing, 60), run.stderr.read() if run.poll() is not None else "not yet"
    run.send_signal(signal.SIGTERM)
    _, err = run.communicate(timeout=60)
    assert run.returncode == 143, err
    assert error_lines(err) == ["egovib: terminated (SIGTERM)"], err
    assert list(tmp_path.iterdir()) == []  # no staging, no lock file, no output


@pytest.mark.parametrize("delay_s", [0.0, 0.05, 0.2, 0.5, 1.0])
def test_ctrl_c_during_start_up_one_line_exit_130(lab, bad_second, tmp_path, delay_s):
    """Ctrl-C while the command's modules load, the model loads or the bag starts: no
    KeyboardInterrupt traceback, one line, exit 130, nothing left (start-up takes ~1.5 s).
    On a fast machine the whole run can end before a late Ctrl-C (seen at 1 s): then its
    output is whole and nothing is said of an interrupt."""
    run = start_egovib(*_denoise_long(lab, bad_second), cwd=tmp_path)
    time.sleep(delay_s)
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=60)
    if run.returncode != 130 and "wrote den" in err:  # finished first
        assert "Traceback" not in err and "interrupted" not in err, err
        assert len(read_recording(tmp_path / "den").denoised) == 30 * FS
        return
    assert run.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert error_lines(err) == ["egovib: interrupted"], err
    assert list(tmp_path.iterdir()) == []


def test_sigkill_the_instant_staging_appears_then_the_next_run_cleans_it(lab, tmp_path):
    """SIGKILL as soon as the staging directory exists (its marker may still be empty, or
    missing its content): the next run writing there removes it and writes its output."""
    run = start_egovib(*_format(den("motion"), lab), cwd=tmp_path)
    try:
        assert wait_for(lambda: any(tmp_path.glob(".den.*.partial")), 60), "no staging seen"
    finally:
        run.kill()
        run.communicate(timeout=60)
    assert list(tmp_path.glob(".den.*.partial")), "the run ended before its staging was seen"
    # the next run in a process of its own: a staging is stale only if older than the run
    again = egovib_subprocess(*_format(den("motion"), lab), cwd=tmp_path)
    assert again.code == 0, again.err
    assert not list(tmp_path.glob(".*.partial")), list(tmp_path.iterdir())
    assert len(read_recording(tmp_path / "den").denoised) == len(
        read_recording(lab["motion"]).sensor
    )


def test_ctrl_c_during_a_parallel_denoise_one_line_exit_130(lab, bad_second, tmp_path):
    """Ctrl-C at the terminal (SIGINT to the whole process group: egovib, Dask's scheduler
    and its worker processes) while the workers write: one line, exit 130, no Dask
    traceback (there were 3-6, 61-101 lines); no staging left; each bag written is whole."""
    (tmp_path / "in").mkdir()
    for name in ("a", "b", "c", "d"):
        shutil.copytree(bad_second / "clean", tmp_path / "in" / name)
    run = subprocess.Popen(
        [sys.executable, "-c", _ENTRY, "denoise", "in", "--model", str(lab["model"]), "--out"]
        + ["out", "--jobs", "2", "--quiet"],
        cwd=tmp_path,
        env=_child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_signals,
        start_new_session=True,  # its own process group, as a shell job is
    )
    try:
        assert run.stdout.readline().strip() == "main"
        writing = wait_for(lambda: any((tmp_path / "out").glob(".*.partial/*/*.mcap")), 180)
        os.killpg(run.pid, signal.SIGINT)
        _, err = run.communicate(timeout=180)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
    assert writing, err
    assert run.returncode == 130, err
    assert "Traceback" not in err and error_lines(err) == ["egovib: interrupted"], err
    left = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert not [n for n in left if n.endswith(".partial")], left
    for name in left:
        assert len(read_recording(tmp_path / "out" / name).denoised) == 30 * FS


# A library that swallows the KeyboardInterrupt (C code clearing errors while modules load
# does; here a bare `except:` around the framer, hit by a real SIGINT mid-run).
_SWALLOWING = """
import os, signal, sys
from egovib_ros.core import stream
append, sent = stream._Framer.push_sensor, []
def swallowing_append(self, *args):
    if not sent:
        sent.append(True)
        try:
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(1000))  # bytecode: the handler runs here and raises
        except:  # noqa: E722
            pass
    return append(self, *args)
stream._Framer.push_sensor = swallowing_append
from egovib_ros.cli import main
sys.exit(main())
"""


@pytest.mark.parametrize("sigterm", [False, True], ids=["ctrl_c", "sigterm"])
def test_a_swallowed_interrupt_still_stops_before_the_output_is_committed(lab, tmp_path, sigterm):
    driver = _SWALLOWING.replace("SIGINT", "SIGTERM") if sigterm else _SWALLOWING
    proc = subprocess.run(
        [sys.executable, "-c", driver, *_format(den("motion"), lab)],
        cwd=tmp_path,
        env=_child_env(),
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=_default_signals,
    )
    assert proc.returncode == (143 if sigterm else 130), proc.stderr
    line = "egovib: terminated (SIGTERM)" if sigterm else "egovib: interrupted"
    assert error_lines(proc.stderr) == [line], proc.stderr
    assert list(tmp_path.iterdir()) == []


# --- an unexpected exception is a bug: one line, exit 1, traceback in a log ----------------

# A genuine internal error: a core function patched to raise in the middle of the work (after
# the output is staged), then the console entry point (cli.main, in this process: what the
# console script runs; sys.exit gives its return value as the exit status).


def _bug_in_framer(monkeypatch, only: str | None = None) -> None:
    """The denoiser's framer raises (the output bag is staged and being written by now);
    with `only`, only for the bag whose source contains it."""
    from egovib_ros.core import stream

    append = stream._Framer.push_sensor

    def failing_append(self, *args):
        if only is not None and only not in self.s.source:
            return append(self, *args)
        raise ValueError("injected failure\nwith a second line")

    monkeypatch.setattr(stream._Framer, "push_sensor", failing_append)


def _bug_in_save(monkeypatch) -> None:
    from egovib_ros.core import NoiseModel

    def failing_save(self, path):
        with open(path, "wb") as fh:
            fh.write(b"half a model")
        raise RuntimeError("injected failure")

    monkeypatch.setattr(NoiseModel, "save", failing_save)


BUG_ROWS = [
    ("denoise", _bug_in_framer, den("motion"), "motion", "ValueError: injected failure", "den"),
    # the paper's table only: the bug is in saving, after whatever calibration ran (the
    # methods' fit would add work the row does not look at)
    (
        "calibrate",
        _bug_in_save,
        cal("sweep", "--methods", "paper"),
        "sweep",
        "RuntimeError: injected failure",
        "m.npz",
    ),
]


@pytest.mark.parametrize("row", BUG_ROWS, ids=[row[0] for row in BUG_ROWS])
@pytest.mark.parametrize("log_dir", ["state", "temp"])
def test_internal_error_one_line_exit_1_traceback_logged(row, log_dir, lab, tmp_path, monkeypatch):
    """`egovib: internal error in COMMAND (INPUT): TYPE: MESSAGE; traceback written to PATH`,
    exit 1 (bad input keeps 2), the log holding the command line and the traceback, no
    output, staging or lock left. The log goes to $XDG_STATE_HOME/egovib, or to the temp
    directory when that cannot be written."""
    command, patch, args, bag, summary, output = row
    work, temp = tmp_path / "work", tmp_path / "tmp"
    work.mkdir()
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))  # as TMPDIR=temp would
    if log_dir == "temp":
        monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "a_file"))
        (tmp_path / "a_file").write_text("not a directory\n")
    monkeypatch.chdir(work)
    patch(monkeypatch)
    result = egovib(*_format(args, lab))
    assert result.code == 1, result.err
    lines = error_lines(result.err)
    assert len(lines) == 1, result.err
    match = re.fullmatch(
        rf"egovib: internal error in {command} \((.+)\): (.+); traceback written to (.+)",
        lines[0],
    )
    assert match, lines[0]
    assert match[1] == str(lab[bag]) and match[2] == summary, lines[0]
    log = Path(match[3])
    expected_dir = Path(os.environ["XDG_STATE_HOME"]) / "egovib" if log_dir == "state" else temp
    assert log.parent == expected_dir and log.is_file(), log
    text = log.read_text()
    assert f"command: egovib {command}" in text
    assert "Traceback (most recent call last)" in text and summary in text
    assert "with a second line" in text or command != "denoise"  # the whole message is kept
    assert list(work.iterdir()) == [], f"left: {list(work.iterdir())}"
    assert sorted(p.name for p in temp.iterdir()) == ([log.name] if log_dir == "temp" else [])


def test_internal_error_in_one_of_several_bags_is_still_a_bug(
    lab, tmp_path, state_home, monkeypatch
):
    """Several bags: the others complete and the summary names the failed one; a failure that
    is a bug still ends the run as an internal error (exit 1) with its traceback logged."""
    (tmp_path / "in").mkdir()
    for name in ("a", "b"):
        shutil.copytree(lab["motion"], tmp_path / "in" / name)
    _bug_in_framer(monkeypatch, only="in/a")
    monkeypatch.chdir(tmp_path)
    result = egovib("denoise", "in", "--model", lab["model"], "--out", "out", "--quiet")
    assert result.code == 1, result.err
    lines = error_lines(result.err)
    assert "FAILED in/a: ValueError: injected failure" in result.err
    assert "2 bag(s): 1 done, 1 failed" in result.err
    assert lines[-1].startswith("egovib: internal error in denoise (in): BagTaskBug: 1 of 2")
    log = Path(lines[-1].rsplit("traceback written to ", 1)[1])
    assert log.parent == state_home / "egovib" and "in/a" in log.read_text()
    assert "ValueError: injected failure" in log.read_text()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["b"]  # nothing of a


def test_bad_input_keeps_exit_2_and_writes_no_log(lab, tmp_path, state_home, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = egovib(*_format(den("crashed_at_start"), lab))
    assert result.code == 2 and "internal error" not in result.err
    assert not (state_home / "egovib").exists()


# --- live: the denoiser node refuses a stream whose rate changes ---------------------------


def _live_denoiser(nodes, ros_client, feeder, model_path):
    """The denoiser node on the PR2 profile, inputs reliable, its output collected raw by the
    test's client: (process, received messages, feeder with one joint state published,
    profile)."""
    from sensor_msgs.msg import Imu

    from egovib_research.tools.orchestration import reliable_input
    from egovib_ros.nodes.common import stream_publisher_qos
    from egovib_ros.robot import load_profile

    profile = load_profile()
    den = nodes.start(
        "denoiser",
        {
            "model": str(model_path),
            **reliable_input(profile.sensor_topic, profile.joints_topic),
        },
    )
    received = []
    ros_client.node.create_subscription(
        Imu,
        profile.node_denoised_topic,
        received.append,
        stream_publisher_qos(depth=30_000),
        raw=True,
    )
    feed = feeder(profile)
    assert feed.wait_for_subscribers("denoiser"), nodes.log(den)
    feed.publish_joint_state()
    return den, received, feed, profile


def test_live_sensor_rate_halving_is_an_error_and_publishing_stops(
    nodes, ros_client, feeder, sim_model_path
):
    """The node on real DDS, fed 1 s at 3 kHz, then 1.5 s at 1.5 kHz: /diagnostics turns
    ERROR naming the rate (it said "N missing samples bridged" each second before), output
    stops within 3 rate windows of the change, the rest is withheld, the node keeps running."""
    from conftest import reports
    from diagnostic_msgs.msg import DiagnosticStatus

    from egovib_research.tools.watcher import decode_imu_messages
    from egovib_ros.nodes.convert import diagnostic_values

    den, received, feed, profile = _live_denoiser(nodes, ros_client, feeder, sim_model_path)
    rate = profile.rate_hz
    before = feed.stamp0 + (np.arange(int(rate)) * 1e9 / rate).astype(np.int64)
    after = before[-1] + (np.arange(1, int(0.75 * rate) + 1) * 2e9 / rate).astype(np.int64)
    stamps = np.r_[before, after]
    joint_stamps = np.arange(stamps[0], stamps[-1], 1_000_000)
    velocity = np.tile([0.3 * v for v in profile.max_speed], (len(joint_stamps), 1))
    feed.publish(stamps, feed.rng.normal(0.0, 0.5, (len(stamps), 3)), joint_stamps, velocity)
    assert ros_client.spin_until(
        lambda: reports(ros_client, "denoiser", DiagnosticStatus.ERROR, "rate changed", "1500 Hz"),
        10.0,
    ), nodes.log(den)
    window = 4 * 64  # RATE_WINDOW_BLOCKS blocks of the model's 64 samples

    def withheld() -> int:  # by the latest 1 Hz report
        return int(diagnostic_values(ros_client.statuses["denoiser"])["samples_withheld"])

    assert ros_client.spin_until(lambda: withheld() >= len(after) - 3 * window, 5.0), withheld()

    def output_before_the_change() -> int:  # denoised as usual
        return int(np.count_nonzero(decode_imu_messages(received)[0] <= before[-1]))

    assert ros_client.spin_until(lambda: output_before_the_change() > 0.9 * len(before), 5.0)
    out_stamps, _, _ = decode_imu_messages(received)
    assert np.count_nonzero(out_stamps > before[-1]) <= 3 * window
    assert "rate changed" in nodes.log(den) and den.poll() is None


def test_a_ctrl_c_raised_where_it_cannot_propagate_is_recorded_not_printed():
    """Ctrl-C whose KeyboardInterrupt is raised inside a callback Python only reports as
    "Exception ignored" (the import system's module-lock weakref callback, during start-up):
    not reported (no traceback on stderr); the stop stays recorded, for the points where
    the command checks it and its exit status (130)."""
    from egovib_ros import outputs

    class RaisesOnCollect:
        def __del__(self):
            raise KeyboardInterrupt  # as the SIGINT handler does, inside a finaliser

    reported: list = []
    stopped, hook = list(cli._stopped), sys.unraisablehook
    sys.unraisablehook = lambda unraisable: reported.append(unraisable.exc_type)
    try:
        with cli._signals_raise():
            cli._request_stop(KeyboardInterrupt)
            RaisesOnCollect()  # collected at once: its exception is unraisable
            assert reported == [] and KeyboardInterrupt in cli._stopped
        RaisesOnCollect()  # outside a command: reported as ever
        assert reported == [KeyboardInterrupt]
    finally:
        sys.unraisablehook = hook
        cli._stopped[:] = stopped
        outputs.clear_stop()  # the stop recorded for commits too: not for the next tests


def test_cli_main_leaves_the_logging_of_a_process_hosting_it_alone(caplog):
    """egovib says each message once per run on its own stderr handler; a process that runs
    cli.main in-process (a notebook, a test) keeps every record its own handlers get."""
    import logging

    with contextlib.redirect_stdout(io.StringIO()):
        assert cli.main(["--version"]) == 0
    log = logging.getLogger("egovib_ros.core")
    with caplog.at_level(logging.WARNING, logger="egovib_ros.core"):
        log.warning("said twice")
        log.warning("said twice")
    assert caplog.text.count("said twice") == 2


def _publish_burst_stream(feed, profile) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1 s at the profile's rate, a burst of 0.2 s of samples stamped at 10 x the rate (a
    driver glitch), then 2 s at the rate, joint states at 1 kHz at 0.3 x top speed:
    published; returns the stamps of the three parts."""
    rate = profile.rate_hz
    before = feed.stamp0 + (np.arange(int(rate)) * 1e9 / rate).astype(np.int64)
    burst = before[-1] + (np.arange(1, int(0.2 * rate) + 1) * 1e8 / rate).astype(np.int64)
    after = burst[-1] + (np.arange(1, 2 * int(rate) + 1) * 1e9 / rate).astype(np.int64)
    stamps = np.r_[before, burst, after]
    joint_stamps = np.arange(stamps[0], stamps[-1], 1_000_000)
    velocity = np.tile([0.3 * v for v in profile.max_speed], (len(joint_stamps), 1))
    feed.publish(stamps, feed.rng.normal(0.0, 0.5, (len(stamps), 3)), joint_stamps, velocity)
    return before, burst, after


def test_live_burst_refused_then_calibration_goes_on(nodes, ros_client, feeder, tmp_path):
    """The calibrator fed 1 s at 3 kHz, a burst of 600 samples stamped at 30 kHz, then 2 s
    at 3 kHz: the burst is refused ("rate changed"), and once two rate windows fit again
    calibration goes on with what it had (`rate_recoveries` 1): blocks from after the burst
    are gathered (they were dropped for good before)."""
    from egovib_research.tools.orchestration import reliable_input
    from egovib_ros.nodes.convert import diagnostic_values
    from egovib_ros.robot import load_profile

    profile = load_profile()
    cal = nodes.start(
        "calibrator",
        {
            "output": str(tmp_path / "model.npz"),
            "grid": "free",
            **reliable_input(profile.sensor_topic, profile.joints_topic),
        },
    )
    feed = feeder(profile)
    assert feed.wait_for_subscribers("calibrator"), nodes.log(cal)
    feed.publish_joint_state()
    before, _, _ = _publish_burst_stream(feed, profile)

    def values() -> dict:
        status = ros_client.statuses.get("calibrator")
        return diagnostic_values(status) if status is not None else {}

    assert ros_client.spin_until(lambda: int(values().get("rate_recoveries", 0)) == 1, 20.0), (
        values(),
        nodes.log(cal),
    )
    assert "rate changed" in nodes.log(cal) and "calibration goes on" in nodes.log(cal)
    # the 1 s before the burst gives at most len(before) / hop blocks; most of the 2 s after it
    blocks_before = len(before) / profile.hop
    assert ros_client.spin_until(lambda: int(values()["blocks"]) > 2 * blocks_before, 20.0), (
        values(),
        nodes.log(cal),
    )
    # what the refusal held back: at least the two windows that proved the rate back
    window = 4 * profile.block_length  # RATE_WINDOW_BLOCKS blocks
    assert int(values()["samples_withheld"]) >= 2 * window and cal.poll() is None


def test_live_burst_at_ten_times_the_rate_refused_then_denoising_resumes(
    nodes, ros_client, feeder, sim_model_path
):
    """1 s at 3 kHz, a burst of 600 samples stamped at 30 kHz (a driver glitch), then 2 s at
    3 kHz:
    /diagnostics turns ERROR naming the rate and nothing is published while it lasts (as
    before); once two rate windows fit the model again the denoiser starts afresh, the
    stream after the burst is denoised (it stayed withheld for good before) and
    `rate_recoveries` counts it."""
    from conftest import reports
    from diagnostic_msgs.msg import DiagnosticStatus

    from egovib_research.tools.watcher import decode_imu_messages
    from egovib_ros.nodes.convert import diagnostic_values

    den, received, feed, profile = _live_denoiser(nodes, ros_client, feeder, sim_model_path)
    before, burst, after = _publish_burst_stream(feed, profile)
    assert "rate changed" in nodes.log(den) or ros_client.spin_until(
        lambda: "rate changed" in nodes.log(den), 10.0
    ), nodes.log(den)

    def recovered() -> bool:
        status = ros_client.statuses.get("denoiser")
        return status is not None and int(diagnostic_values(status)["rate_recoveries"]) == 1

    assert ros_client.spin_until(recovered, 15.0), nodes.log(den)
    assert "denoising restarted" in nodes.log(den), nodes.log(den)

    def output_after_the_burst() -> int:
        return int(np.count_nonzero(decode_imu_messages(received)[0] > burst[-1]))

    # all of the 2 s after the burst but the first rate windows (withheld while measured)
    assert ros_client.spin_until(lambda: output_after_the_burst() > 0.75 * len(after), 15.0), (
        output_after_the_burst(),
        nodes.log(den),
    )
    assert ros_client.spin_until(
        lambda: (
            reports(ros_client, "denoiser", DiagnosticStatus.OK)
            or reports(ros_client, "denoiser", DiagnosticStatus.WARN)
        ),
        10.0,
    ), diagnostic_values(ros_client.statuses["denoiser"])
    out_stamps, _, _ = decode_imu_messages(received)
    window = 4 * 64  # RATE_WINDOW_BLOCKS blocks of the model's 64 samples
    assert np.count_nonzero((out_stamps > before[-1]) & (out_stamps <= burst[-1])) <= 3 * window
    assert den.poll() is None
