"""Figures of the evaluation (PNG, matplotlib Agg): Fig. 5 analogues, PR curves, method vs speed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import signal

from egovib_ros.evaluation import baselines
from egovib_ros.outputs import atomic_output
from egovib_ros.viz import pyplot

SHOWN_S = 5.0  # seconds of signal in the time-series figures


def _save(fig, path: Path) -> Path:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    pyplot().close(fig)
    return path


def _window(report: dict, fs: float) -> slice:
    """A SHOWN_S-second window starting just before the first tap after 1 s."""
    onsets = report["signals"]["seg"].onsets
    n = len(report["signals"]["raw"])
    later = onsets[onsets > fs]
    start = int(later[0] - 0.2 * fs) if later.size else int(fs)
    start = max(0, min(start, n - int(SHOWN_S * fs)))
    return slice(start, min(n, start + int(SHOWN_S * fs)))


def fig5(
    report: dict, path: Path, *, title: str, fs: float = 3000.0, method: str = "paper"
) -> Path:
    """Paper Fig. 5 analogue: time series and spectrograms, raw vs denoised, with the
    true contact."""
    sig = report["signals"]
    window = _window(report, fs)
    t = np.arange(window.start, window.stop) / fs
    fig, axes = pyplot().subplots(4, 1, figsize=(10, 9), sharex=True)
    lim = 1.05 * np.abs(sig["raw"][window]).max()
    for ax, key, label in (
        (axes[0], "raw", "raw (band-passed)"),
        (axes[1], method, f"denoised: {baselines.METHOD_LABELS[method]}"),
    ):
        ax.plot(t, sig[key][window], lw=0.6, color="tab:blue", label=label)
        ax.plot(
            t, sig["reference"][window], lw=0.6, color="tab:orange", alpha=0.8, label="true contact"
        )
        ax.set_ylim(-lim, lim)
        ax.set_ylabel("m/s$^2$")
        ax.legend(loc="upper right", fontsize=8)
    m = report["methods"][method]
    axes[1].set_title(
        f"noise {m['noise_mean_raw']:.3f} -> {m['noise_mean_denoised']:.3f} m/s$^2$, "
        f"peak {m['tap_peak_raw']:.2f} -> {m['tap_peak_denoised']:.2f} m/s$^2$, "
        f"peak SNR {m['peak_snr_raw_db']:.1f} -> {m['peak_snr_denoised_db']:.1f} dB",
        fontsize=9,
    )
    vmax = None
    for ax, key in ((axes[2], "raw"), (axes[3], method)):
        f, tt, power = signal.spectrogram(sig[key][window], fs=fs, nperseg=64, noverlap=32)
        db = 10 * np.log10(power + 1e-12)
        vmax = db.max() if vmax is None else vmax
        mesh = ax.pcolormesh(
            tt + t[0], f, db, shading="auto", vmin=vmax - 60, vmax=vmax, cmap="magma"
        )
        ax.set_ylabel("Hz")
        ax.set_title(f"spectrogram: {'raw' if key == 'raw' else 'denoised'}", fontsize=9)
    # One colour bar for the whole column keeps all four panels the same width (shared time axis).
    fig.colorbar(
        mesh, ax=list(axes), label="spectrogram power (dB)", shrink=0.45, anchor=(0.0, 0.0)
    )
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(title)
    return _save(fig, path)


def pr_figure(
    reports: dict[str, dict], path: Path, methods=("paper", "wiener", "per_axis", "bandpass")
) -> Path:
    """PR curves (threshold sweeps) with each detector's calibrated operating point."""
    fig, axes = pyplot().subplots(1, len(reports), figsize=(5.0 * len(reports), 4.5), squeeze=False)
    for ax, (title, report) in zip(axes[0], reports.items()):
        curves = report["pr_curves"]
        raw = curves["raw_bandpassed"]
        ax.plot(raw["recall"], raw["precision"], "-", color="gray", label="raw band-passed (sweep)")
        det = report["detection"]
        ax.plot(
            det["raw_bandpassed"]["recall"], det["raw_bandpassed"]["precision"], "o", color="gray"
        )
        for i, name in enumerate(n for n in methods if n in curves and n != "bandpass"):
            curve = curves[name]
            color = f"C{i}"
            ax.plot(
                curve["recall"],
                curve["precision"],
                "-",
                color=color,
                label=f"{baselines.METHOD_LABELS[name]} (sweep)",
            )
            m = report["methods"][name]
            ax.plot(m["recall"], m["precision"], "o", color=color)
        for marker, key in (("s", "pr2_2ms2"), ("^", "pr2_5ms2")):
            ax.plot(
                det[key]["recall"],
                det[key]["precision"],
                marker,
                color="k",
                mfc="none",
                label=f"PR2 {det[key]['threshold']:g} m/s$^2$ on raw magnitude",
            )
        ax.set_xlim(-0.02, 1.02)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_title(f"{title} (dots: calibrated thresholds)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="lower left")
    return _save(fig, path)


def speed_figure(results: dict, path: Path) -> Path:
    """Each method's noise reduction, peak-SNR gain and F1 against the speed limit, both
    experiments."""
    speeds = sorted(results["speeds"])
    keys = [
        ("noise_reduction_db", "no-contact noise reduction (dB)"),
        ("peak_snr_improvement_db", "peak SNR improvement (dB)"),
        ("tap_retention", "tap peak retention"),
        ("f1", "event F1"),
    ]
    experiments = list(next(iter(results["speeds"].values())).keys())
    fig, axes = pyplot().subplots(
        len(experiments),
        len(keys),
        figsize=(4.2 * len(keys), 3.6 * len(experiments)),
        squeeze=False,
    )
    x = 100 * np.array(speeds)
    for row, exp in enumerate(experiments):
        names = list(results["speeds"][speeds[0]][exp]["methods"])
        for col, (key, label) in enumerate(keys):
            ax = axes[row][col]
            for i, name in enumerate(names):
                y = [results["speeds"][s][exp]["methods"][name][key] for s in speeds]
                ax.plot(
                    x,
                    y,
                    "o-",
                    color=f"C{i}",
                    label=baselines.METHOD_LABELS[name],
                    lw=2 if name == "paper" else 1,
                )
            if key == "f1":
                for style, det_key, label_det in (
                    (":", "raw_bandpassed", "detector on raw band-passed"),
                    ("--", "pr2_2ms2", "PR2 2 m/s$^2$"),
                    ("-.", "pr2_5ms2", "PR2 5 m/s$^2$"),
                ):
                    y = [results["speeds"][s][exp]["detection"][det_key]["f1"] for s in speeds]
                    ax.plot(x, y, style, color="k", label=label_det)
            ax.set_title(f"exp ({exp}): {label}", fontsize=9)
            ax.set_xlabel("speed limit (% of max)")
            ax.set_xticks(x)
            ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _save(fig, path)


def make_figures(results: dict, out_dir: Path, *, fs: float = 3000.0) -> list[Path]:
    """All evaluation figures from `run_experiments(..., keep_signals=True)` results."""
    out_dir = Path(out_dir)
    speeds = sorted(results["speeds"])
    shown = 0.5 if 0.5 in speeds else speeds[0]
    both = results["speeds"][shown]
    pr_panels = {
        f"exp (a), {shown:.0%}": both["a"],
        f"exp (a), {speeds[-1]:.0%}": results["speeds"][speeds[-1]]["a"],
        f"exp (b), {shown:.0%}": both["b"],
    }
    if "robustness" in results and "pr_curves" in results["robustness"]["a"]:
        robust = results["robustness"]
        pr_panels[f"exp (a), {robust['speed']:.0%}, {robust['effects']}"] = robust["a"]
    paths = [
        fig5(
            both["a"],
            out_dir / "eval_fig5_a.png",
            fs=fs,
            title=f"Experiment (a): taps on the moving hand, speed limit {shown:.0%}",
        ),
        fig5(
            both["b"],
            out_dir / "eval_fig5_b.png",
            fs=fs,
            title=(
                f"Experiment (b): stationary taps added to ego-vibration, speed limit {shown:.0%}"
            ),
        ),
        pr_figure(pr_panels, out_dir / "eval_pr_curve.png"),
        speed_figure(results, out_dir / "eval_speed.png"),
    ]
    return paths
