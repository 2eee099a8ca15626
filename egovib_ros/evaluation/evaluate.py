"""Evaluate denoising methods on one recording with ground truth (CONTRACT section 6).

`evaluate_recording(rec, model, ...)` returns the contract's JSON fields for the
paper's method at the top level, plus every method's metrics, delays, event
detection scores and the PR2 fixed-threshold comparison under "methods" and
"detection".

Signals compared (all combined + band-passed with the core's causal filter):
raw = the accelerometer topic; reference = the ground-truth contact topic;
each method's output on the input stamps (the core's output sample k carries
input stamp k; "alignment_lag_samples" re-checks it by cross-correlation).

Detection thresholds come from no-contact calibration data processed by the
same method (`calibration`): never from the test signal, unless no calibration
data is given, in which case the test's own no-contact samples are used and
"threshold_source" says so.

Bad samples (non-finite, or beyond the sensor range of the model's robot profile)
in the raw, ground-truth or recorded denoised signals are missing data: bridged so
that every method runs on finite input, and every sample they can have touched is
excluded from every metric (metrics.exclude_samples); they are counted under
"bad_samples". More than `max_bad_fraction` of them is an error (BagError).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from egovib_ros.constants import BAG_TOPICS
from egovib_ros.core import NoiseModel
from egovib_ros.errors import BagError
from egovib_ros.evaluation import baselines, detection, metrics

PRIMARY = "paper"
CONTRACT_FIELDS = (
    "noise_mean_raw",
    "noise_mean_denoised",
    "noise_reduction_db",
    "tap_peak_raw",
    "tap_peak_denoised",
    "tap_retention",
    "peak_snr_raw_db",
    "peak_snr_denoised_db",
    "segsnr_contact_raw_db",
    "segsnr_contact_denoised_db",
    "f1_raw",
    "f1_denoised",
    "n_taps",
)


def require_ground_truth(rec, where: str = "recording") -> None:
    """Raise BagError unless `rec` carries the ground-truth contact signal."""
    if rec.contact is None:
        raise BagError(
            f"{where}: missing ground-truth topic {BAG_TOPICS['contact']} "
            f"(evaluate needs a simulated bag with ground truth)"
        )
    if len(rec.contact) != len(rec.accel):
        raise BagError(
            f"{where}: topic {BAG_TOPICS['contact']} has {len(rec.contact)} samples, "
            f"{BAG_TOPICS['raw']} has {len(rec.accel)}"
        )


def sensor_range_of(model: NoiseModel) -> float:
    """+/- full scale of the model's sensor (its robot profile; inf if it states none)."""
    return float(model.profile.sensor_range)


def screen_recording(
    rec,
    model: NoiseModel,
    *,
    source: str = "recording",
    max_bad_fraction: float = metrics.MAX_BAD_FRACTION,
) -> tuple[object, np.ndarray, dict]:
    """(recording with bad samples bridged, (N,) bool bad accelerometer-stamp samples, counts).

    Bad: a raw sample non-finite or beyond the sensor range, a non-finite ground-truth
    contact sample, a non-finite recorded denoised sample. BagError naming `source` if
    more than `max_bad_fraction` of the samples are bad.
    """
    sensor_range = sensor_range_of(model)
    n = len(rec.accel)
    raw_bad, raw_nonfinite, raw_beyond = metrics.bad_samples(rec.accel, sensor_range)
    bad = raw_bad.copy()
    changes = {"accel": metrics.fill_missing(rec.accel, raw_bad)} if raw_bad.any() else {}
    contact_bad = np.zeros(n, bool)
    if rec.contact is not None and len(rec.contact) == n:
        contact_bad, _, _ = metrics.bad_samples(rec.contact)
        bad |= contact_bad
        if contact_bad.any():
            changes["contact"] = metrics.fill_missing(rec.contact, contact_bad)
    denoised_bad = 0
    if rec.denoised is not None and len(rec.denoised):
        row_bad, _, _ = metrics.bad_samples(rec.denoised)
        denoised_bad = int(row_bad.sum())
        if denoised_bad:
            on_input = np.isin(rec.accel_stamps_ns, rec.denoised_stamps_ns[row_bad])
            bad |= on_input
            changes["denoised"] = np.where(row_bad[:, None], 0.0, rec.denoised)
    joint_bad = int(np.count_nonzero(~np.all(np.isfinite(rec.joint_velocity), axis=1)))
    counts = {
        "raw_nonfinite": raw_nonfinite,
        "raw_beyond_range": raw_beyond,
        "contact_nonfinite": int(contact_bad.sum()),
        "denoised_nonfinite": denoised_bad,
        "joint_states_nonfinite": joint_bad,
        "samples": n,
        "bad": int(bad.sum()),
        "bad_fraction": float(bad.mean()) if n else 0.0,
        "max_bad_fraction": float(max_bad_fraction),
        "sensor_range": sensor_range,
    }
    if n and bad.mean() > max_bad_fraction:
        raise BagError(
            f"{source}: {int(bad.sum())} of {n} samples ({bad.mean():.1%}) are "
            f"non-finite or beyond the sensor range (+/-{sensor_range:g}); more than "
            f"{max_bad_fraction:.0%} bad: no metrics"
        )
    if n and bad.all():
        raise BagError(f"{source}: no valid sample")
    return (dataclasses.replace(rec, **changes) if changes else rec), bad, counts


