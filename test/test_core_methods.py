"""core.methods: `paper | cancel | hybrid` behind one push interface, their calibration and
its storage in the noise model (schema 3, older models still load)."""

from __future__ import annotations

import dataclasses
import logging
import math
import zipfile
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import signal
from synthetic import TWO_MOTOR_FS, two_motor_profile, two_motor_recording

from egovib_ros.core import StreamingDenoiser, calibrate_arrays, filters
from egovib_ros.core.contact import joint_acceleration
from egovib_ros.core.lowlatency import MAX_DELAY_MS, GainSettings
from egovib_ros.core.methods import (
    DETECTION_MIN_S,
    MAX_EARLY_OPENING_MS,
    MOTION_SPEED_MARGIN,
    DropInSplit,
    MethodCalibration,
    SampleMethodDenoiser,
    calibrate_detection,
    calibrate_methods,
    denoise_batch_method,
    make_denoiser,
    method_delay_ms,
    motion_limits,
    rest_detection_warning,
    short_detection_warning,
)
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.errors import ConfigError, ModelFileError, StreamError

FS = TWO_MOTOR_FS
PROFILE = two_motor_profile("two_motor_test")


def recording(duration_s: float, *, seed: int, taps_per_s: float = 0.0, tap_peak: float = 2.0):
    """Two motors (synthetic.two_motor_recording) at speeds wandering over 0.1-1.0, jittery
    stamps."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * FS)
    steps = 1.0 + rng.uniform(-0.2, 0.2, n)
    sos = signal.butter(2, 0.5, fs=FS, output="sos")
    speed = np.empty((n, 2))
    for j in range(2):
        walk = signal.sosfiltfilt(sos, rng.normal(size=n + 2000))[1000:-1000]
        speed[:, j] = np.clip(0.55 + 0.2 * walk / walk.std(), 0.1, 1.0)
    mixing = rng.normal(size=(4, 3))
    return two_motor_recording(
        speed, steps, rng, mixing=mixing, taps_per_s=taps_per_s, tap_peak=tap_peak
    )


@pytest.fixture(scope="module")
def model() -> NoiseModel:
    rec = recording(25.0, seed=1)
    paper, _ = calibrate_arrays(
        rec["t"], rec["accel"], rec["tj"], rec["velocity"], profile=PROFILE, sweep="free"
    )
    full, info = calibrate_methods(paper, rec["t"], rec["accel"], rec["tj"], rec["velocity"])
    assert info["harmonic"]["fit"]["joints"]["m1"]["orders"][:2] == [1.0, 2.0]
    return full


def combined_bp(values: np.ndarray) -> np.ndarray:
    return filters.combined_bandpassed(values, PROFILE)


def test_hybrid_removes_the_motors_and_keeps_the_taps_within_5_ms(model):
    # taps about as high as the largest noise peaks (the evaluation's event rule)
    rec = recording(10.0, seed=2, taps_per_s=2.0, tap_peak=4.0)
    quiet_rec = recording(10.0, seed=2)  # the same noise without the taps
    raw = combined_bp(rec["accel"])
    truth = combined_bp(rec["contact"])
    outputs, without = {}, {}
    for method in ("paper", "cancel", "hybrid"):
        for r, store in ((rec, outputs), (quiet_rec, without)):
            stamps, values, stats = denoise_batch_method(
                r["t"],
                r["accel"],
                r["tj"],
                r["velocity"],
                model,
                method=method,
                channels="combined",
            )
            assert np.array_equal(stamps, r["t"])  # one output per input, its stamp
            assert stats.samples_out == len(r["t"]) and stats.samples_bad == 0
            if method != "paper":  # typed; the per-sample methods' own fields, no blocks
                assert stats.method == method and stats.blocks is None
                table = ["samples_unmeasured", "samples_out_of_grid"] * (method == "hybrid")
                assert stats.delay_samples >= 0 and list(stats.as_dict()) == [
                    "method", "samples_in", "samples_out", "dropped_out_of_order",
                    "samples_bad", "gap_filled_samples", "resets", "joint_states_in",
                    "joint_states_dropped", "samples_no_joint_state", "rate_checked",
                    "delay_samples", "frequency_correction", *table,
                    "duplicates", "joint_states_duplicates",
                ]  # fmt: skip
                assert len(stats.frequency_correction) == r["velocity"].shape[1]
            store[method] = values[:, 0]
    quiet = np.ones(len(raw), bool)
    for o in rec["onsets"]:
        quiet[o - 20 : o + 80] = False
    quiet[:1000] = False
    taps = [slice(o, o + 40) for o in rec["onsets"][2:]]

    def reduction(out):
        return 20 * math.log10(np.abs(raw[quiet]).mean() / np.abs(out[quiet]).mean())

    def kept(method):  # what the method left of each tap: with it minus without it
        diff = outputs[method] - without[method]
        peaks = [np.abs(diff[w]).max() / np.abs(truth[w]).max() for w in taps]
        corr = [np.corrcoef(diff[w], truth[w])[0, 1] for w in taps]
        return np.mean(peaks), np.mean(corr)

    assert reduction(outputs["cancel"]) > 6.0
    assert kept("cancel")[0] > 0.95 and kept("cancel")[1] > 0.95
    assert reduction(outputs["hybrid"]) > 15.0
    peak, corr = kept("hybrid")
    assert peak > 0.9 and corr > 0.9
    assert peak > kept("paper")[0]
    # and the output itself looks like the tap
    assert np.mean([np.corrcoef(outputs["hybrid"][w], truth[w])[0, 1] for w in taps]) > 0.9
    assert method_delay_ms(model, "hybrid", output="bandpassed") <= MAX_DELAY_MS
    assert method_delay_ms(model, "cancel", channels="combined") == 0.0
    assert method_delay_ms(model, "paper") == pytest.approx(31.0)


@settings(max_examples=10, deadline=None)
@given(
    st.sampled_from(["cancel", "hybrid"]),
    st.lists(st.integers(min_value=1, max_value=900), min_size=1, max_size=8),
    st.sampled_from(["per_axis", "combined"]),
    st.booleans(),
)
# a chunk ending just before the gap: the segment's end must still release the look-ahead
@example("hybrid", [1, 1, 298, 900], "per_axis", False)
@example("hybrid", [6, 6, 6, 6, 6, 6, 900], "per_axis", True)
def test_streaming_equals_batch_for_any_chunking(model, method, cuts, channels, together):
    """Pushed apart, or (`together`, as the denoiser node does) each sensor chunk with
    the joint states that came with it, in one `push`."""
    rec = recording(3.0, seed=3, taps_per_s=2.0)
    keep = np.ones(len(rec["t"]), bool)
    keep[1200:1230] = False  # a long gap: the segment ends and restarts
    t, accel = rec["t"][keep], rec["accel"][keep]
    want_t, want, _ = denoise_batch_method(
        t, accel, rec["tj"], rec["velocity"], model, method=method, channels=channels
    )
    denoiser = make_denoiser(model, method, channels=channels)
    edges = np.r_[np.unique(np.clip(np.cumsum(cuts), 1, len(t))), len(t)]
    got_t, got, j_pos, start = [], [], 0, 0
    for stop in np.unique(edges):
        limit = int(np.searchsorted(rec["tj"], t[stop - 1] + 21_000_000, side="right"))
        last = j_pos + (limit - j_pos - 1) // 7 * 7 if together and limit > j_pos else limit
        for a in range(j_pos, last, 7):  # joint states in small batches
            chunk = denoiser.push_joint_states(
                rec["tj"][a : min(a + 7, limit)], rec["velocity"][a : min(a + 7, limit)]
            )
            got_t.append(chunk.stamps_ns)
            got.append(chunk.values)
        j_pos = max(j_pos, limit)
        if last < limit:  # the last batch of joint states with the samples
            jt, jv = rec["tj"][last:limit], rec["velocity"][last:limit]
            chunk = denoiser.push(jt, jv, t[start:stop], accel[start:stop])
        else:
            chunk = denoiser.push_sensor(t[start:stop], accel[start:stop])
        got_t.append(chunk.stamps_ns)
        got.append(chunk.values)
        start = stop
        stats = denoiser.stats  # the node's cheap count agrees with the stats
        assert denoiser.samples_pending == stats.samples_in - stats.samples_out  # none bad
    chunk = denoiser.push_joint_states(rec["tj"][j_pos:], rec["velocity"][j_pos:])
    got_t.append(chunk.stamps_ns)
    got.append(chunk.values)
    chunk = denoiser.flush()
    got_t.append(chunk.stamps_ns)
    got.append(chunk.values)
    assert np.array_equal(np.concatenate(got_t), want_t)
    assert np.array_equal(np.concatenate(got), want)
    assert np.array_equal(want_t, t)


@pytest.mark.parametrize("method", ["cancel", "hybrid"])
def test_dropin_output_keeps_gravity_and_motion_and_removes_the_motors(model, method):
    """The drop-in output: the raw samples less what the method took from the band, so what
    lies below the band (gravity, a slow rigid-body motion) passes as it was."""
    rec = recording(10.0, seed=2)
    n = len(rec["t"])
    motion = np.zeros((n, 3))
    motion[:, 0] = 0.8 * np.sin(2 * np.pi * 2.0 * np.arange(n) / FS)  # 2 Hz, far below the band
    raw = rec["accel"] + motion
    args = (rec["t"], raw, rec["tj"], rec["velocity"], model)
    stamps, dropin, stats = denoise_batch_method(*args, method=method)
    _, band, _ = denoise_batch_method(*args, method=method, output="bandpassed")
    assert np.array_equal(stamps, rec["t"]) and dropin.shape == raw.shape
    # cancel: no delay (the lines are subtracted as they come); hybrid: its look-ahead
    assert (stats.delay_samples > 0) == (method == "hybrid")
    low = signal.butter(8, 10.0, fs=FS, output="sos")  # steep: the removal is 60 Hz and up
    settled = slice(1000, n - 1000)
    below = signal.sosfiltfilt(low, dropin - raw, axis=0)[settled]
    # gravity (9.81 on z) passes exactly and the motion (0.8 at 2 Hz) to 1.5 %: what moves
    # below 10 Hz is the removal's own slow part: hybrid's split keeps most of it out (its
    # FIR, as short as its look-ahead, passes the motion to ~1 %); cancel, with no delay to
    # split in, subtracts its lines' own slow part too (the paper's drop-in: 0.021)
    assert np.abs(below).max() < (0.015 if method == "cancel" else 0.012)
    quiet = np.zeros(n, bool)
    quiet[settled] = True

    def reduction(out):
        return 20 * math.log10(
            np.abs(combined_bp(raw)[quiet]).mean() / np.abs(combined_bp(out)[quiet]).mean()
        )

    # what the band-passed output removes, the drop-in removes from the raw signal too (up
    # to the band-pass inverse's fit)
    assert reduction(dropin) > (5.0 if method == "cancel" else 12.0)
    assert reduction(dropin) > reduction(band[:, :]) - 10.0


@pytest.mark.parametrize("output", ["dropin", "bandpassed"])
@pytest.mark.parametrize("seed", [4, 5, 8, 11])
def test_a_stream_started_in_motion_does_not_begin_with_a_burst(model, seed, output):
    # The motors run from the first sample; the canceller's trackers start from nothing.
    # Before the guard started raised (GainSettings.guard_start), the first 0.45 s reached
    # 3.6-5.5 times the rest's largest peak (an event to any detector); now 0.1-0.5.
    rec = recording(3.0, seed=seed)
    _, values, _ = denoise_batch_method(
        rec["t"], rec["accel"], rec["tj"], rec["velocity"], model, method="hybrid", output=output
    )
    band = np.abs(combined_bp(values))
    assert band[: int(0.45 * FS)].max() < band[int(0.5 * FS) :].max()


@pytest.mark.parametrize("seed", [1, 4, 6])
def test_after_a_long_gap_the_stream_does_not_start_again_with_a_burst(model, seed):
    # 0.2 s lost mid-motion: a new segment, the lines' phases lost. Before the guard stood
    # at its start again, the first 0.45 s after the gap reached 1.8-3.3 times the largest
    # peak elsewhere; now 0.3-0.4.
    rec = recording(5.0, seed=seed)
    keep = np.ones(len(rec["t"]), bool)
    keep[2000:2200] = False
    _, values, _ = denoise_batch_method(
        rec["t"][keep], rec["accel"][keep], rec["tj"], rec["velocity"], model, method="hybrid"
    )
    band = np.abs(combined_bp(values))
    after = band[2000 : 2000 + int(0.45 * FS)].max()
    assert after < max(band[600:1900].max(), band[2600:].max())


def test_gain_settings_given_to_calibration_still_get_the_fitted_split(model):
    # An ablation's settings (here 4 bands) once brought back the 4 ms look-ahead the split
    # cannot stop the band in: the drop-in output then lost what the band-passed one removes.
    rec = recording(25.0, seed=1)
    paper, _ = calibrate_arrays(
        rec["t"], rec["accel"], rec["tj"], rec["velocity"], profile=PROFILE, sweep="free"
    )
    fitted = MethodCalibration.from_model(model).gain.split_ms
    full, _ = calibrate_methods(
        paper, rec["t"], rec["accel"], rec["tj"], rec["velocity"], gain=GainSettings(bands=4)
    )
    gain = MethodCalibration.from_model(full).gain
    assert fitted > GainSettings().lookahead_ms
    assert (gain.bands, gain.split_ms) == (4, fitted)


def test_combined_is_the_sum_of_the_cleaned_axes(model):
    rec = recording(2.0, seed=4)
    _, per_axis, _ = denoise_batch_method(
        rec["t"], rec["accel"], rec["tj"], rec["velocity"], model, method="hybrid",
        output="bandpassed",
    )  # fmt: skip
    _, combined, _ = denoise_batch_method(
        rec["t"],
        rec["accel"],
        rec["tj"],
        rec["velocity"],
        model,
        method="hybrid",
        channels="combined",
    )
    np.testing.assert_allclose(combined[:, 0], per_axis.sum(axis=1), rtol=0, atol=1e-12)


def test_the_model_file_carries_the_methods_and_older_models_still_load(model, tmp_path):
    path = tmp_path / "model.npz"
    model.save(path)
    with np.load(path, allow_pickle=False) as data:
        assert int(data["schema_version"]) == 3
        assert any(k.startswith("extra.harmonic.") for k in data.files)
    loaded = NoiseModel.load(path)
    a, b = MethodCalibration.from_model(model), MethodCalibration.from_model(loaded)
    np.testing.assert_array_equal(a.harmonic.line_coefficient, b.harmonic.line_coefficient)
    np.testing.assert_array_equal(a.alpha, b.alpha)
    assert a.gain == b.gain and a.canceller == b.canceller
    rec = recording(1.0, seed=5)
    args = (rec["t"], rec["accel"], rec["tj"], rec["velocity"])
    np.testing.assert_array_equal(
        denoise_batch_method(*args, model, method="hybrid")[1],
        denoise_batch_method(*args, loaded, method="hybrid")[1],
    )
    # A version-2 file (no extras) loads; `paper` runs on it, the new methods say what is missing.
    old = tmp_path / "old.npz"
    with np.load(path, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files if not k.startswith("extra.")}
    fields["schema_version"] = np.array(2)
    with open(old, "wb") as fh:
        np.savez_compressed(fh, **fields)
    v2 = NoiseModel.load(old)
    assert v2.extras == {}
    assert isinstance(make_denoiser(v2, "paper"), StreamingDenoiser)
    with pytest.raises(ModelFileError, match="old.npz: calibrated for the paper's method only"):
        make_denoiser(v2, "hybrid")
    # A model calibrated before the gain's guard (no gain.guard_ref and none of its settings)
    # loads and runs hybrid without the guard: what it did before.
    assert a.guard_ref is not None and b.guard_ref is not None
    np.testing.assert_array_equal(a.guard_ref, b.guard_ref)
    unguarded = tmp_path / "unguarded.npz"
    with np.load(path, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files if "guard" not in k}
    with open(unguarded, "wb") as fh:
        np.savez_compressed(fh, **fields)
    before = MethodCalibration.from_model(NoiseModel.load(unguarded))
    assert before.guard_ref is None
    stage = make_denoiser(NoiseModel.load(unguarded), "hybrid")._gain
    assert np.all(np.isinf(stage.guard_ref))
    # A model calibrated before the low-delay split (linear-phase taps, no split_delay) runs
    # with its split's delay, half its length; low-delay taps without their delay are refused.
    taps, delay = a.dropin_split
    assert len(taps) > 2 * delay + 1  # this robot's split: a low-delay FIR
    linear = tmp_path / "linear.npz"
    with np.load(path, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files if k != "extra.gain.split_delay"}
    fields["extra.gain.split_taps"] = filters.split_taps(
        sample_rate_hz=FS, band_hz=model.band_hz, delay=delay + 2
    )
    fields["extra.gain.split_ms"] = np.array(1e3 * (delay + 2) / FS)
    with open(linear, "wb") as fh:
        np.savez_compressed(fh, **fields)
    assert make_denoiser(NoiseModel.load(linear), "hybrid").delay == delay + 2
    fields["extra.gain.split_taps"] = taps
    with open(linear, "wb") as fh:
        np.savez_compressed(fh, **fields)
    with pytest.raises(ModelFileError, match="linear.npz: gain split_taps without split_delay"):
        make_denoiser(NoiseModel.load(linear), "hybrid")
    # A damaged extra is a one-line model error, not a crash.
    broken = tmp_path / "broken.npz"
    with np.load(path, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files}
    fields["extra.gain.alpha"] = fields["extra.gain.alpha"][:, :1]
    with open(broken, "wb") as fh:
        np.savez_compressed(fh, **fields)
    with pytest.raises(ModelFileError, match="broken.npz: gain alpha"):
        make_denoiser(NoiseModel.load(broken), "hybrid")
    assert zipfile.is_zipfile(path)


def test_methods_are_chosen_by_name_with_their_own_options(model, caplog):
    assert isinstance(make_denoiser(model, "paper", oversubtraction=2.0), StreamingDenoiser)
    hybrid = make_denoiser(model, "hybrid", floor=0.1, lookahead_ms=2.0, output="bandpassed")
    assert isinstance(hybrid, SampleMethodDenoiser)
    assert hybrid.delay_samples == (2, 2)
    # the drop-in output (the default) takes the look-ahead its split needs for this robot
    # (set in calibration from the recording's spectrum), or the one asked for
    split = MethodCalibration.from_model(model).gain.split_ms
    assert 4.0 < split <= 25.0
    dropin = make_denoiser(model, "hybrid")
    assert dropin.output == "dropin" and dropin.delay_ms == pytest.approx(split, abs=0.5)
    assert method_delay_ms(model, "hybrid") == pytest.approx(dropin.delay_ms)  # the default
    assert method_delay_ms(model, "hybrid", output="bandpassed") == pytest.approx(4.0)
    assert make_denoiser(model, "hybrid", lookahead_ms=2.0).delay_samples == (2, 2)
    with pytest.raises(ConfigError, match="dropin needs channels per_axis"):
        method_delay_ms(model, "hybrid", output="dropin", channels="combined")
    with pytest.raises(ConfigError, match="output: expected one of"):
        make_denoiser(model, "cancel", output="")
    with pytest.raises(ConfigError, match="dropin needs channels per_axis"):
        make_denoiser(model, "cancel", channels="combined", output="dropin")
    with pytest.raises(ConfigError, match="output: expected one of"):
        make_denoiser(model, "cancel", output="raw")
    with pytest.raises(ConfigError, match="method: expected one of"):
        make_denoiser(model, "wiener")
    with pytest.raises(ConfigError, match="oversubtraction.*paper"):
        make_denoiser(model, "hybrid", oversubtraction=2.0)
    with pytest.raises(ConfigError, match="lookahead_ms applies to `hybrid`"):
        make_denoiser(model, "paper", lookahead_ms=2.0)


def test_a_calibration_shorter_than_a_minute_is_said_to_set_unsteady_thresholds():
    assert short_detection_warning(DETECTION_MIN_S) is None
    line = short_detection_warning(16.4)
    assert line.startswith("warning:") and "from 16 s of calibration data" in line


def test_a_calibration_mostly_at_rest_is_said_to_set_thresholds_below_motion():
    """A live calibration left running after its sweep: 70 % of the samples with every joint
    below 2 % of its top speed is said; 30 % is not; a NaN velocity counts as moving."""
    stamps = np.arange(1000) * 1_000_000
    joint_stamps = np.arange(0, 1000, 10) * 1_000_000  # each held over 10 samples
    top = [1.0, 2.0]

    def warned(rest_share: float, unknown: bool = False):
        velocity = np.tile([0.5, 1.0], (len(joint_stamps), 1))
        velocity[: int(rest_share * len(joint_stamps))] = [0.01, 0.0]  # under 2 %
        if unknown:
            velocity[:, 1] = np.nan
        return rest_detection_warning(stamps, joint_stamps, velocity, top)

    line = warned(0.7)
    assert line.startswith("warning: 70% of the calibration data is the robot at rest"), line
    assert warned(0.3) is None and warned(0.7, unknown=True) is None
    assert rest_detection_warning(stamps, joint_stamps[:0], np.zeros((0, 2)), top) is None


def test_hybrid_counts_beyond_the_grid_by_the_papers_rule(model):
    """A speed past the grid's top by less than half its edge step (a sweep's dwell
    overshooting it) is in the edge cell; further out it is beyond the grid
    (noise_model.grid_limits, as test_core_subtraction holds for the paper's method)."""
    rec = recording(2.0, seed=3)
    residual = MethodCalibration.from_model(model).residual
    counts = []
    for past in (0.3, 0.6):
        velocity = np.array([g[-1] + past * (g[-1] - g[-2]) for g in residual.grid]) * np.ones(
            (len(rec["tj"]), 1)
        )
        *_, stats = denoise_batch_method(rec["t"], rec["accel"], rec["tj"], velocity, model)
        counts.append(stats.samples_out_of_grid)
    assert counts[0] == 0 < counts[1]


def test_a_sensor_that_never_changes_is_refused_not_fitted(model):
    """The live calibrator's path (calibrate_methods on what it kept): a field the messages
    leave at zero was an SVD that did not converge; now one line."""
    rec = recording(3.0, seed=4)
    flat = np.zeros_like(rec["accel"])
    with pytest.raises(StreamError, match="never changes"):
        calibrate_methods(model, rec["t"], flat, rec["tj"], rec["velocity"], source="live")


def test_a_long_split_lets_the_gain_open_at_most_the_onset_tolerance_early():
    """A band edge low for the rate needs a long drop-in split (here 20 Hz at 1 kHz); its
    gain looked as far ahead and opened that much before a contact (a 500 Hz robot's onsets
    10-20 ms early, F1 0.30). It looks MAX_EARLY_OPENING_MS ahead at most: before that, a tap
    changes nothing of the output."""
    profile = dataclasses.replace(two_motor_profile("low_edge"), band_hz=(20.0, 450.0))
    rec = recording(12.0, seed=1)
    paper, _ = calibrate_arrays(
        rec["t"], rec["accel"], rec["tj"], rec["velocity"], profile=profile, sweep="free"
    )
    model, _ = calibrate_methods(paper, rec["t"], rec["accel"], rec["tj"], rec["velocity"])
    split_delay = MethodCalibration.from_model(model).dropin_split[1]
    early = round(MAX_EARLY_OPENING_MS * 1e-3 * FS)
    assert split_delay > early + 2  # the case: a split longer than the tolerance
    denoiser = make_denoiser(model)
    assert denoiser.delay == split_delay and denoiser.delay_ms == 1e3 * split_delay / FS
    tapped = recording(8.0, seed=2, taps_per_s=2.0, tap_peak=4.0)
    quiet = recording(8.0, seed=2)  # the same noise
    outputs = [
        combined_bp(denoise_batch_method(r["t"], r["accel"], r["tj"], r["velocity"], model)[1])
        for r in (tapped, quiet)
    ]
    change = np.abs(outputs[0] - outputs[1])
    onsets = tapped["onsets"][1:]
    before = np.concatenate([change[o - early - 8 : o - early - 1] for o in onsets])
    after = np.concatenate([change[o : o + 20] for o in onsets])
    assert before.max() < 0.05 * after.max(), (before.max(), after.max())


def test_a_band_edge_no_split_can_reach_is_said_at_calibration(caplog):
    """A 3 Hz band edge at 1 kHz: no split within SPLIT_MAX_DELAY_S keeps motion apart from
    the band (a probe's 5 Hz edge: onsets 20 ms early in the drop-in output). Calibration
    says so, naming the recording; the 60 Hz edge of two_motor_profile does not."""
    rec = recording(6.0, seed=1)
    for edge, said in ((60.0, False), (3.0, True)):
        profile = dataclasses.replace(two_motor_profile("edge"), band_hz=(edge, 450.0))
        paper, _ = calibrate_arrays(
            rec["t"], rec["accel"], rec["tj"], rec["velocity"], profile=profile, sweep="free"
        )
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="egovib_ros.core"):
            calibrate_methods(
                paper, rec["t"], rec["accel"], rec["tj"], rec["velocity"], source="run: /imu"
            )
        warned = [r.getMessage() for r in caplog.records if "too low" in r.getMessage()]
        assert len(warned) == int(said), warned
    assert warned[0].startswith("run: /imu: the band's low edge (3 Hz) is too low")
    assert "`output: bandpassed`" in warned[0]


