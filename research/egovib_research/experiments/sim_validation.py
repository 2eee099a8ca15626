"""Does the simulator reproduce what the paper observed?  Fig. 3 / Fig. 4 analogues and levels.

Spectra are computed as in the paper, with the robot profile's settings (the PR2 hand's:
sum of the 3 axes, 4th-order Butterworth band-pass 150-750 Hz, 64-sample blocks with hop
32), the core's periodic Hamming window, magnitude of the rfft; per velocity cell the mean mu(f) and
standard deviation sd(f) over the blocks, N(f) = mu + sd (Eq. 5).

Fig. 4 metric (superposition error of one cell (w, g)):

    N6(f)  = mu(w,0) + mu(0,g) - mu(0,0) + sqrt(sd(w,0)^2 + sd(0,g)^2 + sd(0,0)^2) (Eq. 6, literal)
    Nobs(f) = mu(w,g) + sd(w,g)
    error   = 100 * |sum_f N6(f) - sum_f Nobs(f)| / sum_f Nobs(f),
              f over the rfft bins in the profile's band

Blocks are assigned to cells by the commanded cell and kept only when the true
joint speeds stay within 0.5 % of max speed of the cell's speeds over the whole
block (settling and gripper reversals are left out).  This validates the
simulator's physics; the project's calibrator does the same from bags by
measured velocity.

Run `python -m egovib_research.experiments.sim_validation --out docs` to regenerate the figures
and docs/sim_results.json.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import signal

from egovib_ros.bag import read_recording, write_recording
from egovib_ros.core.blocks import analysis_window
from egovib_ros.core.filters import design_bandpass
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.robot import load_profile
from egovib_ros.sim.hand import HandSimulator
from egovib_ros.sim.params import SimParams
from egovib_ros.sim.scenarios import iter_sweep, simulate_motion, sweep_cells
from egovib_ros.viz import pyplot, save_figure

# The simulated hand's settings come from its robot profile (the PR2 right hand, the default),
# as for any robot: rate, band, blocks, top speeds and the grid's speed fractions.
PROFILE = load_profile()
# the grid's speeds as fractions of max speed (the same for both joints)
CELL_FRACTIONS = PROFILE.grid_values(0) / PROFILE.max_speed[0]

STEADY_TOLERANCE = 0.005  # of max speed
FREQS_HZ = np.fft.rfftfreq(PROFILE.block_length, 1.0 / PROFILE.rate_hz)
BAND_BINS = (PROFILE.band_hz[0] <= FREQS_HZ) & (PROFILE.band_hz[1] >= FREQS_HZ)


BAND_SOS = design_bandpass(
    sample_rate_hz=PROFILE.rate_hz, band_hz=PROFILE.band_hz, order=PROFILE.band_order
)


def bandpass_combined(accel: np.ndarray) -> np.ndarray:
    """Sum of the 3 axes, band-passed (the profile's Butterworth band-pass, causal)."""
    return signal.sosfilt(BAND_SOS, np.asarray(accel, float).sum(axis=1))


def _blocks(x: np.ndarray) -> np.ndarray:
    """(B, L) the profile's blocks of `x`, a hop apart."""
    return np.lib.stride_tricks.sliding_window_view(x, PROFILE.block_length)[:: PROFILE.hop]


def block_magnitudes(x: np.ndarray) -> np.ndarray:
    """|rfft(window * block)| of the profile's blocks and hop: (B, F)."""
    if len(x) < PROFILE.block_length:
        return np.zeros((0, len(FREQS_HZ)))
    window = analysis_window(PROFILE.block_length, PROFILE.hop)
    return np.abs(np.fft.rfft(_blocks(x) * window, axis=1))


@dataclass
class CellStats:
    cells: np.ndarray  # (C, 2) commanded velocities
    mean: np.ndarray  # (C, F)
    std: np.ndarray  # (C, F)
    counts: np.ndarray  # (C,) blocks used


def sweep_cell_stats(
    *,
    params: SimParams | None = None,
    effects: dict | None = None,
    seed: int = 0,
    grid: str = "full",
    dwell_s: float = 3.0,
    settle_s: float = 0.3,
    cells: np.ndarray | None = None,
) -> CellStats:
    """Per-cell mean/std magnitude spectra from a simulated sweep (no bag).

    `cells` (C, 2) overrides `grid` with an explicit list of commanded velocities.
    """
    params = params if params is not None else SimParams.load()
    sim = HandSimulator(params, effects=effects, seed=seed)
    cells = sweep_cells(grid) if cells is None else np.asarray(cells, float).reshape(-1, 2)
    zi = np.zeros((BAND_SOS.shape[0], 2))
    vmax = np.asarray(PROFILE.max_speed)
    pieces: dict[int, list] = {}
    for ci, _cell, _, chunk in iter_sweep(sim, cells, dwell_s=dwell_s, settle_s=settle_s):
        bp, zi = signal.sosfilt(BAND_SOS, chunk.sensor.sum(axis=1), zi=zi)
        if ci not in pieces:
            # frame on the global hop grid, as a continuous calibrator does (blocks start at
            # multiples of the hop, so a hop-periodic idle hum looks the same in every cell)
            first = int(
                round((chunk.sensor_stamps_ns[0] - sim.start_ns) * PROFILE.rate_hz / NS_PER_S)
            )
            skip = (-first) % PROFILE.hop
            pieces[ci] = []
            bp, vel = bp[skip:], chunk.true_velocity[skip:]
        else:
            vel = chunk.true_velocity
        pieces[ci].append((bp, vel))
    mean = np.zeros((len(cells), len(FREQS_HZ)))
    std = np.zeros_like(mean)
    counts = np.zeros(len(cells), np.int64)
    for ci, parts in pieces.items():
        bp = np.concatenate([p[0] for p in parts])
        vel = np.concatenate([p[1] for p in parts])
        off = np.abs(np.abs(vel) - np.abs(cells[ci])) / vmax  # (n, 2)
        bad = np.any(off > STEADY_TOLERANCE, axis=1).astype(float)
        steady = _blocks(bad).max(axis=1) == 0
        mags = block_magnitudes(bp)[steady]
        counts[ci] = len(mags)
        if len(mags):
            mean[ci], std[ci] = mags.mean(axis=0), mags.std(axis=0)
    return CellStats(cells=cells, mean=mean, std=std, counts=counts)


def _grid_index(stats: CellStats) -> np.ndarray:
    """(C, 2) integer grid indices of the cells (the nearest of the profile's grid fractions)."""
    frac = stats.cells / np.asarray(PROFILE.max_speed)
    return np.abs(frac[..., None] - CELL_FRACTIONS).argmin(axis=-1)


def superposition_error(stats: CellStats) -> np.ndarray:
    """(G, G) Fig. 4 error map in % (G grid points per joint, 21 for the PR2; rows wrist,
    columns gripper): each cell's mu + sd against Eq. 6 from the single-joint cells."""
    n = len(CELL_FRACTIONS)
    mu = np.full((n, n, len(FREQS_HZ)), np.nan)
    sd = np.full_like(mu, np.nan)
    for (i, j), m, s, c in zip(_grid_index(stats), stats.mean, stats.std, stats.counts):
        if c > 0:
            mu[i, j], sd[i, j] = m, s
    z = len(CELL_FRACTIONS) // 2
    with np.errstate(invalid="ignore"):
        n6 = (
            mu[:, z][:, None]
            + mu[z, :][None, :]
            - mu[z, z]
            + np.sqrt(sd[:, z][:, None] ** 2 + sd[z, :][None, :] ** 2 + sd[z, z] ** 2)
        )
        n_obs = mu + sd
        s6, sobs = n6[..., BAND_BINS].sum(axis=-1), n_obs[..., BAND_BINS].sum(axis=-1)
        return 100.0 * np.abs(s6 - sobs) / sobs


def motion_levels(
    *,
    params: SimParams | None = None,
    effects: dict | None = None,
    seed: int = 0,
    duration_s: float = 60.0,
    max_speed: float = 0.5,
    tap_rate_hz: float = 1.0,
) -> dict:
    """Paper section 4 levels on random smooth motion with taps (raw signal, no denoising).

    noise_mean: mean |band-passed sum of axes| outside contacts (onset .. onset + 60 ms excluded);
    tap_peak: mean over taps of max |band-passed| within 30 ms of the onset; peak SNR in dB.
    """
    rec, truth = simulate_motion(
        duration_s=duration_s,
        max_speed=max_speed,
        tap_rate_hz=tap_rate_hz,
        effects=effects,
        seed=seed,
        params=params,
    )
    bp = np.abs(bandpass_combined(rec.sensor))
    onsets = np.searchsorted(rec.sensor_stamps_ns, np.asarray(truth["tap_onsets_ns"], np.int64))
    in_contact = np.zeros(len(bp), bool)
    win, excl = int(0.03 * PROFILE.rate_hz), int(0.06 * PROFILE.rate_hz)
    peaks = []
    for k in onsets:
        in_contact[k : k + excl] = True
        if k + win <= len(bp):
            peaks.append(bp[k : k + win].max())
    noise = float(bp[~in_contact][int(0.1 * PROFILE.rate_hz) :].mean())
    peak = float(np.mean(peaks)) if peaks else float("nan")
    stationary = HandSimulator(params if params is not None else SimParams.load(), seed=seed).step(
        int(5 * PROFILE.rate_hz)
    )
    background = float(
        np.abs(bandpass_combined(stationary.sensor))[int(0.1 * PROFILE.rate_hz) :].mean()
    )
    return {
        "noise_mean_raw": noise,
        "tap_peak_raw": peak,
        "peak_snr_raw_db": 20 * np.log10(peak / noise),
        "n_taps": len(peaks),
        "stationary_background_mean": background,
        "duration_s": duration_s,
        "max_speed": max_speed,
    }


def generation_speed(seconds: float = 20.0, seed: int = 0) -> float:
    """Signal generation speed as a multiple of real time (both joints moving, taps on)."""
    sim = HandSimulator(SimParams.load(), seed=seed, tap_rate_hz=1.0)
    sim.set_command([0.5 * PROFILE.max_speed[0], 0.5 * PROFILE.max_speed[1]])
    t0 = time.perf_counter()
    for _ in range(int(seconds)):
        sim.step(int(PROFILE.rate_hz))
    return seconds / (time.perf_counter() - t0)


def bag_io_speed(seconds: float = 30.0, *, compress: bool = False, seed: int = 0) -> dict:
    """Bag write/read throughput for a simulated motion recording (raw + contact + ego +
    joint states).

    Returns messages/s and multiples of real time for write_recording and read_recording.
    """

    rec, _ = simulate_motion(duration_s=seconds, max_speed=0.5, tap_rate_hz=1.0, seed=seed)
    n_messages = 3 * len(rec.sensor) + len(rec.joint_stamps_ns) + len(rec.commands)
    with tempfile.TemporaryDirectory(prefix="egovib_sim_validation_") as tmp:
        bag = Path(tmp) / "bag"
        t0 = time.perf_counter()
        write_recording(bag, rec, compress=compress)
        t_write = time.perf_counter() - t0
        t0 = time.perf_counter()
        read_recording(bag)
        t_read = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in bag.iterdir())
    return {
        "seconds": seconds,
        "messages": n_messages,
        "compress": compress,
        "bytes": size,
        "write_msgs_per_s": n_messages / t_write,
        "read_msgs_per_s": n_messages / t_read,
        "write_x_realtime": seconds / t_write,
        "read_x_realtime": seconds / t_read,
    }


