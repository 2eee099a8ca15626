"""The streaming evaluation (evaluation/stream.py): each accumulator equals its whole-array
definition under any chunking; a bag evaluated in any slicing gives the whole-array report;
several bags in parallel, with a corrupt one among them."""

import dataclasses
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy import signal

from egovib_research.experiments import scoring
from egovib_ros.bag import concat_recordings, iter_recording, read_recording, write_recording
from egovib_ros.cli import main
from egovib_ros.core import calibrate_arrays, denoise_batch
from egovib_ros.evaluation import baselines, detection, metrics
from egovib_ros.evaluation import evaluate as evaluate_module
from egovib_ros.evaluation.evaluate import evaluate_bag, evaluate_recording
from egovib_ros.evaluation.stream import Screen
from egovib_ros.sim import simulate_motion, simulate_sweep

FS = 3000.0


def chunks(n: int, rng, sizes=(1, 7, 64, 500, 3001)) -> list[slice]:
    """Random consecutive slices covering range(n), of very different sizes."""
    out, start = [], 0
    while start < n:
        stop = min(n, start + int(rng.choice(sizes)) + int(rng.integers(0, 3)))
        out.append(slice(start, stop))
        start = stop
    return out


def exclusion_mask(bad: np.ndarray, *, margin: int, settle_max: int) -> np.ndarray:
    """Each run [a, b) of `bad` widened to [a - margin, b + margin + min(b - a, settle_max))."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], bad.astype(np.int8), [0]))))
    out = np.zeros(bad.size, bool)
    for a, b in edges.reshape(-1, 2):
        out[max(a - margin, 0) : b + margin + min(b - a, settle_max)] = True
    return out


def estimate_lag(reference: np.ndarray, x: np.ndarray, *, max_lag: int = 96) -> int:
    """Lag (samples, positive: `x` late) maximising the cross-correlation."""
    corr = signal.correlate(x, reference, mode="full", method="fft")
    lags = signal.correlation_lags(x.size, reference.size, mode="full")
    keep = np.abs(lags) <= max_lag
    return int(lags[keep][np.argmax(corr[keep])])


def fill_missing(values: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """`values` with bad rows linearly bridged from the good ones either side (held at the
    ends)."""
    values = np.array(values, float)
    good, missing = np.flatnonzero(~bad), np.flatnonzero(bad)
    for column in range(values.shape[1]):
        values[missing, column] = np.interp(missing, good, values[good, column])
    return values


def bursty(rng, n: int) -> np.ndarray:
    """Noise with decaying bursts (tap-like events), some close together."""
    x = rng.normal(scale=0.2, size=n)
    for onset in rng.choice(n - 400, size=25, replace=False):
        x[onset : onset + 300] += 3.0 * rng.uniform(0.3, 1) * np.exp(-np.arange(300) / 60.0)
    return np.abs(x)


# --------------------------------------------------------------------------
# Accumulators against their whole-array definitions
# --------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_event_detector_and_matcher_equal_whole_array(seed):
    rng = np.random.default_rng(seed)
    magnitude = bursty(rng, 30_000)
    magnitude[12_000:14_000] = 2.0 + rng.uniform(size=2000)  # one long event
    truth = np.sort(rng.choice(30_000, size=40, replace=False))
    for threshold in (0.6, 1.2):
        onsets = scoring.detect_events(magnitude, threshold, sample_rate_hz=FS)
        expected = scoring.precision_recall_f1(onsets, truth, sample_rate_hz=FS)
        detector = detection.EventDetector(threshold, sample_rate_hz=FS)
        matcher = detection.EventMatcher(sample_rate_hz=FS)
        got, added = [], 0
        for part in chunks(len(magnitude), rng):
            detector.push(magnitude[part])
            new = detector.take()
            got += list(new)
            # truth arrives in order too, only up to what has been read
            upto = np.searchsorted(truth, part.stop)
            matcher.add(detected=new, truth=truth[added:upto])
            added = upto
            matcher.advance(min(detector.horizon, part.stop))
        detector.finish()
        last = detector.take()
        matcher.add(detected=last, truth=truth[added:])
        matcher.finish()
        np.testing.assert_array_equal(np.array(got + list(last)), onsets)
        assert matcher.scores() == expected


def test_contact_segmenter_and_exclusion_equal_whole_array():
    rng = np.random.default_rng(3)
    n = 40_000
    reference = np.zeros(n)
    for onset in rng.choice(n - 600, size=30, replace=False):
        length = int(rng.integers(20, 400))
        reference[onset : onset + length] += rng.normal(size=length)
    level = metrics.activity_threshold(reference)
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    segmenter = metrics.ContactSegmenter(level=level, n=n, sample_rate_hz=FS)
    bad = np.zeros(n, bool)
    for start in rng.choice(n - 50, size=8, replace=False):
        bad[start : start + int(rng.integers(1, 40))] = True
    bad[-3:] = True  # a run open at the end
    exclusion = metrics.BadRunExclusion(margin=64, settle_max=300, n=n)
    for part in chunks(n, rng):
        segmenter.push(reference[part])
        exclusion.push(bad[part])
    segmenter.finish()
    exclusion.finish()
    taps = segmenter.take_new()
    np.testing.assert_array_equal([t.start for t in taps], seg.onsets)
    np.testing.assert_array_equal([[t.window_start, t.window_stop] for t in taps], seg.tap_windows)
    expected = exclusion_mask(bad, margin=64, settle_max=300)
    np.testing.assert_array_equal(exclusion.mask(0, n), expected)
    assert exclusion.bad == bad.sum()


def test_top_values_quantile_and_lag_correlation_equal_whole_array():
    rng = np.random.default_rng(4)
    values = np.abs(rng.standard_cauchy(size=20_001))
    top = metrics.TopValues.for_quantile(metrics.SPIKE_QUANTILE, len(values))
    reference = rng.normal(size=5000)
    late = np.concatenate([np.zeros(3), reference[:-3]]) + 0.1 * rng.normal(size=5000)
    lag = metrics.LagCorrelation()
    for part in chunks(len(values), rng):
        top.push(values[part])
    for part in chunks(len(reference), rng):
        lag.push(reference[part], late[part])
    assert len(top.values) < 30
    for q in (metrics.SPIKE_QUANTILE, 0.9995, 1.0):
        assert top.quantile(q) == np.quantile(values, q)
    assert lag.lag() == estimate_lag(reference, late) == 3


def test_stationary_gate_is_noisereduce_in_any_chunking():
    noisereduce = pytest.importorskip("noisereduce")
    rng = np.random.default_rng(5)
    noise = rng.normal(size=12_000)
    x = bursty(rng, 9001) * rng.choice([-1, 1], size=9001)
    expected = noisereduce.reduce_noise(
        y=x,
        sr=3000,
        stationary=True,
        y_noise=noise,
        n_fft=64,
        freq_mask_smooth_hz=None,
        time_mask_smooth_ms=None,
    )
    threshold = baselines.gate_threshold(noise)
    gate = baselines.StationaryGate()  # the threshold comes after the first input
    out = [gate.push(x[:2000]), gate.set_threshold(threshold)]
    for part in chunks(len(x) - 2000, rng):
        out.append(gate.push(x[2000:][part]))
    out.append(gate.finish())
    np.testing.assert_allclose(np.concatenate(out), expected, rtol=0, atol=1e-12)


def test_screen_bridges_bad_samples_as_fill_missing():
    rng = np.random.default_rng(6)
    values = rng.normal(size=(5000, 3))
    values[:5] = np.nan  # at the start: held
    values[1000:1300, 1] = np.inf
    values[2000, 0] = 99.0  # beyond the range
    values[-7:] = np.nan  # at the end: held
    bad, _, _ = metrics.bad_samples(values, 10.0)
    screen = Screen([10.0])
    got_values, got_bad = [], []
    for part in chunks(len(values), rng):
        _, filled, flags = screen.push(np.arange(part.start, part.stop), values[part])
        got_values += filled
        got_bad += flags
    _, filled, flags = screen.finish()
    np.testing.assert_array_equal(np.concatenate(got_values + filled), fill_missing(values, bad))
    np.testing.assert_array_equal(np.concatenate(got_bad + flags), bad)


# --------------------------------------------------------------------------
# A bag in any slicing gives the whole-array report
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A model, a 15 s motion bag with taps, bad samples and its own denoised topic (with a
    few messages missing and one non-finite), and a no-contact calibration bag."""
    root = tmp_path_factory.mktemp("evaluate_stream")
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=0.6, settle_s=0.3, seed=31)
    model, _ = calibrate_arrays(
        sweep.sensor_stamps_ns,
        sweep.sensor,
        sweep.joint_stamps_ns,
        sweep.joint_velocity,
        sweep="superposition",
        source="test sweep",
    )
    model.save(root / "model.npz")
    rec, _ = simulate_motion(duration_s=15.0, max_speed=0.5, tap_rate_hz=2.0, seed=32)
    accel = rec.sensor.copy()
    accel[int(4.2 * FS) : int(4.25 * FS)] = np.nan  # a burst inside or near a tap
    accel[int(9 * FS), 2] = 1e3  # beyond the sensor range
    stamps, values, _ = denoise_batch(
        rec.sensor_stamps_ns, accel, rec.joint_stamps_ns, rec.joint_velocity, model
    )
    keep = np.ones(len(stamps), bool)
    keep[5000:5010] = False  # a few samples without a denoised message
    values = values.copy()
    values[7000] = np.nan
    rec = dataclasses.replace(
        rec, sensor=accel, ego=None, denoised_stamps_ns=stamps[keep], denoised=values[keep]
    )
    write_recording(root / "motion", rec, chunk_bytes=200_000, window_s=0.25)
    quiet, _ = simulate_motion(duration_s=6.0, max_speed=0.5, tap_rate_hz=0.0, seed=33)
    write_recording(root / "quiet", dataclasses.replace(quiet, contact=None, ego=None))
    return {"root": root, "model": model, "bag": root / "motion", "quiet": root / "quiet"}