def test_a_narrow_band_waits_for_its_band_pass_and_keeps_the_taps():
    """A 40 Hz wide band: the band-passed signal shows a tap ~25 ms late, and the gains
    decided on it opened that late on the raw samples (a probe's narrow band: retention 0.30
    in the drop-in output, 0.85 band-passed). The drop-in output now waits for it."""
    profile = dataclasses.replace(two_motor_profile("narrow"), band_hz=(200.0, 240.0))
    rec = recording(12.0, seed=1)
    paper, _ = calibrate_arrays(
        rec["t"], rec["accel"], rec["tj"], rec["velocity"], profile=profile, sweep="free"
    )
    model, _ = calibrate_methods(paper, rec["t"], rec["accel"], rec["tj"], rec["velocity"])
    late = filters.bandpass_delay(sample_rate_hz=FS, band_hz=(200.0, 240.0), order=4)
    assert make_denoiser(model).delay >= round(late) > 15
    tapped = recording(8.0, seed=2, taps_per_s=2.0, tap_peak=4.0)
    quiet = recording(8.0, seed=2)  # the same noise
    band = signal.butter(4, (200.0, 240.0), btype="band", fs=FS, output="sos")
    kept = {}
    for output in ("dropin", "bandpassed"):
        out = [
            denoise_batch_method(r["t"], r["accel"], r["tj"], r["velocity"], model, output=output)
            for r in (tapped, quiet)
        ]
        change = out[0][1].sum(axis=1) - out[1][1].sum(axis=1)  # the taps, as denoised
        kept[output] = np.abs(signal.sosfilt(band, change) if output == "dropin" else change)
    truth = np.abs(signal.sosfilt(band, tapped["contact"].sum(axis=1)))
    windows = [slice(o, o + 80) for o in tapped["onsets"][1:]]
    retention = {
        k: np.mean([v[w].max() / truth[w].max() for w in windows]) for k, v in kept.items()
    }
    assert retention["dropin"] > 0.8 * retention["bandpassed"] > 0.5, retention


