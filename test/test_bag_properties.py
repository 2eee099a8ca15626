"""Property-based tests (hypothesis) of reading streams from bags of any shape.

Drawn at random: the sensor rate (50 Hz to 10 kHz), the length (so any number of samples
in the last block), stamp jitter, the joint-state rate, gaps in the sensor stream, and the
file: writer (rosbags, the mcap library, the project's), order (time, topic by topic,
reversed, windows), storage, chunk size and compression, log times (the stamps, receive
times, another clock). Properties:

- `egovib denoise` (denoise_bag) writes one message per valid raw sample, equal to
  `denoise_batch` on the bag's own arrays;
- `egovib calibrate` (calibrate_bag) and `denoise_bag` give the same result for every file
  layout of the same messages.

The default profile ("ci", deterministic) keeps the run short; `HYPOTHESIS_PROFILE=long`
draws 300 examples (see conftest.py and README's test section).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import bagcorpus
import numpy as np
import robots
from bagcorpus import Layout
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from egovib_ros.bag import read_recording, write_recording
from egovib_ros.bag.calibrate import calibrate_bag
from egovib_ros.bag.denoise import denoise_bag
from egovib_ros.core import calibrate_arrays, denoise_batch

RATES = (50.0, 120.0, 250.0, 1000.0, 2000.0, 3000.0, 8000.0, 10_000.0)


@st.composite
def layouts(draw) -> Layout:
    writer = draw(st.sampled_from(["rosbags", "mcap", "project"]))
    storage = "sqlite3" if writer == "rosbags" and draw(st.booleans()) else "mcap"
    compression = (
        ""
        if storage == "sqlite3"
        else draw(st.sampled_from(["", "zstd", "lz4"] if writer == "mcap" else ["", "zstd"]))
    )
    return Layout(
        "drawn",
        writer=writer,
        storage=storage,
        compression=compression,
        order=draw(st.sampled_from(["time", "topic", "rtopic", "windows"])),
        chunk_bytes=draw(st.sampled_from([4096, 65536, 1 << 20])),
        log=draw(st.sampled_from(["stamp", "latency", "offset"])),
    )


@dataclasses.dataclass(frozen=True)
class Stream:
    """What is drawn of a recording (small, so a failing example prints readably)."""

    rate_hz: float
    n_joints: int
    n_samples: int  # any number of samples in the last block
    seed: int
    jitter: float
    joint_rate_ratio: float
    gaps: tuple[tuple[int, int], ...]  # (start, length) of sensor samples left out

    def profile(self):
        return dataclasses.replace(
            robots.profile(self.n_joints, rate_hz=self.rate_hz), name="drawn"
        )

    def recording(self, p, *, seconds: float | None = None, seed: int | None = None):
        n = self.n_samples if seconds is None else int(seconds * self.rate_hz)
        arrays = robots.recording(
            p,
            n / self.rate_hz,
            seed=self.seed if seed is None else seed,
            jitter=self.jitter,
            joint_rate_hz=min(self.rate_hz, 1000.0) * self.joint_rate_ratio,
        )
        if seconds is None:  # gaps: short ones are bridged, long ones restart the filter
            keep = np.ones(len(arrays["t_acc"]), bool)
            for start, length in self.gaps:
                keep[start : start + length] = False
            keep[:8] = True
            for key in ("t_acc", "accel", "contact"):
                arrays[key] = arrays[key][keep]
        return robots.as_recording(p, arrays)


@st.composite
def streams(draw) -> Stream:
    n = draw(st.integers(3 * 64, 2400))
    return Stream(
        rate_hz=draw(st.sampled_from(RATES)),
        n_joints=draw(st.integers(1, 3)),
        n_samples=n,
        seed=draw(st.integers(0, 2**16)),
        jitter=draw(st.floats(0.0, 0.3)),
        joint_rate_ratio=draw(st.sampled_from([0.25, 0.5, 1.0])),
        gaps=tuple(
            (draw(st.integers(0, n - 1)), draw(st.integers(1, 40)))
            for _ in range(draw(st.integers(0, 3)))
        ),
    )


def _model(stream: Stream, p):
    """A free-motion model of the drawn robot, from a longer recording of its own."""
    rec = stream.recording(p, seconds=max(20.0, 4000 / stream.rate_hz), seed=stream.seed + 1)
    model, _ = calibrate_arrays(
        rec.sensor_stamps_ns,
        rec.sensor,
        rec.joint_stamps_ns,
        rec.joint_velocity,
        profile=p,
        sweep="free",
    )
    # at the lowest rates a 64-sample block spans seconds of motion: no block may be steady
    assume(len(model.cells) > 0)
    return model


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(streams(), layouts(), layouts())
# found by the long profile: 50 Hz, joint states at 12.5 Hz, written topic by topic by rosbags
# (one chunk held every sensor sample and the first third of the joint states)
@example(
    Stream(50.0, 1, 1492, 0, 0.0, 0.25, ()),
    Layout("drawn", writer="rosbags", order="time", chunk_bytes=4096),
    Layout("drawn", writer="rosbags", order="topic", chunk_bytes=4096),
)
def test_denoise_and_calibrate_agree_with_batch_and_across_file_layouts(stream, first, second):
    p = stream.profile()
    rec = stream.recording(p)
    model = _model(stream, p)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_recording(tmp / "source", rec, profile=p)
        results = []
        for k, layout in enumerate((first, second)):
            bag = bagcorpus.write_layout(tmp / "source", tmp / f"bag{k}", layout)
            denoise_bag(bag, tmp / f"out{k}", model=model)
            out = read_recording(tmp / f"out{k}", profile=p, ground_truth=False)
            arrays = read_recording(bag, profile=p, ground_truth=False, denoised=False)
            stamps, values, stats = denoise_batch(
                arrays.sensor_stamps_ns,
                arrays.sensor,
                arrays.joint_stamps_ns,
                arrays.joint_velocity,
                model,
            )
            # one message per valid raw sample (all are valid here), the batch core's values
            np.testing.assert_array_equal(out.denoised_stamps_ns, arrays.sensor_stamps_ns)
            np.testing.assert_array_equal(out.denoised_stamps_ns, stamps)
            np.testing.assert_allclose(out.denoised, values, rtol=0, atol=1e-12)
            acc = calibrate_bag(bag, profile=p, sweep="free")
            results.append((out, acc.to_model()))
        (out_a, model_a), (out_b, model_b) = results
        np.testing.assert_array_equal(out_a.denoised_stamps_ns, out_b.denoised_stamps_ns)
        np.testing.assert_allclose(out_a.denoised, out_b.denoised, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(model_a.cells, model_b.cells)
        np.testing.assert_array_equal(model_a.cell_counts, model_b.cell_counts)
        np.testing.assert_allclose(model_a.cell_mean, model_b.cell_mean, rtol=0, atol=1e-12)
