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
"""
from __future__ import annotations

import numpy as np

from egovib_ros.constants import BAG_TOPICS
from egovib_ros.core import NoiseModel
from egovib_ros.errors import BagError
from egovib_ros.evaluation import baselines, detection, metrics

PRIMARY = "paper"
CONTRACT_FIELDS = ("noise_mean_raw", "noise_mean_denoised", "noise_reduction_db", "tap_peak_raw",
                   "tap_peak_denoised", "tap_retention", "peak_snr_raw_db", "peak_snr_denoised_db",
                   "segsnr_contact_raw_db", "segsnr_contact_denoised_db", "f1_raw", "f1_denoised", "n_taps")


def require_ground_truth(rec, where: str = "recording") -> None:
    """Raise BagError unless `rec` carries the ground-truth contact signal."""
    if rec.contact is None:
        raise BagError(f"{where}: missing ground-truth topic {BAG_TOPICS['contact']} "
                       f"(evaluate needs a simulated bag with ground truth)")
    if len(rec.contact) != len(rec.accel):
        raise BagError(f"{where}: topic {BAG_TOPICS['contact']} has {len(rec.contact)} samples, "
                       f"{BAG_TOPICS['raw']} has {len(rec.accel)}")


def prepare_signals(rec, model: NoiseModel) -> dict:
    """Raw and reference signals and the contact segmentation of a recording."""
    require_ground_truth(rec)
    fs = model.sample_rate_hz
    raw = baselines.combined_bandpassed(rec.accel, model)
    reference = baselines.combined_bandpassed(rec.contact, model)
    seg = metrics.segment_contacts(reference, sample_rate_hz=fs)
    return {"raw": raw, "reference": reference, "seg": seg}


def evaluate_recording(rec, model: NoiseModel, *, calibration=None, model_short: NoiseModel | None = None,
                       methods: list[str] | None = None, keep_signals: bool = False,
                       pr_curves: bool = False) -> dict:
    """Metrics of every method on `rec` (a bagio.Recording with ground truth).

    calibration: a no-contact Recording (e.g. the calibration sweep or a no-contact
        motion segment) used for detection thresholds and the noisereduce noise clip.
    model_short: model calibrated with 32-sample blocks (enables "paper_L32").
    methods: subset of baselines.METHOD_LABELS (default: all that can run).
    keep_signals: also return the signals (key "signals", not JSON-serialisable).
    pr_curves: also return PR curves of the raw and each method's signal ("pr_curves").
    """
    fs = model.sample_rate_hz
    prepared = prepare_signals(rec, model)
    raw, reference, seg = prepared["raw"], prepared["reference"], prepared["seg"]
    noise_clip = baselines.combined_bandpassed(calibration.accel, model) if calibration is not None else None
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
        in_envelope = speed_envelope_mask(calibration, rec)
        if np.count_nonzero(cal_mask & in_envelope) >= fs:       # at least 1 s left
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
    raw_detection = detection.evaluate_detector(env(raw), truth, raw_threshold, sample_rate_hz=fs)
    pr2_magnitude = detection.pr2_magnitude(rec.accel, sample_rate_hz=fs)
    pr2 = {f"pr2_{t:g}ms2": detection.evaluate_detector(pr2_magnitude, truth, t, sample_rate_hz=fs)
           for t in detection.PR2_THRESHOLDS_MS2}
    minutes = len(raw) / fs / 60.0
    for scores in (raw_detection, *pr2.values()):
        scores["false_alarms_per_min"] = scores["fp"] / minutes

    per_method = {}
    for name in names:
        result = metrics.signal_metrics(raw, outputs[name], reference, seg)
        result["label"] = baselines.METHOD_LABELS[name]
        result["delay_ms"] = baselines.method_delay_ms(name, ctx)
        scores = detection.evaluate_detector(env(outputs[name]), truth, threshold_for(name), sample_rate_hz=fs)
        result.update({"f1": scores["f1"], "precision": scores["precision"], "recall": scores["recall"],
                       "threshold": scores["threshold"], "false_alarms": scores["fp"],
                       "false_alarms_per_min": scores["fp"] / minutes})
        per_method[name] = result

    if rec.denoised is not None and len(rec.denoised):
        per_method["bag_denoised"], outputs["bag_denoised"] = _bag_denoised(
            rec, raw, reference, seg, per_method, outputs, threshold_for, env, truth, fs, minutes)

    primary = per_method[PRIMARY]
    report = {field: primary[field] for field in CONTRACT_FIELDS if field in primary}
    report.update({
        "f1_raw": raw_detection["f1"],
        "f1_denoised": primary["f1"],
        "peak_snr_improvement_db": primary["peak_snr_improvement_db"],
        "delay_ms": primary["delay_ms"],
        "alignment_lag_samples": metrics.estimate_lag(reference, outputs[PRIMARY]) if seg.n_taps else None,
        "duration_s": len(raw) / fs,
        "threshold_source": "calibration data (no contact), at joint speeds within this run's envelope"
        if calibration is not None
        else "no-contact part of this recording (no calibration data given)",
        "detection": {"raw_bandpassed": raw_detection, **pr2,
                      "rule": {"envelope": f"causal RMS over {detection.ENVELOPE_S * 1e3:g} ms",
                               "refractory_s": detection.REFRACTORY_S, "tolerance_s": detection.TOLERANCE_S,
                               "threshold": f"{detection.CALIBRATION_MARGIN} x max envelope on calibration data"}},
        "methods": per_method,
    })
    if pr_curves:
        report["pr_curves"] = {"raw_bandpassed": detection.pr_curve(env(raw), truth, sample_rate_hz=fs),
                               **{name: detection.pr_curve(env(outputs[name]), truth, sample_rate_hz=fs)
                                  for name in names}}
    if keep_signals:
        report["signals"] = {"raw": raw, "reference": reference, "seg": seg, **outputs}
    return report


def _bag_denoised(rec, raw, reference, seg, per_method, outputs, threshold_for, env, truth, fs, minutes):
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
    scores = detection.evaluate_detector(env(signal), truth, threshold, sample_rate_hz=fs)
    result.update({"f1": scores["f1"], "precision": scores["precision"], "recall": scores["recall"],
                   "threshold": threshold, "false_alarms": scores["fp"],
                   "false_alarms_per_min": scores["fp"] / minutes,
                   "samples_missing": int(len(raw) - np.isin(rec.accel_stamps_ns, rec.denoised_stamps_ns).sum()),
                   "alignment_lag_samples": metrics.estimate_lag(reference, signal) if seg.n_taps else None})
    if like in outputs:
        batch = outputs[like]
        result["rms_difference_vs_batch"] = float(np.sqrt(np.mean((signal - batch) ** 2))
                                                  / max(np.sqrt(np.mean(batch ** 2)), 1e-300))
    return result, signal


def speed_envelope_mask(calibration, rec, margin: float = 1.05) -> np.ndarray:
    """Calibration accelerometer samples whose joint speeds stay within the largest joint
    speeds of `rec` (per joint, times `margin`)."""
    limit = np.nanmax(np.abs(rec.joint_velocity), axis=0) * margin
    mask = np.ones(len(calibration.accel_stamps_ns), bool)
    for j in range(calibration.joint_velocity.shape[1]):
        speed = np.interp(calibration.accel_stamps_ns, calibration.joint_stamps_ns,
                          np.abs(calibration.joint_velocity[:, j]))
        mask &= speed <= limit[j]
    return mask


def _edge_mask(n: int, fs: float) -> np.ndarray:
    """Drop the filter/denoiser start-up and flush at both ends of calibration data."""
    edge = min(int(metrics.EDGE_S * fs), n // 4)
    mask = np.ones(n, bool)
    mask[:edge] = False
    mask[n - edge:] = False
    return mask