def assert_same_report(got: dict, expected: dict, rtol: float = 1e-9, path: str = "") -> None:
    assert set(got) == set(expected), path
    for key, value in expected.items():
        where = f"{path}.{key}"
        if isinstance(value, dict):
            assert_same_report(got[key], value, rtol, where)
        elif isinstance(value, float) and value is not None:
            assert got[key] == pytest.approx(value, rel=rtol, abs=0), where
        else:
            assert got[key] == value, where


def whole_array_report(lab, calibration: bool) -> dict:
    profile = lab["model"].profile
    rec = read_recording(lab["bag"], profile=profile)
    cal = read_recording(lab["quiet"], profile=profile, ground_truth=False, denoised=False)
    report = evaluate_recording(
        rec, lab["model"], calibration=cal if calibration else None, source=str(lab["bag"])
    )
    return metrics.json_safe(report)


def rechunk(pieces, samples: int):
    """The same recording in slices of `samples` sensor samples (the last one shorter).
    Joint states and denoised messages go with the first slice cut after they arrived
    (ahead of their samples, as the streaming consumers allow)."""
    held, held_n = [], 0
    for piece in pieces:
        held.append(piece)
        held_n += len(piece.sensor_stamps_ns)
        while held_n >= samples:
            whole = concat_recordings(held)
            yield _cut(whole, 0, samples, first=True)
            rest = _cut(whole, samples, len(whole.sensor_stamps_ns), first=False)
            held, held_n = [rest], len(rest.sensor_stamps_ns)
    if held:
        yield concat_recordings(held)