# --- figures ---------------------------------------------------------------------
def plot_fig3(stats: CellStats, path: str | Path) -> None:
    """Mean + std spectra (Eq. 5) for a subset of cells, 4 direction combinations each
    (paper Fig. 3)."""
    plt = pyplot()

    idx = _grid_index(stats)
    lookup = {(i, j): k for k, (i, j) in enumerate(idx)}
    zero = len(CELL_FRACTIONS) // 2  # the grid's 0 (symmetric: both directions)
    levels = [int(round(f * zero)) for f in (0.0, 0.3, 0.6, 1.0)]  # grid steps from 0
    fig, axs = plt.subplots(len(levels), len(levels), figsize=(12, 10), sharex=True, sharey=True)
    for r, lw in enumerate(levels):
        for c, lg in enumerate(levels):
            ax = axs[r, c]
            for sw, sg, style in ((1, 1, "-"), (1, -1, "--"), (-1, 1, "-."), (-1, -1, ":")):
                k = lookup.get((zero + sw * lw, zero + sg * lg))
                if k is None or stats.counts[k] == 0:
                    continue
                ax.plot(
                    FREQS_HZ,
                    stats.mean[k] + stats.std[k],
                    style,
                    lw=1,
                    label=f"w{'+' if sw > 0 else '-'} g{'+' if sg > 0 else '-'}",
                )
            ax.axvspan(*PROFILE.band_hz, color="0.92", zorder=0)
            if r == 0:
                ax.set_title(f"gripper {100 * CELL_FRACTIONS[zero + lg]:.0f} %", fontsize=9)
            if c == 0:
                ax.set_ylabel(
                    f"wrist {100 * CELL_FRACTIONS[zero + lw]:.0f} %\n|N| (Eq. 5)", fontsize=9
                )
            if r == len(levels) - 1:
                ax.set_xlabel("Hz")
    axs[0, 0].legend(fontsize=6)
    fig.suptitle(
        "Simulated ego-vibration spectra mu+sd (sum of axes, band-passed; "
        f"shaded = {PROFILE.band_hz[0]:g}-{PROFILE.band_hz[1]:g} Hz)"
    )
    save_figure(fig, path, dpi=90)