def bad_samples_said(bad: dict) -> str:
    """The report's "bad_samples" as one line ('' if there were none)."""
    if not (bad["bad"] or bad.get("calibration_bad") or bad["joint_states_nonfinite"]):
        return ""
    calibration = f", {bad['calibration_bad']} calibration" if bad.get("calibration_bad") else ""
    return (
        f"{bad['bad']} bad samples of {bad['samples']} ({bad['bad_fraction']:.2%}) treated as "
        f"missing: {bad['raw_nonfinite']} non-finite and {bad['raw_beyond_range']} beyond "
        f"+/-{bad['sensor_range']:g} raw, {bad['contact_nonfinite']} ground truth, "
        f"{bad['denoised_nonfinite']} denoised{calibration}; "
        f"{bad['joint_states_nonfinite']} non-finite joint states; "
        f"{bad['excluded_samples']} samples and {bad['taps_excluded']} taps left out of the "
        f"metrics"
    )


def excluded_around(bad: np.ndarray, model: NoiseModel) -> np.ndarray:
    """Samples a run of bad input samples can have touched: every block that holds one
    of them (a block either side) and, after a bridged run, the band-pass settling: as
    long as the run, at most metrics.EDGE_S."""
    return metrics.exclusion_mask(
        bad,
        margin=int(model.block_length),
        settle_max=int(round(metrics.EDGE_S * model.sample_rate_hz)),
    )


def prepare_signals(rec, model: NoiseModel, excluded: np.ndarray | None = None) -> dict:
    """Raw and reference signals and the contact segmentation of a recording
    (without the `excluded` samples, see metrics.exclude_samples)."""
    require_ground_truth(rec)
    fs = model.sample_rate_hz
    raw = baselines.combined_bandpassed(rec.accel, model)
    reference = baselines.combined_bandpassed(rec.contact, model)
    seg = metrics.segment_contacts(reference, sample_rate_hz=fs)
    if excluded is not None:
        seg = metrics.exclude_samples(seg, excluded)
    return {"raw": raw, "reference": reference, "seg": seg}


def _score(
    envelope: np.ndarray,
    truth: np.ndarray,
    threshold: float,
    fs: float,
    excluded: np.ndarray | None,
) -> dict:
    """Event scores like detection.evaluate_detector, ignoring detections in `excluded`."""
    onsets = detection.detect_events(envelope, threshold, sample_rate_hz=fs)
    if excluded is not None and onsets.size:
        onsets = onsets[~excluded[onsets]]
    scores = detection.precision_recall_f1(onsets, truth, sample_rate_hz=fs)
    scores["threshold"] = float(threshold)
    return scores