def test_detection_calibration_stores_the_motion_it_held(model):
    """calibrate_detection keeps what the contact detector needs to know where the robot
    moves beyond its calibration: each joint's speeds (a margin past them) and the largest
    joint acceleration; the threshold's factor is the raw signal's threshold over the
    method's, none for the raw signal; a malformed field is refused naming it."""
    rec = recording(25.0, seed=1)
    arrays = rec["t"], rec["accel"], rec["tj"], rec["velocity"]
    calibrated, thresholds = calibrate_detection(model, *arrays)
    limits = motion_limits(calibrated, "hybrid")
    top = [np.abs(g).max() for g in calibrated.grid]
    low = rec["velocity"].min(axis=0) - MOTION_SPEED_MARGIN * np.array(top)
    assert limits.speed_low == pytest.approx(tuple(low))
    assert limits.accel == pytest.approx(joint_acceleration(rec["tj"], rec["velocity"]).max())
    assert limits.factor == pytest.approx(thresholds["raw"] / thresholds["hybrid"])
    assert limits.factor > 1.0
    assert motion_limits(calibrated, "raw") is None and motion_limits(model, "hybrid") is None
    broken = calibrated.replace(
        extras={**calibrated.extras, "detector.motion.speed_high": np.zeros(5)}
    )
    with pytest.raises(ModelFileError, match="detector.motion.speed_high"):
        motion_limits(broken, "hybrid")