def _cut(rec, a: int, b: int, *, first: bool):
    changes = {
        "sensor_stamps_ns": rec.sensor_stamps_ns[a:b],
        "sensor": rec.sensor[a:b],
        "contact": None if rec.contact is None else rec.contact[a:b],
        "ego": None if rec.ego is None else rec.ego[a:b],
    }
    if not first:
        width = rec.joint_velocity.shape[1]
        changes.update(
            joint_stamps_ns=rec.joint_stamps_ns[:0],
            joint_position=np.zeros((0, width)),
            joint_velocity=np.zeros((0, width)),
            denoised_stamps_ns=None,
            denoised=None,
            command_stamps_ns=None,
            commands=None,
        )
    return dataclasses.replace(rec, **changes)


def sliced_report(lab, chunk_s: float, calibration: bool, monkeypatch) -> dict:
    """evaluate_bag's report with its bag reader's slices cut to `chunk_s` seconds."""
    opened = []

    def sliced(*args, **options):
        opened.append(args[0])
        return rechunk(iter_recording(*args, **options), round(chunk_s * FS))

    with monkeypatch.context() as patch:
        patch.setattr(evaluate_module, "iter_recording", sliced)
        quiet = lab["quiet"] if calibration else None
        report = evaluate_bag(lab["bag"], model=lab["model"], calibration=quiet)
    assert lab["bag"] in opened and (quiet is None or quiet in opened)  # read sliced
    return report


