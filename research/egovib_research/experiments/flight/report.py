"""The real-flight report: markdown tables, JSON, figures (DIR/real_*).

Every number in the markdown is formatted from the result dict that is also written as
JSON; the "where a baseline wins" sentences are computed from it, never written by hand.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from scipy import signal as sps

from egovib_research.experiments import fmt
from egovib_research.experiments.flight.methods import LABELS
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.evaluation.metrics import json_safe
from egovib_ros.outputs import atomic_output
from egovib_ros.robot import RobotProfile
from egovib_ros.viz import pyplot

BASELINES = ("global", "mean_command", "notch_q5", "notch_q2")
FIRMWARE_LABEL = "(d) firmware's own filtered gyro (noise only)"
FILES = {
    "markdown": "real_results.md",
    "readme": "real_readme_section.md",
    "json": "real_results.json",
    "spectrogram": "real_spectrogram.png",
    "timeseries": "real_timeseries.png",
    "methods": "real_methods.png",
}
# (key, label, larger is better)
COMPARED = (
    ("noise_reduction_db", "noise reduction", True),
    ("tap_retention", "event peak retention", True),
    ("peak_snr_improvement_db", "peak-SNR gain", True),
    ("f1", "event F1", True),
    ("false_alarms_per_min", "false alarms per minute", False),
)
AT_1X = "1"


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _header(names) -> list[str]:
    return [_row(names), "|" + "---|" * len(names)]


def single_rows(fold: dict) -> dict:
    """Metrics of the first event set at 1x, per method (and the firmware row)."""
    return fold["results"][AT_1X]


def comparison_values(fold: dict) -> dict:
    """{method: {metric: value}} at 1x: over the event sets when there are several (means; F1
    from the pooled counts), else the single set."""
    pooled = fold.get("over_seeds") or {}
    if pooled:
        return {
            name: {
                key: entry["f1_pooled"] if key == "f1" else entry[key]["mean"]
                for key, _, _ in COMPARED
            }
            for name, entry in pooled["methods"].items()
        }
    return {
        name: {key: row[key] for key, _, _ in COMPARED}
        for name, row in single_rows(fold).items()
        if name != "firmware"
    }


def best_baseline(fold: dict) -> str:
    """The baseline a user would be best served by here: highest event F1, then peak-SNR gain."""
    rows = comparison_values(fold)
    present = [name for name in BASELINES if name in rows]
    return max(present, key=lambda n: (round(rows[n]["f1"], 6), rows[n]["peak_snr_improvement_db"]))


# --- tables ------------------------------------------------------------------
def table(fold: dict) -> list[str]:
    """Every metric of the first event set at 1x."""
    rows = single_rows(fold)
    methods = fold["methods"]
    lines = _header(
        (
            "method",
            "delay ms",
            "noise rad/s",
            "noise red. dB",
            "spike rad/s",
            "event peak rad/s",
            "retention",
            "peak SNR dB",
            "gain dB",
            "threshold",
            "P",
            "R",
            "F1",
            "F1 +-30 ms",
            "FA/min",
        )
    )
    for name, m in rows.items():
        if name == "firmware":
            continue
        lines.append(
            _row(
                (
                    LABELS[name],
                    fmt(methods[name]["delay_ms"], 0),
                    fmt(m["noise_mean_denoised"], 4),
                    fmt(m["noise_reduction_db"]),
                    fmt(m["noise_spike_denoised"], 3),
                    fmt(m["tap_peak_denoised"], 3),
                    fmt(m["tap_retention"], 2),
                    fmt(m["peak_snr_denoised_db"]),
                    fmt(m["peak_snr_improvement_db"]),
                    fmt(m["threshold"], 3),
                    fmt(m["precision"], 2),
                    fmt(m["recall"], 2),
                    fmt(m["f1"], 2),
                    fmt(m["f1_30ms"], 2),
                    fmt(m["false_alarms_per_min"]),
                )
            )
        )
    if "firmware" in rows:
        fw = rows["firmware"]
        lines.append(
            _row(
                (
                    f"{FIRMWARE_LABEL}: filtered in flight, before any event",
                    "n/a",
                    fmt(fw["noise_mean_denoised"], 4),
                    fmt(fw["noise_reduction_db"]),
                    fmt(fw["noise_spike_denoised"], 3),
                )
                + ("n/a",) * 10
            )
        )
    return lines


def pooled_table(fold: dict) -> list[str]:
    """Main metrics over the event sets at 1x: mean (min-max), F1 from pooled counts."""
    pooled = fold.get("over_seeds") or {}
    if not pooled:
        return []
    events = pooled["methods"]["raw"]["events"]
    lines = _header(
        (
            "method",
            "noise red. dB",
            "retention",
            "peak-SNR gain dB",
            f"F1 pooled ({events} events)",
            "F1 per set",
            "FA/min",
        )
    )

    def span(entry: dict, key: str, digits: int) -> str:
        v = entry[key]
        return f"{fmt(v['mean'], digits)} ({fmt(v['min'], digits)}-{fmt(v['max'], digits)})"

    for name, e in pooled["methods"].items():
        lines.append(
            _row(
                (
                    LABELS[name],
                    span(e, "noise_reduction_db", 1),
                    span(e, "tap_retention", 2),
                    span(e, "peak_snr_improvement_db", 1),
                    fmt(e["f1_pooled"], 2),
                    f"{fmt(e['f1']['min'], 2)}-{fmt(e['f1']['max'], 2)}",
                    span(e, "false_alarms_per_min", 1),
                )
            )
        )
    fw = single_rows(fold).get("firmware")
    if fw:
        lines.append(_row((FIRMWARE_LABEL, fmt(fw["noise_reduction_db"])) + ("n/a",) * 5))
    return lines


def amplitude_table(fold: dict) -> list[str]:
    amplitudes = list(fold["results"])
    lines = _header(
        ("method", *(f"F1 at {a}x" for a in amplitudes), *(f"gain dB at {a}x" for a in amplitudes))
    )
    for name in fold["methods"]:
        rows = [fold["results"][a][name] for a in amplitudes]
        lines.append(
            _row(
                (
                    LABELS[name],
                    *(fmt(r["f1"], 2) for r in rows),
                    *(fmt(r["peak_snr_improvement_db"]) for r in rows),
                )
            )
        )
    return lines


# --- sentences -----------------------------------------------------------------
def where_baselines_win(fold: dict) -> list[str]:
    """One sentence per baseline naming every metric on which it beats ours."""
    rows = comparison_values(fold)
    ours = rows["ours"]
    lines = []
    for name in ("raw",) + BASELINES:
        if name not in rows:
            continue
        wins = []
        for key, label, larger in COMPARED:
            if name == "raw" and key not in ("f1", "false_alarms_per_min"):
                continue  # doing nothing keeps all of an event and removes no noise: no contest
            a, b = rows[name][key], ours[key]
            if not (np.isfinite(a) and np.isfinite(b)):
                continue
            if (a > b + 1e-9) if larger else (a < b - 1e-9):
                wins.append(f"{label} {fmt(a, 2)} vs ours {fmt(b, 2)}")
        what = "event F1 and false alarms" if name == "raw" else "every metric"
        lines.append(
            f"- {LABELS[name]} beats ours on " + "; ".join(wins) + "."
            if wins
            else f"- {LABELS[name]}: ours is as good or better on {what} here."
        )
    single = single_rows(fold)
    if "firmware" in single:
        fw, mine = single["firmware"], single["ours"]
        verdict = "less" if fw["noise_mean_denoised"] < mine["noise_mean_denoised"] else "more"
        text = (
            f"- (d) the firmware's filtered gyro leaves {fmt(fw['noise_mean_denoised'], 4)} "
            f"rad/s of noise in the band ({fmt(fw['noise_reduction_db'])} dB below raw), "
            f"{verdict} than ours ({fmt(mine['noise_mean_denoised'], 4)} rad/s)"
        )
        transfer = fold.get("firmware_transfer")
        if transfer:
            low, high = transfer["band_hz"]
            text += (
                ". It is no event-preserving filter: its estimated transfer from the raw "
                "gyro (Welch cross-spectrum over the test part) has a median gain of "
                f"{fmt(transfer['median_gain_db'])} dB over {low:g}-{high:g} Hz (median "
                f"coherence {fmt(transfer['median_coherence'], 2)}), so an event in the band "
                "would be cut about as much as the noise."
            )
        lines.append(text if text.endswith(".") else text + ".")
    return lines


def _unmeasured(fold: dict) -> str:
    denoise = fold["methods"]["ours"]["info"].get("denoise", {})
    if "blocks_unmeasured" not in denoise:
        return ""
    return (
        f"{denoise['blocks_unmeasured']} of {denoise['blocks']} test blocks fell on cells the "
        "calibration never measured (Eq. 6 or the nearest measured cell stands in), "
        f"{denoise['blocks_out_of_grid']} outside the grid."
    )


def _range(fold: dict, part: str) -> str:
    low, high = (round(v, 2) + 0.0 for v in fold["motor_command_range"][part])  # no "-0.00"
    return f"{low:.2f}-{high:.2f}"


def _span_s(span: list) -> str:
    return f"{span[0]:g}-{span[1]:g} s"


def _phase(result: dict, part: str, lead: str = " (", tail: str = ")") -> str:
    """The flight phases of a part, where the split is the one they were written for."""
    phases = result["protocol"].get("phases")
    return f"{lead}{phases[part]}{tail}" if phases else ""


def _swapped_phases(result: dict) -> str:
    calibration = _phase(result, "swapped_calibration", "calibrated on ", "")
    test = _phase(result, "swapped_test", "tested on ", "")
    return f" ({calibration}, {test})" if calibration else ""


def _split_sentence(result: dict) -> str:
    primary, phases = result["primary"], result["protocol"].get("phases")
    calibration = f"motor commands {_range(primary, 'calibration')}"
    test = f"commands {_range(primary, 'test')}"
    spans = _span_s(primary["calibration_s"]), _span_s(primary["test_s"])
    if not phases:
        return f"Calibrate on {spans[0]}, {calibration}; test on {spans[1]}, {test}."
    return (
        f"Calibrate on {spans[0]} ({phases['calibration']}, {calibration}); test on {spans[1]} "
        f"({phases['test']}, {test}); {phases['left_out']}."
    )


def _protocol(result: dict) -> str:
    primary = result["primary"]
    spec = result["protocol"]["events"]
    events = primary["events"][AT_1X]
    f_low, f_high = spec["frequency_hz"]
    tau_low, tau_high = (1e3 * t for t in spec["decay_s"])
    return " ".join(
        (
            _split_sentence(result),
            f"{events['n_events']} known events are added to the test part's real gyro: damped",
            "sinusoids e(t) = A exp(-t/tau) sin(2 pi f t) on one random axis, f uniform in",
            f"{f_low:g}-{f_high:g} Hz, tau uniform in {tau_low:g}-{tau_high:g} ms, one every",
            f"{spec['spacing_s']:g} s +- {spec['jitter_s']:g} s (seed {spec['seed']}); each scaled",
            "so its band-passed peak equals the largest band-passed noise magnitude of the test",
            f"part ({events['target_peak_rad_s']:.3f} rad/s; the paper's taps were \"similar to",
            "the maximum noise magnitude\"). Detection thresholds: each method's own output on the",
            "calibration part (at motor commands the test reaches), 1.1 x its largest 4 ms RMS",
            "envelope; never tuned on the test part (for the noise tables that part is also their",
            "training data, so their calibration residual is smaller than on new data: a threshold",
            "biased low, towards false alarms, i.e. against them). Metrics:",
            "`egovib_ros.evaluation.metrics` / `detection` (INTERFACES.md section 6) on the "
            "summed,",
            "band-passed gyro; event F1 with +-10 ms onset tolerance (also +-30 ms: IIR notches",
            "ring and delay an event).",
        )
    )


def _models(fold: dict) -> str:
    coverage = fold["methods"]["ours"]["info"]["coverage"]
    text = (
        f"Ours: {coverage['cells_measured']} of the {coverage['cells_total']} cells of the "
        f"4-motor grid measured from {coverage['blocks']} calibration blocks (median "
        f"{coverage['median_blocks']:g} blocks per cell: the motors move together, so a flight "
        f"visits few cells); {_unmeasured(fold)}"
    )
    notch = fold["methods"].get("notch_q5", {}).get("info", {}).get("map")
    if notch:
        text += (
            " Notch map fitted on the calibration part: f1 = "
            f"{notch['coefficient_hz']:.0f} Hz x u^{notch['exponent']:.2f} "
            f"({notch['windows_used']} windows, rms error "
            f"{notch['rms_error_hz']:.1f} Hz); notches at 3 harmonics of each motor, folded "
            "below Nyquist (the log was decimated without anti-aliasing)."
        )
    return text


def markdown(result: dict) -> str:
    primary = result["primary"]
    profile = result["profile"]
    processing = profile["processing"]
    step = result["data"]["sample_step_ms"]
    best = best_baseline(primary)
    seeds = (primary.get("over_seeds") or {}).get("seeds", [])
    lines = [
        "# On real data: a quadcopter's gyro and its four motors",
        "",
        f"Regenerate: `{result['command']}` ({result['runtime_s']:.0f} s); every number below "
        "comes from [real_results.json](real_results.json), written by the same command.",
        "",
        " ".join(
            (
                f"**Data.** {result['data']['attribution']} Licence MIT OR Apache-2.0. Shipped as",
                f"the bag `{result['bag']}`: unfiltered gyro (`{profile['sensor']['topic']}`,",
                f"`{profile['sensor']['field']}`, rad/s), the firmware-filtered gyro, four motor",
                f"commands as `/joint_states`; {result['data']['samples']} samples in",
                f"{result['data']['duration_s']:.2f} s, steps {step['min']:.3f}-{step['max']:.3f}",
                f"ms (median {step['median']:.3f}).",
                f"Profile `config/robots/{profile['name']}.yaml`:",
                f"{len(profile['joints']['names'])} one-directional joints,",
                f"{profile['joints']['steps']} steps, L = {processing['block_length']}, hop",
                f"{processing['hop']}, band",
                f"{processing['band_hz'][0]:g}-{processing['band_hz'][1]:g} Hz.",
            )
        ),
        "",
        f"**Protocol** (the paper's experiment (b)). {_protocol(result)}",
        "",
    ]
    if seeds:
        lines += [
            f"## Results: events at 1x, over {len(seeds)} event sets (seeds "
            f"{', '.join(map(str, seeds))}): mean (min-max)",
            "",
            *pooled_table(primary),
            "",
        ]
    lines += [
        f"### Where a baseline wins (computed{' over the event sets' if seeds else ''})",
        "",
        *where_baselines_win(primary),
        "",
        f"## Every metric, first event set (seed {result['protocol']['events']['seed']}), 1x",
        "",
        *table(primary),
        "",
        f"{_models(primary)} Best baseline here (by event F1, then peak-SNR gain): {LABELS[best]}.",
        "",
        "## Event F1 and peak-SNR gain vs event amplitude (x the paper's rule, first event set)",
        "",
        *amplitude_table(primary),
        "",
    ]
    if "swapped" in result:
        swapped = result["swapped"]
        lines += [
            f"## Swapped: calibrate on {_span_s(swapped['calibration_s'])}"
            f"{_phase(result, 'swapped_calibration')}, test on {_span_s(swapped['test_s'])}",
            "",
            " ".join(
                (
                    f"The test part now holds{_phase(result, 'swapped_test', ' ', ':')} motor",
                    f"commands {_range(swapped, 'test')}, the calibration only",
                    f"{_range(swapped, 'calibration')}. Events are scaled to this part's largest",
                    f"noise ({swapped['events'][AT_1X]['target_peak_rad_s']:.3f} rad/s, from the",
                    "punch-outs).",
                    f"The worse case for every keyed method. {_unmeasured(swapped)}",
                )
            ),
            "",
            *(pooled_table(swapped) or table(swapped)),
            "",
            "Where a baseline wins here:",
            "",
            *where_baselines_win(swapped),
            "",
        ]
    lines += [
        "## Figures",
        "",
        "- [real_spectrogram.png](real_spectrogram.png): the test part, band-passed: raw with "
        f"events, ours, the best baseline ({LABELS[best]}), the firmware's filtered gyro.",
        "- [real_timeseries.png](real_timeseries.png): two seconds of the same, with the true "
        "events.",
        "- [real_methods.png](real_methods.png): noise reduction, event retention, peak-SNR gain "
        "and F1 per method, both splits (over the event sets).",
        "",
    ]
    return "\n".join(lines)


def readme_section(result: dict) -> str:
    """A short "On real data" section for the README, with the headline table; its links
    are relative to docs/, where it is written beside the files it links."""
    primary = result["primary"]
    rows = comparison_values(primary)
    single = single_rows(primary)
    swapped = result.get("swapped")
    worse = comparison_values(swapped)["ours"] if swapped else None
    lines = [
        "### On real data (a quadcopter's gyro)",
        "",
        "A real Betaflight flight log (LOG00037.BFL from ilya-epifanov/fc-blackbox, MIT OR "
        "Apache-2.0, first posted in gyroflow/gyroflow/issues/72) ships as "
        "`bags/quadcopter_ar8` with the "
        "profile `config/robots/quadcopter.yaml`. Calibrated on "
        f"{_span_s(primary['calibration_s'])} of the flight{_phase(result, 'calibration')}, "
        "tested on the rest with known contact-like events added to the real noise "
        f"(the paper's experiment (b)); `{result['command']}`:",
        "",
        *_header(
            ("method", "noise red. dB", "retention", "peak-SNR gain dB", "event F1", "FA/min")
        ),
    ]
    for name, v in rows.items():
        lines.append(
            _row(
                (
                    LABELS[name],
                    fmt(v["noise_reduction_db"]),
                    fmt(v["tap_retention"], 2),
                    fmt(v["peak_snr_improvement_db"]),
                    fmt(v["f1"], 2),
                    fmt(v["false_alarms_per_min"]),
                )
            )
        )
    if "firmware" in single:
        lines.append(
            _row((FIRMWARE_LABEL, fmt(single["firmware"]["noise_reduction_db"])) + ("n/a",) * 4)
        )
    lines += [
        "",
        f"Means over {len(primary['over_seeds']['seeds'])} event sets; F1 pooled."
        if primary.get("over_seeds")
        else "",
    ]
    if worse:
        lines.append(
            f"With the halves swapped{_swapped_phases(result)} ours gives "
            f"{fmt(worse['noise_reduction_db'])} dB, gain "
            f"{fmt(worse['peak_snr_improvement_db'])} dB, F1 {fmt(worse['f1'], 2)}: the "
            "worse figure."
        )
    lines += [
        "",
        "Where a baseline wins:",
        "",
        *where_baselines_win(primary),
        "",
        # linked from where the section is written, beside them (docs/)
        "Details and figures: [docs/real_results.md](real_results.md), "
        "![spectrogram](real_spectrogram.png) ![methods](real_methods.png)",
        "",
    ]
    return "\n".join(lines)


def summary_text(result: dict) -> str:
    rows = comparison_values(result["primary"])
    out = [f"{'method':14s} {'noise red dB':>12s} {'retention':>10s} {'gain dB':>8s} {'F1':>5s}"]
    for name, v in rows.items():
        out.append(
            f"{name:14s} {fmt(v['noise_reduction_db']):>12s} "
            f"{fmt(v['tap_retention'], 2):>10s} {fmt(v['peak_snr_improvement_db']):>8s} "
            f"{fmt(v['f1'], 2):>5s}"
        )
    firmware = single_rows(result["primary"]).get("firmware")
    if firmware:
        out.append(f"{'firmware':14s} {fmt(firmware['noise_reduction_db']):>12s}   (noise only)")
    return "\n".join(out)


def strip_signals(result: dict) -> dict:
    out = dict(result)
    for key in ("primary", "swapped"):
        if key in out:
            out[key] = {k: v for k, v in out[key].items() if k != "signals"}
    return json_safe(out)


# --- figures -----------------------------------------------------------------
def _png(fig) -> bytes:
    plt = pyplot()
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=110, format="png")
    plt.close(fig)
    return buffer.getvalue()


def spectrogram_figure(result: dict, profile: RobotProfile) -> bytes:
    plt = pyplot()
    fold = result["primary"]
    sig = fold["signals"]
    best = best_baseline(fold)
    t = (sig["stamps_ns"] - sig["t0_ns"]) / NS_PER_S
    panels = [
        ("raw_input", "raw gyro + added events (band-passed)"),
        ("ours", LABELS["ours"]),
        (best, f"best baseline: {LABELS[best]}"),
    ]
    if sig.get("firmware") is not None:
        panels.append(("firmware", "(d) firmware's filtered gyro (no events: filtered in flight)"))
    fig, axes = plt.subplots(len(panels), 1, figsize=(11, 2.4 * len(panels) + 0.6), sharex=True)
    vmax = None
    onsets = t[sig["seg"].onsets]
    for ax, (key, title) in zip(axes, panels):
        f, tt, power = sps.spectrogram(sig[key], fs=profile.rate_hz, nperseg=64, noverlap=48)
        db = 10 * np.log10(power + 1e-14)
        vmax = db.max() if vmax is None else vmax
        mesh = ax.pcolormesh(
            tt + t[0], f, db, shading="auto", vmin=vmax - 60, vmax=vmax, cmap="magma"
        )
        ax.set_ylabel("Hz")
        ax.set_title(title, fontsize=9)
        if key != "firmware":
            ax.plot(onsets, np.full(len(onsets), f[-1] * 0.97), "v", color="cyan", ms=4)
    fig.colorbar(mesh, ax=list(axes), label="power (dB, (rad/s)^2/Hz)", shrink=0.5)
    axes[-1].set_xlabel("flight time (s); triangles: true event onsets")
    fig.suptitle("Real quadcopter flight, test part: spectrogram before / after", fontsize=11)
    return _png(fig)


def timeseries_figure(result: dict, profile: RobotProfile, window_s: float = 2.0) -> bytes:
    plt = pyplot()
    fold = result["primary"]
    sig = fold["signals"]
    fs = profile.rate_hz
    best = best_baseline(fold)
    t = (sig["stamps_ns"] - sig["t0_ns"]) / NS_PER_S
    onsets = sig["seg"].onsets
    start = max(0, int(onsets[1] - 0.25 * fs) if len(onsets) > 1 else 0)
    window = slice(start, min(len(t), start + int(window_s * fs)))
    rows = single_rows(fold)
    fig, axes = plt.subplots(3, 1, figsize=(11, 7), sharex=True)
    lim = 1.05 * np.abs(sig["raw_input"][window]).max()
    for ax, key in zip(axes, ("raw_input", "ours", best)):
        label = "raw (band-passed)" if key == "raw_input" else LABELS[key]
        ax.plot(t[window], sig[key][window], lw=0.7, color="tab:blue", label=label)
        ax.plot(
            t[window],
            sig["reference"][window],
            lw=0.7,
            color="tab:orange",
            alpha=0.8,
            label="true events",
        )
        ax.set_ylim(-lim, lim)
        ax.set_ylabel("rad/s")
        ax.legend(loc="upper right", fontsize=8)
        if key != "raw_input":
            m = rows[key]
            ax.set_title(
                f"noise {m['noise_mean_raw']:.4f} -> {m['noise_mean_denoised']:.4f} "
                f"rad/s, retention {m['tap_retention']:.2f}, peak SNR gain "
                f"{m['peak_snr_improvement_db']:.1f} dB, F1 {m['f1']:.2f}",
                fontsize=9,
            )
    axes[-1].set_xlabel("flight time (s)")
    fig.suptitle(
        "Real flight with added events: two seconds of the test part (first event set)", fontsize=11
    )
    return _png(fig)


def methods_figure(result: dict) -> bytes:
    plt = pyplot()
    folds = [("primary", "calibrate on the 1st part, test the 2nd")]
    if "swapped" in result:
        folds.append(("swapped", "swapped"))
    names = [n for n in comparison_values(result["primary"]) if n != "raw"] + ["firmware"]
    panels = (
        ("noise_reduction_db", "noise reduction outside events (dB)"),
        ("tap_retention", "event peak retention"),
        ("peak_snr_improvement_db", "peak-SNR gain (dB)"),
        ("f1", "event F1"),
    )
    fig, axes = plt.subplots(1, 4, figsize=(15, 4.8), sharey=True)
    y = np.arange(len(names))
    height = 0.8 / len(folds)
    for ax, (key, title) in zip(axes, panels):
        for i, (fold_key, fold_label) in enumerate(folds):
            values = comparison_values(result[fold_key])
            firmware = single_rows(result[fold_key]).get("firmware", {})
            bars = [values[n][key] if n in values else firmware.get(key, np.nan) for n in names]
            ax.barh(y + i * height, bars, height=height, label=fold_label, color=f"C{i}")
        ax.set_title(title, fontsize=9)
        ax.axvline(0, color="k", lw=0.5)
    axes[0].set_yticks(y + height * (len(folds) - 1) / 2)
    axes[0].set_yticklabels([LABELS.get(n, FIRMWARE_LABEL) for n in names], fontsize=7)
    axes[0].invert_yaxis()
    axes[-1].legend(fontsize=8, loc="lower right")
    fig.suptitle(
        "Real quadcopter flight, events at 1x (over the event sets): ours vs what a user "
        "would otherwise pick",
        fontsize=11,
    )
    fig.tight_layout()
    return _png(fig)


def write_report(result: dict, profile: RobotProfile, out_dir: Path) -> list[Path]:
    """Render everything first, then write each file atomically (no partial output)."""
    contents = {
        FILES["markdown"]: markdown(result).encode(),
        FILES["readme"]: readme_section(result).encode(),
        FILES["json"]: (json.dumps(strip_signals(result), indent=1) + "\n").encode(),
        FILES["spectrogram"]: spectrogram_figure(result, profile),
        FILES["timeseries"]: timeseries_figure(result, profile),
        FILES["methods"]: methods_figure(result),
    }
    written = []
    for name, data in contents.items():
        path = Path(out_dir) / name
        with atomic_output(path) as tmp:
            tmp.write_bytes(data)
        written.append(path)
    return written