@given(
    n_taps=st.sampled_from([3, 25, 49]),
    symmetric=st.booleans(),
    cuts=st.lists(st.integers(0, 4000), max_size=4),
    seed=st.integers(0, 2**16),
)
@example(n_taps=49, symmetric=False, cuts=[1023, 1024, 1025], seed=0)  # the FIRs' tile edges
@settings(max_examples=30)
def test_dropin_split_is_the_textbook_fir_and_gives_the_same_bits_in_any_chunking(
    n_taps, symmetric, cuts, seed
):
    """The drop-in split's FIRs (tiled, compiled) against np.convolve, and chunked against one
    call: low = the raw signal through the taps, high = the cleaned one late less its low."""
    rng = np.random.default_rng(seed)
    taps = rng.standard_normal(n_taps)
    delay = (n_taps - 1) // 2 if symmetric else n_taps // 4
    if symmetric:
        taps = (taps + taps[::-1]) / 2
    raw, cleaned = rng.standard_normal((2, 5000, 3))
    low, high = DropInSplit(taps, delay).process(raw, cleaned)

    def through(x):  # the history starts as the first sample held
        padded = np.concatenate([np.repeat(x[:1], n_taps - 1, axis=0), x])
        return np.stack([np.convolve(padded[:, c], taps, "valid") for c in range(3)], axis=1)

    late = np.concatenate([np.repeat(cleaned[:1], delay, axis=0), cleaned])[: len(cleaned)]
    np.testing.assert_allclose(low, through(raw), rtol=0, atol=1e-12)
    np.testing.assert_allclose(high, late - through(cleaned), rtol=0, atol=1e-12)
    chunked = DropInSplit(taps, delay)
    bounds = pairwise([0, *sorted(cuts), len(raw)])
    parts = [chunked.process(raw[a:b], cleaned[a:b]) for a, b in bounds]
    assert np.array_equal(np.concatenate([p[0] for p in parts]), low)
    assert np.array_equal(np.concatenate([p[1] for p in parts]), high)