def test_any_slicing_gives_the_whole_array_report(lab, monkeypatch):
    expected = whole_array_report(lab, calibration=True)
    bad = expected["bad_samples"]
    assert bad["raw_nonfinite"] == 150 and bad["raw_beyond_range"] == 1
    assert bad["denoised_nonfinite"] == 1 and bad["excluded_samples"] > 150
    # the 151 bad samples (the core drops them) and the 10 messages left out
    assert expected["methods"]["bag_denoised"]["samples_missing"] == 161
    assert set(expected["methods"]) >= {"paper", "noisereduce", "wiener", "bag_denoised"}
    assert expected["n_taps"] > 20
    report = evaluate_bag(lab["bag"], model=lab["model"], calibration=lab["quiet"])
    assert_same_report(metrics.json_safe(report), expected)  # the bag's own slices
    for chunk_s in (1.0, 7.3, 1e6):  # 1 s, 7.3 s, the whole bag
        report = sliced_report(lab, chunk_s, calibration=True, monkeypatch=monkeypatch)
        assert_same_report(metrics.json_safe(report), expected)


def test_without_calibration_any_slicing_gives_the_whole_array_report(lab, monkeypatch):
    expected = whole_array_report(lab, calibration=False)
    assert expected["threshold_source"].startswith("no-contact part")
    report = sliced_report(lab, 0.7, calibration=False, monkeypatch=monkeypatch)
    assert_same_report(metrics.json_safe(report), expected)


def test_rechunk_keeps_every_sample_in_order(lab):
    pieces = list(rechunk([read_recording(lab["bag"], profile=lab["model"].profile)], 4000))
    assert [len(p.sensor_stamps_ns) for p in pieces] == [4000] * 11 + [1000]
    assert sum(len(p.joint_stamps_ns) for p in pieces) == len(pieces[0].joint_stamps_ns)


# --------------------------------------------------------------------------
# Several bags
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet(lab):
    """Three short bags in a directory tree and one cut before its first complete chunk
    (nothing to read: refused; a bag cut later is read up to the cut, test_faults)."""
    root = lab["root"] / "fleet"
    for seed in range(3):
        rec, _ = simulate_motion(duration_s=4.0, max_speed=0.5, tap_rate_hz=2.0, seed=40 + seed)
        write_recording(root / ("day1" if seed < 2 else "day2") / f"run{seed}", rec)
    broken = root / "day2" / "broken"
    shutil.copytree(root / "day1" / "run0", broken)
    mcap = next(broken.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:5000])
    return root


