"""Calibration: known per-cell noise recovered, one pass, rejection, resume."""

import numpy as np
import pytest
from scipy import signal
from synthetic import FS, push_random_chunks, stream

from egovib_ros.core import CalibrationAccumulator, NoiseModel, analysis_window, calibrate_arrays

CELLS = [(0.0, 0.0), (1.5, 0.0), (0.0, 0.02), (-3.0, -0.04)]
SIGMA = [0.1, 1.0, 0.5, 2.0]


@pytest.fixture(scope="module")
def calibrated():
    data = stream(40, CELLS, sigma=SIGMA, seed=3)
    model, stats = calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    return data, model, stats


def cell_index(model, velocity):
    return tuple(int(np.argmin(np.abs(g - v))) for g, v in zip(model.grid, velocity))


def test_white_noise_levels_and_rayleigh_spread_are_recovered(calibrated):
    _, model, _ = calibrated
    band = (model.freqs_hz > 250) & (model.freqs_hz < 650)
    level = [model.mean[cell_index(model, c)][0, band].mean() for c in CELLS]
    spread = [model.std[cell_index(model, c)][0, band].mean() for c in CELLS]
    # Level scales with the noise std of the cell (~900 half-overlapping blocks per cell
    # and 8 bins: about 1 % sampling error)...
    np.testing.assert_allclose(np.array(level) / level[1], np.array(SIGMA) / SIGMA[1], rtol=0.03)
    # ...and the magnitude of complex Gaussian bins is Rayleigh: std/mean = sqrt(4/pi - 1).
    np.testing.assert_allclose(
        np.array(spread) / np.array(level), np.sqrt(4 / np.pi - 1), rtol=0.05
    )