def evaluate_recording(
    rec,
    model: NoiseModel,
    *,
    calibration=None,
    model_short: NoiseModel | None = None,
    methods: list[str] | None = None,
    keep_signals: bool = False,
    pr_curves: bool = False,
    source: str = "recording",
    calibration_source: str = "calibration recording",
    max_bad_fraction: float = metrics.MAX_BAD_FRACTION,
) -> dict:
    """Metrics of every method on `rec` (a bagio.Recording with ground truth).

    calibration: a no-contact Recording (e.g. the calibration sweep or a no-contact
        motion segment) used for detection thresholds and the noisereduce noise clip.
    model_short: model calibrated with 32-sample blocks (enables "paper_L32").
    methods: subset of baselines.METHOD_LABELS (default: all that can run).
    keep_signals: also return the signals (key "signals", not JSON-serialisable).
    pr_curves: also return PR curves of the raw and each method's signal ("pr_curves").
    source, calibration_source: names for errors; max_bad_fraction: see screen_recording.
    """
    fs = model.sample_rate_hz
    require_ground_truth(rec, where=source)
    rec, bad, bad_counts = screen_recording(
        rec, model, source=source, max_bad_fraction=max_bad_fraction
    )
    excluded = excluded_around(bad, model) if bad.any() else None
    prepared = prepare_signals(rec, model, excluded)
    raw, reference, seg = prepared["raw"], prepared["reference"], prepared["seg"]
    excluded = seg.excluded_mask  # now also the windows of the taps it dropped
    cal_excluded = None
    if calibration is not None:
        calibration, cal_bad, cal_counts = screen_recording(
            dataclasses.replace(calibration, contact=None, denoised=None),
            model,
            source=calibration_source,
            max_bad_fraction=max_bad_fraction,
        )
        bad_counts["calibration_bad"] = cal_counts["bad"]
        cal_excluded = excluded_around(cal_bad, model) if cal_bad.any() else None
    noise_clip = (
        baselines.combined_bandpassed(calibration.accel, model) if calibration is not None else None
    )
    ctx = baselines.MethodContext(model=model, model_short=model_short, noise_clip=noise_clip)
    names = methods or baselines.available_methods(ctx)
    if PRIMARY not in names:
        names = [PRIMARY] + list(names)

    def env(x: np.ndarray) -> np.ndarray:
        return detection.envelope(x, sample_rate_hz=fs)

    cal_mask = None
    if calibration is not None:
        # Only the calibration samples recorded at joint speeds the test run reaches: a
        # sweep's full-speed cells would set the threshold for a slow run (joint states only,
        # never the test accelerometer signal).
        cal_mask = _edge_mask(len(calibration.accel_stamps_ns), fs)
        if cal_excluded is not None:
            cal_mask &= ~cal_excluded
        in_envelope = speed_envelope_mask(calibration, rec)
        if np.count_nonzero(cal_mask & in_envelope) >= fs:  # at least 1 s left
            cal_mask &= in_envelope

    def threshold_for(name: str | None) -> float:
        """Detection threshold of the raw signal (name None) or of a method's output."""
        if calibration is not None:
            cal = noise_clip if name is None else baselines.run_method(name, calibration, ctx)
            return detection.threshold_from_calibration(env(cal)[cal_mask])
        signal = raw if name is None else outputs[name]
        return detection.threshold_from_calibration(env(signal)[seg.no_contact_mask])

    outputs: dict[str, np.ndarray] = {}
    for name in names:
        outputs[name] = baselines.run_method(name, rec, ctx)
    truth = seg.onsets
    raw_threshold = threshold_for(None)
    raw_detection = _score(env(raw), truth, raw_threshold, fs, excluded)
    pr2_magnitude = detection.pr2_magnitude(rec.accel, sample_rate_hz=fs)
    pr2 = {
        f"pr2_{t:g}ms2": _score(pr2_magnitude, truth, t, fs, excluded)
        for t in detection.PR2_THRESHOLDS_MS2
    }
    minutes = (len(raw) - (int(excluded.sum()) if excluded is not None else 0)) / fs / 60.0
    for scores in (raw_detection, *pr2.values()):
        scores["false_alarms_per_min"] = scores["fp"] / minutes

    per_method = {}
    for name in names:
        result = metrics.signal_metrics(raw, outputs[name], reference, seg)
        result["label"] = baselines.METHOD_LABELS[name]
        result["delay_ms"] = baselines.method_delay_ms(name, ctx)
        scores = _score(env(outputs[name]), truth, threshold_for(name), fs, excluded)
        result.update(
            {
                "f1": scores["f1"],
                "precision": scores["precision"],
                "recall": scores["recall"],
                "threshold": scores["threshold"],
                "false_alarms": scores["fp"],
                "false_alarms_per_min": scores["fp"] / minutes,
            }
        )
        per_method[name] = result

    if rec.denoised is not None and len(rec.denoised):
        per_method["bag_denoised"], outputs["bag_denoised"] = _bag_denoised(
            rec,
            raw,
            reference,
            seg,
            per_method,
            outputs,
            threshold_for,
            env,
            truth,
            fs,
            minutes,
            excluded,
        )

    primary = per_method[PRIMARY]
    report = {field: primary[field] for field in CONTRACT_FIELDS if field in primary}
    report.update(
        {
            "f1_raw": raw_detection["f1"],
            "f1_denoised": primary["f1"],
            "peak_snr_improvement_db": primary["peak_snr_improvement_db"],
            "delay_ms": primary["delay_ms"],
            "alignment_lag_samples": metrics.estimate_lag(reference, outputs[PRIMARY])
            if seg.n_taps
            else None,
            "duration_s": len(raw) / fs,
            "bad_samples": {
                **bad_counts,
                "excluded_samples": int(excluded.sum()) if excluded is not None else 0,
                "taps_excluded": seg.n_taps_excluded,
                "rule": "non-finite or beyond the sensor range: missing data, bridged "
                "for the filters; the blocks around them and the band-pass "
                "settling after them are left out of every metric, and so is "
                "any tap they touch",
            },
            "threshold_source": (
                "calibration data (no contact), at joint speeds within this run's envelope"
                if calibration is not None
                else "no-contact part of this recording (no calibration data given)"
            ),
            "detection": {
                "raw_bandpassed": raw_detection,
                **pr2,
                "rule": {
                    "envelope": f"causal RMS over {detection.ENVELOPE_S * 1e3:g} ms",
                    "refractory_s": detection.REFRACTORY_S,
                    "tolerance_s": detection.TOLERANCE_S,
                    "threshold": (
                        f"{detection.CALIBRATION_MARGIN} x max envelope on calibration data"
                    ),
                },
            },
            "methods": per_method,
        }
    )
    if pr_curves:

        def env_kept(x: np.ndarray) -> np.ndarray:  # no detection where bad input was
            return env(x) if excluded is None else np.where(excluded, 0.0, env(x))

        report["pr_curves"] = {
            "raw_bandpassed": detection.pr_curve(env_kept(raw), truth, sample_rate_hz=fs),
            **{
                name: detection.pr_curve(env_kept(outputs[name]), truth, sample_rate_hz=fs)
                for name in names
            },
        }
    if keep_signals:
        report["signals"] = {"raw": raw, "reference": reference, "seg": seg, **outputs}
    return report


