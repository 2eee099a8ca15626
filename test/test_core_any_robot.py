"""Core on robots that are not the PR2: N joints, any rate, gyro field, jittery
stamps, free-motion calibration, sparse models, coverage, streaming == batch."""

import tracemalloc

import numpy as np
import pytest
from robots import profile, recording
from synthetic import push_random_chunks

from egovib_ros.core import (
    CalibrationAccumulator,
    NoiseModel,
    StreamingDenoiser,
    calibrate_arrays,
    denoise_batch,
)
from egovib_ros.core.filters import BandPass, channel_matrix
from egovib_ros.core.noise_model import sweep_cells
from egovib_ros.errors import ConfigError, ModelFileError
from egovib_ros.robot import RobotProfile


@pytest.fixture(scope="module")
def three_joint():
    """A 3-joint robot at 1.6 kHz (two bidirectional joints, one one-directional)."""
    p = profile(3, rate_hz=1600.0)
    train = recording(p, 240.0, seed=1, joint_rate_hz=400.0)
    model, stats = calibrate_arrays(
        train["t_acc"],
        train["accel"],
        train["t_joint"],
        train["velocity"],
        profile=p,
        sweep="auto",
        source="free motion",
    )
    return p, model, stats


def test_free_motion_is_recognised_and_calibrates_a_sparse_model(three_joint):
    p, model, stats = three_joint
    assert stats.mode == "free" and model.measured == "free"
    assert model.profile == p and model.grid_shape == (21, 21, 11)
    cov = model.coverage()
    assert cov["cells_measured"] == len(model.cells) > 100 and cov["cells_total"] == 21 * 21 * 11
    assert cov["blocks"] == stats.blocks_used > 0.8 * stats.blocks
    # the one-directional joint is never measured below zero
    assert model.grid[2][0] == 0.0 and np.all(model.cells[:, 2] >= 0)


def test_keyed_free_motion_model_beats_a_global_average_spectrum(three_joint):
    """Keyed on the 3 joints, the free-motion model gains peak SNR where subtracting one
    average spectrum (what a user would otherwise pick) mostly trades taps for noise."""
    p, model, _ = three_joint
    train = recording(p, 240.0, seed=1, joint_rate_hz=400.0)
    at_rest = RobotProfile(
        **{
            **{f: getattr(p, f) for f in p.__dataclass_fields__ if f != "source"},
            "joint_names": ("none",),
            "max_speed": (1.0,),
            "bidirectional": (False,),
            "steps": 1,
        }
    )
    global_model, _ = calibrate_arrays(
        train["t_acc"],
        train["accel"],
        train["t_joint"],
        np.zeros((len(train["t_joint"]), 1)),
        profile=at_rest,
        sweep="free",
    )
    test = recording(p, 30.0, seed=2, joint_rate_hz=400.0, taps_per_s=1.0)
    band = BandPass(sample_rate_hz=p.rate_hz, band_hz=p.band_hz, order=p.band_order, n_channels=1)
    raw = band.process(channel_matrix(test["accel"], "combined").T)[0]
    quiet = np.ones(len(raw), dtype=bool)
    for o in test["onsets"]:
        quiet[max(0, o - 100) : o + 300] = False
    quiet[:2000] = quiet[-2000:] = False

    def peak_snr(x):
        peak = np.mean([np.abs(x[o : o + 120]).max() for o in test["onsets"][1:-1]])
        return 20 * np.log10(peak / np.mean(np.abs(x[quiet]))), peak

    keyed_stamps, keyed, stats = denoise_batch(
        test["t_acc"], test["accel"], test["t_joint"], test["velocity"], model, channels="combined"
    )
    _, flat, _ = denoise_batch(
        test["t_acc"],
        test["accel"],
        test["t_joint"],
        np.zeros((len(test["t_joint"]), 1)),
        global_model,
        channels="combined",
    )
    assert np.array_equal(keyed_stamps, test["t_acc"])  # jittery stamps kept, one output per input
    (snr_raw, peak_raw), (snr_keyed, peak_keyed), (snr_flat, _) = (
        peak_snr(raw),
        peak_snr(keyed[:, 0]),
        peak_snr(flat[:, 0]),
    )
    reduction = 20 * np.log10(np.mean(np.abs(raw[quiet])) / np.mean(np.abs(keyed[quiet, 0])))
    assert reduction > 4.0 and peak_keyed / peak_raw > 0.6, (reduction, peak_keyed / peak_raw)
    assert snr_keyed - snr_raw > (snr_flat - snr_raw) + 1.5, (snr_raw, snr_keyed, snr_flat)
    assert stats.blocks_unmeasured < 0.5 * stats.blocks


