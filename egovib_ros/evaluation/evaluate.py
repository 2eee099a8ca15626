"""Evaluate denoising methods on one recording with ground truth (INTERFACES.md section 6).

`evaluate_bag(bag, model=...)` streams a bag (any length, flat memory);
`evaluate_recording(rec, model, ...)` takes whole arrays (figures, experiments, demo).
Both push the recording through the same streaming evaluation (evaluation/stream.py) and
return the contract's JSON fields for the default method at the top level, plus every
method's metrics, delays, event detection scores and the PR2 fixed-threshold comparison
under "methods" and "detection".

Signals compared (all combined + band-passed with the core's causal filter): raw = the
sensor topic; reference = the ground-truth contact topic; each method's output on the
input stamps ("alignment_lag_samples" re-checks by cross-correlation that output k
carries input stamp k). Detection thresholds come from no-contact calibration data
processed by the same method: never from the test signal, unless no calibration data is
given ("threshold_source" says so). Bad samples are counted under "bad_samples" and left
out of every metric (evaluation/metrics.py); more than `max_bad_fraction` of them is an
error (BagError).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterable

from egovib_ros.bag import iter_recording
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.core import NoiseModel, contact
from egovib_ros.core.methods import default_method, with_motion
from egovib_ros.errors import BagError
from egovib_ros.evaluation import baselines, detection, metrics
from egovib_ros.evaluation import stream as streaming
from egovib_ros.evaluation.stream import require_ground_truth

PRIMARY = "default"  # the figures at the top: what a user gets without options
REPORT_FIELDS = (
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
#: More of the run than this left out of the metrics around bad samples: no metrics (5 %
#: of the samples bad, scattered, left 34 of 40000 samples to measure).
MAX_EXCLUDED_FRACTION = 0.5
BAD_SAMPLE_RULE = (
    "non-finite or beyond the sensor range: missing data, bridged "
    "for the filters; the blocks around them and the band-pass "
    "settling after them are left out of every metric, and so is "
    "any tap they touch"
)


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


def evaluate_pieces(
    open_run: Callable[[], Iterable],
    model: NoiseModel,
    *,
    open_calibration: Callable[[], Iterable] | None = None,
    model_short: NoiseModel | None = None,
    methods: list[str] | None = None,
    keep_signals: bool = False,
    source: str = "recording",
    calibration_source: str = "calibration recording",
    max_bad_fraction: float = metrics.MAX_BAD_FRACTION,
    adapt=None,
) -> dict:
    """The evaluation of a recording given as time slices: `open_run()` (and
    `open_calibration()`) return a fresh iterable of its Recording slices each time they
    are called (once per pass, see evaluation/stream.py). Returns the report. `adapt`
    (core.adapt.AdaptSettings): the methods that can (the default, cancel, hybrid) adapt
    their model online, in every pass afresh from the model."""
    names = streaming.method_names(
        methods, calibration=open_calibration is not None, model_short=model_short, model=model
    )
    summary = _through(
        streaming.SummaryPass(model, source=source, max_bad_fraction=max_bad_fraction), open_run()
    )
    like = summary.recorded_like
    extra = [like] if like is not None and like not in names else []
    gate, calibration_bad = None, None
    common = dict(names=names, summary=summary, model_short=model_short, source=source)
    if open_calibration is not None:
        calibration = streaming.CalibrationPass(
            model,
            names=names + extra,
            model_short=model_short,
            source=calibration_source,
            max_bad_fraction=max_bad_fraction,
            adapt=adapt,
        )
        result = _through(calibration, open_calibration())
        thresholds, gate, calibration_bad = result.thresholds, result.gate, result.bad
        # the detector's motion limits: those of the data its thresholds came from
        common["limits_model"] = with_motion(model, *result.joints)
    else:
        own = streaming.EvaluationPass(model, thresholds=None, extra=extra, adapt=adapt, **common)
        _through(own, open_run())
        thresholds = own.noise_thresholds()
    if like is not None:
        thresholds["bag_denoised"] = thresholds[like]
    run = streaming.EvaluationPass(
        model, thresholds=thresholds, gate=gate, keep_signals=keep_signals, adapt=adapt, **common
    )
    _through(run, open_run())
    if run.n and run.excluded > MAX_EXCLUDED_FRACTION * run.n:
        raise BagError(
            f"{source}: {run.excluded} of {run.n} samples ({run.excluded / run.n:.0%}) are left "
            f"out of the metrics around its {summary.counts['bad']} bad samples (each takes the "
            f"blocks around it and the band-pass's settling after it): too little left to "
            f"measure; more than {MAX_EXCLUDED_FRACTION:.0%} is refused"
        )
    report = _report(run, model, names=names, calibration_bad=calibration_bad)
    if keep_signals:
        report["signals"] = run.signals()
    report["adapt"] = None if adapt is None else dict(vars(adapt))
    for name, stream in run.streams.items():
        stats = getattr(getattr(stream, "denoiser", None), "adaptation_stats", None)
        if stats is not None and name in report["methods"]:
            report["methods"][name]["adapt"] = stats.as_dict()
    return report


def _through(stage, pieces: Iterable):
    """Push every slice through a pass; its finish()."""
    for piece in pieces:
        stage.push(piece)
    return stage.finish()


def _detector_scores(run: streaming.EvaluationPass, key: str, minutes: float) -> dict:
    scores = run.scores(key)
    scores["false_alarms_per_min"] = scores["fp"] / minutes if minutes else float("nan")
    return scores


def _method_result(run: streaming.EvaluationPass, key: str, label: str, delay, minutes) -> dict:
    result = run.signal_metrics(key)
    result["label"] = label
    result["delay_ms"] = delay
    scores = _detector_scores(run, key, minutes)
    result.update({name: scores[name] for name in ("f1", "precision", "recall", "threshold")})
    result["false_alarms"] = scores["fp"]
    result["false_alarms_per_min"] = scores["false_alarms_per_min"]
    return result


#: The detection rule, in words, for the report.
DETECTION_RULE = {
    "detector": "core.contact.ContactDetector (egovib detect, contact_detector)",
    "envelope": f"causal RMS over {contact.ENVELOPE_S * 1e3:g} ms",
    "refractory_s": contact.REFRACTORY_S,
    "onset": f"first sample at {contact.ONSET_FRACTION:g} of the peak within 10 ms of the crossing",
    "tolerance_s": detection.TOLERANCE_S,
    "threshold": (
        f"{contact.THRESHOLD_MARGIN} x the no-contact envelope's level exceeded "
        f"{contact.BURST_S * 1e3:g} ms a minute "
        f"({contact.FALSE_ALARMS_PER_MIN:g} false alarm a minute)"
    ),
}


def _label(name: str, model: NoiseModel) -> str:
    """The method's label; the default's names the method it is for this model (a model
    calibrated for the paper's method alone runs that by default)."""
    label = baselines.METHOD_LABELS[name]
    return label.replace("the default:", f"the default ({default_method(model)}):", 1)


def _report(
    run: streaming.EvaluationPass, model: NoiseModel, *, names: list[str], calibration_bad
) -> dict:
    minutes = run.minutes()
    raw_detection = _detector_scores(run, "raw", minutes)
    pr2 = {
        f"pr2_{t:g}ms2": _detector_scores(run, f"pr2_{t:g}ms2", minutes)
        for t in detection.PR2_THRESHOLDS_MS2
    }
    per_method = {
        name: _method_result(run, name, _label(name, model), run.streams[name].delay_ms, minutes)
        for name in names
    }
    summary = run.summary
    if summary.recorded:
        like = summary.recorded_like
        result = _method_result(
            run,
            "bag_denoised",
            f"from bag: {bag_topic_names(model.profile)['denoised']} (like {like}"
            + (", drop-in output band-passed)" if summary.recorded_dropin else ")"),
            None,
            minutes,
        )
        result["samples_missing"] = run.recorded.missing
        result["alignment_lag_samples"] = run.lags["bag_denoised"].lag() if run.kept else None
        if run.compare:
            result["rms_difference_vs_batch"] = run.difference_vs_batch()
        per_method["bag_denoised"] = result
    primary = per_method[PRIMARY]
    counts = dict(summary.counts)
    if calibration_bad is not None:
        counts["calibration_bad"] = calibration_bad
    report = {field: primary[field] for field in REPORT_FIELDS if field in primary}
    report.update(
        {
            "f1_raw": raw_detection["f1"],
            "f1_denoised": primary["f1"],
            "peak_snr_improvement_db": primary["peak_snr_improvement_db"],
            "delay_ms": primary["delay_ms"],
            "alignment_lag_samples": run.lags[PRIMARY].lag() if run.kept else None,
            "duration_s": run.n / model.sample_rate_hz,
            "bad_samples": {
                **counts,
                "excluded_samples": run.excluded,
                "taps_excluded": run.dropped,
                "rule": BAD_SAMPLE_RULE,
            },
            "method": default_method(model),
            "threshold_source": (
                "calibration data (no contact)"
                if calibration_bad is not None
                else "no-contact part of this recording (no calibration data given)"
            ),
            "detection": {
                "raw_bandpassed": raw_detection,
                **pr2,
                "rule": DETECTION_RULE,
            },
            "methods": per_method,
        }
    )
    return report


def evaluate_recording(
    rec,
    model: NoiseModel,
    *,
    calibration=None,
    model_short: NoiseModel | None = None,
    methods: list[str] | None = None,
    keep_signals: bool = False,
    source: str = "recording",
    adapt=None,
) -> dict:
    """Metrics of every method on `rec` (a bag.Recording with ground truth), pushed as one
    slice through the streaming evaluation.

    calibration: a no-contact Recording (e.g. the calibration sweep or a no-contact
        motion segment) used for detection thresholds and the noisereduce noise clip.
    model_short: model calibrated with 32-sample blocks (enables "paper_L32").
    methods: subset of baselines.METHOD_LABELS (default: all that can run).
    keep_signals: also return the signals (key "signals", not JSON-serialisable).
    source: the recording's name in errors.
    """
    require_ground_truth(rec, where=source, profile=model.profile)
    return evaluate_pieces(
        lambda: [rec],
        model,
        open_calibration=None if calibration is None else (lambda: [calibration]),
        model_short=model_short,
        methods=methods,
        keep_signals=keep_signals,
        source=source,
        adapt=adapt,
    )


def evaluate_bag(
    bag: str | os.PathLike,
    *,
    model: NoiseModel,
    calibration: str | os.PathLike | None = None,
    model_short: NoiseModel | None = None,
    methods: list[str] | None = None,
    max_bad_fraction: float = metrics.MAX_BAD_FRACTION,
    progress: Callable[[int], None] | None = None,
    adapt=None,
) -> dict:
    """The report of one bag, streamed (memory does not grow with the bag): topics, field
    and joints from the model's robot profile. `calibration`: a no-contact bag for the
    detection thresholds. `progress(bytes)` as the bag is read (all passes together
    count as its size once)."""

    profile = model.robot_profile()
    passes = 2 if calibration is not None else 3
    size_share = None if progress is None else (lambda n: progress(n / passes))

    def pieces(path, *, truth: bool, report=None):
        return lambda: iter_recording(
            path,
            profile=profile,
            ground_truth=truth,
            denoised=truth,
            commands=False,
            progress=report,
        )

    return evaluate_pieces(
        pieces(Path(bag), truth=True, report=size_share),
        model,
        open_calibration=None if calibration is None else pieces(Path(calibration), truth=False),
        model_short=model_short,
        methods=methods,
        source=str(bag),
        calibration_source=str(calibration),
        max_bad_fraction=max_bad_fraction,
        adapt=adapt,
    )