def _bag_denoised(
    rec,
    raw,
    reference,
    seg,
    per_method,
    outputs,
    threshold_for,
    env,
    truth,
    fs,
    minutes,
    excluded=None,
):
    """Metrics of the bag's own /accelerometer/denoised (e.g. recorded from the live node).

    Its layout tells which method produced it: y = z = 0 is the combined (paper)
    pipeline, anything else per-axis output; that method's calibrated threshold and
    batch output are used for detection and for the node-vs-batch comparison.
    """
    signal = baselines.on_input_stamps(rec.denoised_stamps_ns, rec.denoised, rec.accel_stamps_ns)
    like = "paper" if not np.any(rec.denoised[:, 1:]) else "per_axis"
    result = metrics.signal_metrics(raw, signal, reference, seg)
    result["label"] = f"from bag: {BAG_TOPICS['denoised']} (like {like})"
    result["delay_ms"] = None
    threshold = per_method[like]["threshold"] if like in per_method else threshold_for(like)
    scores = _score(env(signal), truth, threshold, fs, excluded)
    result.update(
        {
            "f1": scores["f1"],
            "precision": scores["precision"],
            "recall": scores["recall"],
            "threshold": threshold,
            "false_alarms": scores["fp"],
            "false_alarms_per_min": scores["fp"] / minutes,
            "samples_missing": int(
                len(raw) - np.isin(rec.accel_stamps_ns, rec.denoised_stamps_ns).sum()
            ),
            "alignment_lag_samples": metrics.estimate_lag(reference, signal)
            if seg.n_taps
            else None,
        }
    )
    if like in outputs:
        keep = slice(None) if excluded is None else ~excluded
        batch, own = outputs[like][keep], signal[keep]
        result["rms_difference_vs_batch"] = float(
            np.sqrt(np.mean((own - batch) ** 2)) / max(np.sqrt(np.mean(batch**2)), 1e-300)
        )
    return result, signal


def speed_envelope_mask(calibration, rec, margin: float = 1.05) -> np.ndarray:
    """Calibration accelerometer samples whose joint speeds stay within the largest joint
    speeds of `rec` (per joint, times `margin`)."""
    limit = np.nanmax(np.abs(rec.joint_velocity), axis=0) * margin
    mask = np.ones(len(calibration.accel_stamps_ns), bool)
    for j in range(calibration.joint_velocity.shape[1]):
        speed = np.interp(
            calibration.accel_stamps_ns,
            calibration.joint_stamps_ns,
            np.abs(calibration.joint_velocity[:, j]),
        )
        mask &= speed <= limit[j]
    return mask


def _edge_mask(n: int, fs: float) -> np.ndarray:
    """Drop the filter/denoiser start-up and flush at both ends of calibration data."""
    edge = min(int(metrics.EDGE_S * fs), n // 4)
    mask = np.ones(n, bool)
    mask[:edge] = False
    mask[n - edge :] = False
    return mask