def test_three_joint_streaming_equals_batch_for_any_chunking(three_joint):
    p, model, _ = three_joint
    test = recording(p, 6.0, seed=3, joint_rate_hz=400.0)
    stamps, values, _ = denoise_batch(
        test["t_acc"], test["accel"], test["t_joint"], test["velocity"], model
    )
    rng = np.random.default_rng(4)
    denoiser = StreamingDenoiser(model)
    chunks = push_random_chunks(denoiser, test, rng, max_chunk=97) + [denoiser.flush()]
    got_stamps = np.concatenate([c.stamps_ns for c in chunks])
    got = np.concatenate([c.values for c in chunks])
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got, values)
    # calibration too: chunked accumulation gives the batch model
    acc = CalibrationAccumulator(profile=p, sweep="free")
    push_random_chunks(acc, test, rng, max_chunk=211)
    acc.flush()
    streamed = acc.to_model()
    batch, _ = calibrate_arrays(
        test["t_acc"], test["accel"], test["t_joint"], test["velocity"], profile=p, sweep="free"
    )
    np.testing.assert_array_equal(streamed.cells, batch.cells)
    np.testing.assert_allclose(streamed.cell_mean, batch.cell_mean, rtol=1e-12)


def test_joint_states_slower_than_the_sensor_and_model_round_trip(three_joint, tmp_path):
    p, model, _ = three_joint
    path = tmp_path / "robot.npz"
    model.save(path)
    loaded = NoiseModel.load(path)
    assert loaded.profile == p and loaded.measured == "free"
    np.testing.assert_array_equal(loaded.cells, model.cells)
    test = recording(p, 4.0, seed=5, joint_rate_hz=100.0)  # joint states at 1/16 of the sensor rate
    a = denoise_batch(test["t_acc"], test["accel"], test["t_joint"], test["velocity"], model)
    b = denoise_batch(test["t_acc"], test["accel"], test["t_joint"], test["velocity"], loaded)
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2].blocks_no_joint_state == 0


def test_auto_recognises_a_sweep_and_the_superposition_sweep():
    p = profile(2, rate_hz=1000.0, bidirectional=(True, False), steps=4)
    rng = np.random.default_rng(6)
    cells = sweep_cells(p.grid(), "superposition")
    fs, dwell = p.rate_hz, 1.0
    n_cell = int(dwell * fs)
    t = (1_000_000_000 + np.arange(len(cells) * n_cell) * 1e9 / fs).astype(np.int64)
    velocity = np.repeat(
        np.array([[p.grid()[j][c[j]] for j in range(2)] for c in cells]), n_cell, axis=0
    )
    accel = rng.normal(size=(len(t), 3)) * (1 + np.abs(velocity).sum(axis=1))[:, None]
    model, stats = calibrate_arrays(t, accel, t, velocity, profile=p, sweep="auto")
    assert stats.mode == model.measured == "superposition"
    assert len(model.cells) == len(cells) == 1 + 8 + 4