def plot_fig4(error: np.ndarray, path: str | Path, title: str) -> None:
    """Superposition error map (paper Fig. 4)."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(6.5, 5.2))
    pct = CELL_FRACTIONS * 100
    half = (pct[1] - pct[0]) / 2  # a cell is one grid step wide
    im = ax.imshow(
        error,
        origin="lower",
        extent=(pct[0] - half, pct[-1] + half, pct[0] - half, pct[-1] + half),
        cmap="viridis",
        vmin=0,
        vmax=max(20.0, float(np.nanmax(error))),
    )
    ax.set_xlabel("gripper velocity (% of max)")
    ax.set_ylabel("wrist roll velocity (% of max)")
    ax.set_title(
        f"{title}\nmax {np.nanmax(error):.1f} %, mean {np.nanmean(error):.1f} %", fontsize=10
    )
    fig.colorbar(im, ax=ax, label="superposition error (%)")
    save_figure(fig, path, dpi=90)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Simulator validation figures (Fig. 3/4 analogues)."
    )
    parser.add_argument("--out", default="docs")
    parser.add_argument("--dwell", type=float, default=3.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--coupling", type=float, default=1.0)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    t0 = time.time()
    full = sweep_cell_stats(grid="full", dwell_s=args.dwell, seed=args.seed)
    err = superposition_error(full)
    plot_fig3(full, out / "sim_fig3_spectra.png")
    plot_fig4(err, out / "sim_fig4_superposition.png", "Base simulator: Eq. 6 superposition error")
    results["fig4_base"] = {
        "max": float(np.nanmax(err)),
        "mean": float(np.nanmean(err)),
        "cells_over_5pct": int(np.sum(err > 5)),
        "dwell_s": args.dwell,
        "max_by_wrist_speed": [float(x) for x in np.nanmax(err, axis=1)],
    }
    coupled = sweep_cell_stats(
        grid="full", dwell_s=args.dwell, seed=args.seed, effects={"coupling": args.coupling}
    )
    err_c = superposition_error(coupled)
    plot_fig4(
        err_c,
        out / "sim_fig4_superposition_coupling.png",
        f"coupling={args.coupling:g}: Eq. 6 superposition error",
    )
    results["fig4_coupling"] = {
        "strength": args.coupling,
        "max": float(np.nanmax(err_c)),
        "mean": float(np.nanmean(err_c)),
        "max_by_wrist_speed": [float(x) for x in np.nanmax(err_c, axis=1)],
    }
    results["levels_motion_50pct"] = motion_levels(seed=args.seed)
    results["generation_x_realtime"] = generation_speed()
    results["bag_io"] = [bag_io_speed(30.0), bag_io_speed(30.0, compress=True)]
    results["wall_s"] = time.time() - t0
    (out / "sim_results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(
        json.dumps(
            {
                k: (
                    v
                    if not isinstance(v, dict)
                    else {kk: vv for kk, vv in v.items() if not isinstance(vv, list)}
                )
                for k, v in results.items()
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