GOOD = ("day1/run0", "day1/run1", "day2/run2")


def test_several_bags_one_json_each_the_broken_one_named_and_jobs_2_the_same(
    lab, fleet, tmp_path, capsys
):
    common = ["--model", str(lab["root"] / "model.npz"), "--calibration", str(lab["quiet"])]
    common += ["--methods", "default,paper"]  # (which methods: test_cli_evaluate)
    singles = {}
    for name in GOOD:
        out = tmp_path / "single" / f"{name}.json"
        assert main(["evaluate", str(fleet / name), *common, "--json", str(out), "--quiet"]) == 0
        singles[name] = json.loads(out.read_text())
    out = tmp_path / "all"
    assert main(["evaluate", str(fleet), *common, "--json", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "FAILED" in err and "day2/broken" in err and "4 bag(s): 3 done, 1 failed" in err
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*.json")) == [
        f"{name}.json" for name in GOOD
    ]
    assert not list(out.rglob("*.partial"))
    for name in GOOD:
        assert json.loads((out / f"{name}.json").read_text()) == singles[name]
    # a second run replaces them only with --force
    assert main(["evaluate", str(fleet), *common, "--json", str(out), "--quiet"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["evaluate", str(fleet), *common, "--json", str(out), "--quiet", "--force"]) == 2
    for name in GOOD:
        assert json.loads((out / f"{name}.json").read_text()) == singles[name]
    # several inputs, --jobs 2 (worker processes, from the console entry point): the same
    # reports, byte for byte, as one at a time
    jobs2 = tmp_path / "jobs2"
    result = subprocess.run(
        [sys.executable, "-m", "egovib_ros.cli", "evaluate", fleet / "day1", fleet / "day2"]
        + [*common, "--json", jobs2, "--quiet", "--jobs", "2"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, result.stderr
    assert "broken" in result.stderr and "3 done, 1 failed" in result.stderr
    for name in GOOD:
        one = (out / f"{name}.json").read_text()
        assert (jobs2 / f"{name.split('/')[1]}.json").read_text() == one, name


def test_the_summary_counts_unusable_joint_states_as_the_framers_drop_them():
    """A driver stamping every joint state zero is refused (more than 10 % unusable); a
    joint clock that restarts (a bag loop, 60 s back) is a restart, as the framers take it,
    not a thousand late stamps; in one slice or in ten alike."""
    from egovib_ros.errors import BagError
    from egovib_ros.evaluation.stream import SummaryPass

    motion, _ = simulate_motion(duration_s=2.0, max_speed=0.5, tap_rate_hz=1.0, seed=4)
    model, _ = calibrate_arrays(
        motion.sensor_stamps_ns, motion.sensor, motion.joint_stamps_ns, motion.joint_velocity
    )
    n, m = len(motion.sensor_stamps_ns), len(motion.joint_stamps_ns)
    looped = motion.joint_stamps_ns.copy()
    looped[m // 2 :] -= 60 * 10**9
    for stamps, unusable in ((looped, 0), (np.zeros_like(looped), m - 1)):
        for slices in (1, 10):
            summary = SummaryPass(model, source="run")
            for k in range(slices):
                a, b = k * n // slices, (k + 1) * n // slices
                c, d = k * m // slices, (k + 1) * m // slices
                summary.push(
                    dataclasses.replace(
                        motion,
                        sensor_stamps_ns=motion.sensor_stamps_ns[a:b],
                        sensor=motion.sensor[a:b],
                        contact=motion.contact[a:b],
                        ego=None,
                        joint_stamps_ns=stamps[c:d],
                        joint_position=motion.joint_position[c:d],
                        joint_velocity=motion.joint_velocity[c:d],
                    )
                )
            assert summary.joint_states_unusable == unusable
            if unusable:
                with pytest.raises(BagError, match="run: /joint_states: .* joint states"):
                    summary.finish()
            else:
                summary.finish()