def test_matches_an_independent_reference_computation():
    data = stream(10, [(0.9, -0.012)], sigma=[0.7], seed=4)
    model, stats = calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    # Reference: scipy's ShortTimeFFT on the band-passed sum of axes, same window and hop.
    sos = signal.butter(4, [150, 750], btype="bandpass", fs=FS, output="sos")
    x = data["accel"].sum(axis=1)
    y, _ = signal.sosfilt(sos, x, zi=signal.sosfilt_zi(sos) * x[0])
    stft = signal.ShortTimeFFT(analysis_window(64, 32), hop=32, fs=FS, mfft=64, fft_mode="onesided")
    spectra = np.abs(
        stft.stft(y, p0=0, p1=(len(y) - 64) // 32 + 1, k_offset=32)
    )  # blocks fully inside
    cell = cell_index(model, (0.9, -0.012))
    assert model.counts[cell] == spectra.shape[1] == stats.blocks_used
    np.testing.assert_allclose(model.mean[cell][0], spectra.mean(axis=1), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(
        model.std[cell][0], spectra.std(axis=1, ddof=1), rtol=1e-7, atol=1e-12
    )


def test_streaming_any_chunking_equals_one_pass(calibrated):
    data, model, _ = calibrated
    acc = CalibrationAccumulator()
    push_random_chunks(acc, data, np.random.default_rng(0), max_chunk=3000)
    acc.flush()
    streamed = acc.to_model()
    np.testing.assert_array_equal(streamed.counts, model.counts)
    np.testing.assert_allclose(streamed.mean, model.mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(streamed.std, model.std, rtol=1e-9, atol=1e-12)


def test_memory_stays_bounded_however_long_the_recording():
    acc = CalibrationAccumulator()
    data = stream(120, [(1.5, 0.02)], seed=5)
    sizes = []
    for start in range(0, len(data["t_acc"]), 3000):
        stop = start + 3000
        j0, j1 = np.searchsorted(
            data["t_joint"],
            data["t_acc"][[start, min(stop, len(data["t_acc"])) - 1]] + [0, 25_000_000],
        )
        acc.push_joint_states(data["t_joint"][j0:j1], data["velocity"][j0:j1])
        acc.push_sensor(data["t_acc"][start:stop], data["accel"][start:stop])
        sizes.append(acc.backlog)
    assert max(s[0] for s in sizes) < 200 and max(s[1] for s in sizes) < 1400


def test_reversals_are_rejected_as_unsteady_and_off_grid_blocks_too():
    data = stream(6, [(0.0, 0.0)], seed=6)
    t = data["t_joint"] / 1e9
    sign = np.where(np.floor(t / 0.1) % 2 == 0, 1.0, -1.0)  # reverses every 0.1 s
    data["velocity"] = np.stack([1.5 * sign, np.zeros_like(t)], axis=1)
    model, stats = calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    n_reversals = int(np.sum(np.diff(sign) != 0))
    assert stats.rejected["unsteady"] >= n_reversals
    used = np.argwhere(model.counts > 0)
    assert sorted(model.grid[0][used[:, 0]].tolist()) == [-1.5, 1.5]
    data["velocity"] = np.tile([0.15, 0.0], (len(t), 1))  # half way between cells
    model, stats = calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    assert model.counts.sum() == 0 and stats.rejected["off_grid"] > 0


def test_superposition_sweep_ignores_cells_with_both_joints_moving():
    data = stream(8, [(1.5, 0.0), (1.5, 0.02)], seed=7)
    model, stats = calibrate_arrays(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], sweep="superposition"
    )
    assert model.measured == "superposition"
    assert model.counts[cell_index(model, (1.5, 0.02))] == 0 and stats.rejected["not_in_sweep"] > 0
    assert model.counts[cell_index(model, (1.5, 0.0))] > 0


def test_resume_from_checkpoint_keeps_cells_and_adds_new_ones(tmp_path, calibrated):
    _, model, _ = calibrated
    path = tmp_path / "checkpoint.npz"
    model.save(path)
    resumed = CalibrationAccumulator.from_model(NoiseModel.load(path))
    again = resumed.to_model()
    np.testing.assert_array_equal(again.counts, model.counts)
    np.testing.assert_allclose(again.mean, model.mean, rtol=1e-12)
    np.testing.assert_allclose(again.std, model.std, rtol=1e-6, atol=1e-12)
    more = stream(4, [(0.9, 0.0)], seed=8)
    resumed.push_joint_states(more["t_joint"], more["velocity"])
    resumed.push_sensor(more["t_acc"], more["accel"])
    resumed.flush()
    grown = resumed.to_model()
    assert grown.counts[cell_index(grown, (0.9, 0.0))] > 0
    assert np.all(grown.counts[model.counts > 0] == model.counts[model.counts > 0])


def test_a_stream_refused_for_its_rate_goes_on_after_restart_stream_with_what_it_had():
    """A burst at another rate is refused (RateError: a calibrator node drops it); once the
    rate is back, `restart_stream` frames afresh: the cells gathered before are kept, new
    cells are added, and the counts run on over the restart."""
    from egovib_ros.errors import RateError

    def part(duration_s, cell, seed, start_s):
        data = stream(duration_s, [cell], seed=seed)
        shift = int(start_s * 1e9)
        return data["t_acc"] + shift, data["accel"], data["t_joint"] + shift, data["velocity"]

    acc = CalibrationAccumulator()
    t, x, tj, v = part(4, (1.5, 0.0), 1, 0)
    acc.push_joint_states(tj, v)
    acc.push_sensor(t, x)
    before = acc.to_model().counts.copy()
    assert before.sum() > 0
    t, x, tj, v = part(2, (1.5, 0.0), 2, 4.01)
    acc.push_joint_states(tj, v)
    with pytest.raises(RateError):  # every other sample lost: half the rate
        acc.push_sensor(t[::2], x[::2])
    with pytest.raises(RateError):  # and it stays refused
        acc.push_sensor(t[-4:] + 10_000_000, x[-4:])
    acc.restart_stream()
    t, x, tj, v = part(4, (0.0, 0.02), 3, 6.02)
    acc.push_joint_states(tj, v)
    acc.push_sensor(t, x)
    acc.flush()
    after = acc.to_model()
    assert np.all(after.counts[before > 0] >= before[before > 0])
    assert after.counts[cell_index(after, (0.0, 0.02))] > 0
    assert acc.stats.samples_in > len(t) + 2 * FS  # counted over the restart


def test_a_sample_bridged_now_and_then_keeps_its_block_a_run_of_them_does_not():
    """1.6 % of the samples NaN on one axis (each bridged by the core): every block held
    one and was set aside as partial, so no model; blocks with at most MAX_BRIDGED_SAMPLES
    inside them are used, and the levels stay those of the clean stream. A 20-sample run of
    bad samples still sets its blocks aside; any chunking gives the same model."""
    from egovib_ros.core.calibration import MAX_BRIDGED_SAMPLES

    data = stream(10, CELLS, sigma=SIGMA, seed=6)
    arrays = (data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    clean, clean_stats = calibrate_arrays(*arrays)
    sparse = data["accel"].copy()
    sparse[np.random.default_rng(1).random(len(sparse)) < 0.016, 0] = np.nan
    sparse[5000:5020] = np.nan  # a run: its blocks stay out
    model, stats = calibrate_arrays(data["t_acc"], sparse, data["t_joint"], data["velocity"])
    assert MAX_BRIDGED_SAMPLES == 2 and stats.samples_bad > 400
    assert stats.blocks_used > 0.7 * clean_stats.blocks_used
    assert stats.rejected["partial"] >= 3  # the run's blocks (and the ends)
    band = (model.freqs_hz > 250) & (model.freqs_hz < 650)
    for cell in CELLS:
        index = cell_index(model, cell)
        got, want = model.mean[index][0, band].mean(), clean.mean[index][0, band].mean()
        assert got == pytest.approx(want, rel=0.05)
    acc = CalibrationAccumulator()
    push_random_chunks(acc, {**data, "accel": sparse}, np.random.default_rng(2), max_chunk=3000)
    acc.flush()
    np.testing.assert_array_equal(acc.to_model().counts, model.counts)


def test_auto_takes_a_superposition_sweep_with_a_few_stray_blocks_for_one():
    """A joint settling while the next starts leaves a few blocks with two joints moving:
    "auto" still calls it a superposition sweep and leaves them out; many such blocks make
    it a full sweep."""
    cells = [(v, 0.0) for v in (-3.0, -1.5, 1.5, 3.0)] + [(0.0, w) for w in (-0.04, 0.02)]
    data = stream(24, cells, seed=8)
    t_joint = data["t_joint"]
    stray = (t_joint - t_joint[0] > 1.0e9) & (t_joint - t_joint[0] < 1.3e9)
    data["velocity"][stray] = (-3.0, 0.02)  # 0.3 s of 24: two joints moving
    model, stats = calibrate_arrays(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], sweep="auto"
    )
    assert stats.mode == model.measured == "superposition"
    assert model.counts[cell_index(model, (-3.0, 0.02))] == 0 and stats.rejected["not_in_sweep"] > 0
    assert model.counts[cell_index(model, (-3.0, 0.0))] > 0
    data["velocity"][t_joint - t_joint[0] < 4e9] = (-3.0, 0.02)  # a sixth of it
    model, stats = calibrate_arrays(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], sweep="auto"
    )
    assert stats.mode == model.measured == "full"
    assert model.counts[cell_index(model, (-3.0, 0.02))] > 0