def test_eight_joint_superposition_model_saves_loads_and_denoises_in_little_memory(tmp_path):
    p = profile(8, rate_hz=1000.0, bidirectional=(True,) * 8, steps=10, field="linear_acceleration")
    cells = sweep_cells(p.grid(), "superposition")  # 161 of 21^8 = 3.8e10 cells
    rng = np.random.default_rng(7)
    n_bins = p.block_length // 2 + 1
    moving = (cells != 10).sum(axis=1)
    mean = rng.uniform(0.1, 1.0, (len(cells), 4, n_bins)) * (1 + moving)[:, None, None]
    tracemalloc.start()
    model = NoiseModel(
        grid=p.grid(),
        joint_names=p.joint_names,
        cells=cells,
        mean=mean,
        std=0.2 * mean,
        counts=np.full(len(cells), 50),
        sample_rate_hz=p.rate_hz,
        block_length=p.block_length,
        hop=p.hop,
        band_hz=p.band_hz,
        band_order=p.band_order,
        measured="superposition",
        profile=p,
    )
    path = tmp_path / "eight.npz"
    model.save(path)
    loaded = NoiseModel.load(path)
    test = recording(p, 20.0, seed=8, joint_rate_hz=250.0)
    stamps, values, stats = denoise_batch(
        test["t_acc"], test["accel"], test["t_joint"], test["velocity"], loaded
    )
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 50 * 2**20, f"{peak / 2**20:.1f} MB"
    assert not loaded.dense_ok and len(stamps) == len(test["t_acc"]) and np.all(np.isfinite(values))
    assert path.stat().st_size < 2**20
    with pytest.raises(ModelFileError, match="too large for a dense view"):
        _ = loaded.mean
    # Eq. 6 for 8 joints: the estimate at a cell is the sum of its axis cells minus 7 x the
    # zero cell
    cell = np.array([[12, 10, 10, 3, 10, 10, 20, 10]])
    velocity = np.array([[p.grid()[j][cell[0, j]] for j in range(8)]])
    noise, outside = loaded.estimate(velocity)
    axis = {tuple(c): k for k, c in enumerate(cells)}
    zero = axis[(10,) * 8]
    parts = [
        axis[tuple(np.where(np.arange(8) == j, cell[0], 10))] for j in range(8) if cell[0, j] != 10
    ]
    mu = mean[parts].sum(axis=0) - (len(parts) - 1) * mean[zero]
    # joints at rest contribute the zero cell: sd^2 terms of 3 moving + 5 resting joints + 7 sd0^2
    sd = np.sqrt(
        ((0.2 * mean[parts]) ** 2).sum(axis=0) + (15 - len(parts)) * (0.2 * mean[zero]) ** 2
    )
    np.testing.assert_allclose(noise[0], np.maximum(mu, 0) + sd, rtol=1e-12)
    assert not outside[0]


def test_unmeasured_cells_fall_back_and_are_counted(three_joint):
    p, model, _ = three_joint
    corner = np.array(
        [[p.max_speed[0], -p.max_speed[1], p.max_speed[2]]]
    )  # never visited at 90 % speed
    noise, outside, measured = model.lookup(corner)
    assert np.all(np.isfinite(noise)) and not outside[0] and not measured[0]
    visited = np.array([[model.grid[j][model.cells[0, j]] for j in range(3)]])
    assert model.lookup(visited)[2][0]


def test_profile_overrides_and_bad_settings_are_refused():
    p = profile(3)
    with pytest.raises(ConfigError, match="grid: expected one of"):
        CalibrationAccumulator(profile=p, sweep="spiral")


def test_pooling_two_recordings_weights_each_cell_by_its_blocks():
    p = profile(2, rate_hz=1000.0, bidirectional=(True, False))
    parts = []
    for seed in (11, 12):
        acc = CalibrationAccumulator(profile=p, sweep="free")
        push_random_chunks(
            acc, recording(p, 20.0, seed=seed), np.random.default_rng(seed), max_chunk=300
        )
        acc.flush()
        parts.append(acc)
    models = [acc.to_model() for acc in parts]
    parts[0].merge(parts[1])
    pooled = parts[0].to_model()
    for k, cell in enumerate(pooled.cells):
        counts, sums = 0, 0.0
        for m in models:
            row = np.flatnonzero((m.cells == cell).all(axis=1))
            if len(row):
                counts += m.cell_counts[row[0]]
                sums = sums + m.cell_counts[row[0]] * m.cell_mean[row[0]]
        assert pooled.cell_counts[k] == counts
        np.testing.assert_allclose(pooled.cell_mean[k], sums / counts, rtol=1e-12)
    with pytest.raises(ConfigError, match="cannot pool"):
        parts[0].merge(CalibrationAccumulator(profile=profile(3)))
