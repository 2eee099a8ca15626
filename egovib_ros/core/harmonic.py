"""Speed-locked harmonic cancellation: each actuator's vibration lines tracked and subtracted.

A motor, gear or propeller shakes the sensor at frequencies proportional to its speed.
Where the paper subtracts a magnitude spectrum per block, this stage predicts each line
sample by sample and subtracts it: no delay, and what is not a line (a contact) keeps its
waveform. Per joint j, the lines' frequencies are

    s_j = |v_j| through a first-order lag (tau_up speeding up, tau_down slowing down:
          a rotor's inertia; the joint state may lead the vibration)
    f_l = c_l * s_j ** p_j * (1 + d_j)      for each line l of joint j

with coefficients c_l (the line "orders", found by `fit_harmonic_map`), exponent p_j and a
bounded per-joint correction d_j tracked online (a reported velocity is a few % off the
real speed). Lines above Nyquist need no care: the references run at the unfolded
frequency, and sampling folds them as it folds the vibration.

Per line and channel, LMS adapts the weights of cos/sin references (`tracking_hz`: each
tracker's bandwidth); per joint, a second-order PLL (`pll_hz`) moves the phase and d_j of
all its lines together. The error driving both is clipped at `clip_sigma` running robust
spreads, so a tap barely moves them. Never worse than nothing: where the short-time power
(`guard_ms`) of the residual exceeds the input's (lines changing faster than the trackers
follow), the prediction is scaled by sqrt(P_in / P_residual) before it is subtracted.

`HarmonicCanceller.process` keeps all state between calls (any chunking gives the same
result, to the bit); the per-sample loop is compiled with numba (`cache=True`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields

import numba
import numpy as np
from scipy.ndimage import median_filter

from egovib_ros.errors import ConfigError, ModelFileError, check_ranges

TWO_PI = 2.0 * math.pi

#: Exponents p tried when fitting the speed -> frequency map (1 = proportional, as a gear
#: mesh; < 1 as a propeller whose speed saturates with command).
EXPONENTS = (0.6, 0.7, 0.8, 0.9, 1.0, 1.1)
#: Orders tried relative to a joint's strongest line: k / m for m = 1..4 (the strongest line
#: may be a harmonic, and commutation lines sit between gear-mesh harmonics), 1/4 .. 8.
ORDERS = tuple(
    sorted(
        {round(k / m, 6) for m in (1, 2, 3, 4) for k in range(1, 8 * m + 1) if 0.25 <= k / m <= 8}
        - {1.0}
    )
)
#: Seconds of a recording whose spectra find the strongest lines and the exponent.
SPECTRA_SECONDS = 600.0
#: Orders (ranked by how high they stand in the spectra) the refinement tries per joint.
ORDER_CANDIDATES = 8
#: Lags tried for speeding up / slowing down, seconds.
LAGS_S = (0.0, 0.01, 0.02, 0.035, 0.05, 0.08)
#: The map search: at most this many lines per joint; a joint whose strongest line stands
#: less than MIN_SCORE_DB above the floor gets none; a change is kept when it lowers the
#: residual by MIN_GAIN_DB; ROUNDS passes over the joints.
MAX_LINES_PER_JOINT = 4
MIN_SCORE_DB = 3.0
MIN_GAIN_DB = 0.05
ROUNDS = 2


def fold(freq_hz, sample_rate_hz: float):
    """Where a line at `freq_hz` appears when sampled at `sample_rate_hz` (no anti-aliasing)."""
    f = np.mod(np.asarray(freq_hz, float), sample_rate_hz)
    return np.where(f > sample_rate_hz / 2, sample_rate_hz - f, f)


# --- The map ------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HarmonicMap:
    """Per joint: exponent, lags, speed below which its lines are off; per line: the joint it
    belongs to and its coefficient (Hz per unit speed**exponent). `line_score_db` is how far
    above the local spectral floor the line stood in calibration (information only)."""

    joint_names: tuple[str, ...]
    exponent: np.ndarray  # (J,)
    tau_up_s: np.ndarray  # (J,)
    tau_down_s: np.ndarray  # (J,)
    min_speed: np.ndarray  # (J,)
    line_joint: np.ndarray  # (L,) int
    line_coefficient: np.ndarray  # (L,) Hz per unit**exponent
    line_score_db: np.ndarray  # (L,)
    residual_rms: np.ndarray  # (C,) spread of the calibration signal per channel (x, y, z)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        J = len(self.joint_names)
        for name in ("exponent", "tau_up_s", "tau_down_s", "min_speed"):
            value = np.asarray(getattr(self, name), float).reshape(-1)
            if value.shape != (J,) or not np.all(np.isfinite(value)) or np.any(value < 0):
                raise ModelFileError(f"harmonic map: {name} must hold {J} finite values >= 0")
            set_(self, name, value)
        if np.any(self.exponent <= 0) or np.any(self.exponent > 4):
            raise ModelFileError("harmonic map: exponents must lie in (0, 4]")
        line_joint = np.asarray(self.line_joint, np.int64).reshape(-1)
        coefficient = np.asarray(self.line_coefficient, float).reshape(-1)
        score = np.asarray(self.line_score_db, float).reshape(-1)
        if not (len(line_joint) == len(coefficient) == len(score)):
            raise ModelFileError("harmonic map: one joint, coefficient and score per line")
        if np.any(line_joint < 0) or np.any(line_joint >= J):
            raise ModelFileError("harmonic map: a line names a joint that does not exist")
        if not np.all(np.isfinite(coefficient)) or np.any(coefficient <= 0):
            raise ModelFileError("harmonic map: line coefficients must be finite and > 0")
        rms = np.asarray(self.residual_rms, float).reshape(-1)
        if not np.all(np.isfinite(rms)) or np.any(rms < 0):
            raise ModelFileError("harmonic map: residual_rms must be finite and >= 0")
        set_(self, "line_joint", line_joint)
        set_(self, "line_coefficient", coefficient)
        set_(self, "line_score_db", score)
        set_(self, "residual_rms", rms)
        set_(self, "joint_names", tuple(str(n) for n in self.joint_names))

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_lines(self) -> int:
        return len(self.line_coefficient)

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        return {prefix + f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_arrays(cls, arrays: dict, prefix: str, *, where: str = "model") -> "HarmonicMap":
        try:
            values = {f.name: arrays[prefix + f.name] for f in fields(cls)}
        except KeyError as exc:
            raise ModelFileError(f"{where}: harmonic map lacks {exc.args[0]!r}") from None
        values["joint_names"] = tuple(str(n) for n in np.asarray(values["joint_names"]).reshape(-1))
        try:
            return cls(**values)
        except ModelFileError as exc:
            raise ModelFileError(f"{where}: {exc}") from None

    def describe(self) -> dict:
        lines = [
            {
                "joint": self.joint_names[int(self.line_joint[q])],
                "coefficient_hz": round(float(self.line_coefficient[q]), 3),
                "score_db": round(float(self.line_score_db[q]), 1),
            }
            for q in range(self.n_lines)
        ]
        return {
            "form": "f = coefficient * lag(|v|)**exponent * (1 + correction)",
            "exponent": self.exponent.round(3).tolist(),
            "tau_up_ms": (1e3 * self.tau_up_s).round(1).tolist(),
            "tau_down_ms": (1e3 * self.tau_down_s).round(1).tolist(),
            "lines": lines,
        }


# --- Fitting the map from a no-contact recording (free motion or a sweep) -----------------
def _pieces(n: int, total: int, piece: int) -> np.ndarray:
    """Mask of evenly spaced pieces of `piece` samples adding up to at most `total` of n."""
    if n <= total:
        return np.ones(n, bool)
    keep = np.zeros(n, bool)
    count = max(1, total // piece)
    for start in np.linspace(0, n - piece, count).astype(np.int64):
        keep[start : start + piece] = True
    return keep


def _window_spectra(
    x: np.ndarray,
    speed: np.ndarray,
    min_speed: np.ndarray,
    window: int,
    nfft: int,
    fs: float,
    band_hz,
):
    """Log spectra of windows (hop window/2), summed over channels, relative to a floor:
    the running median over ~1/6 of the band, or, where higher, the mean spectrum of the
    windows in which no joint moves (lines that are there at rest - a fan's hum - are
    background, whatever the joints do). Returns (window starts, (W, F) log ratios, freqs)."""
    hop = window // 2
    starts = np.arange(0, len(x) - window + 1, hop)
    taper = np.hanning(window)
    freqs = np.fft.rfftfreq(nfft, 1.0 / fs)
    power = np.zeros((len(starts), len(freqs)))
    index = starts[:, None] + np.arange(window)[None, :]
    for first in range(0, len(starts), 256):  # bounded memory
        rows = index[first : first + 256]
        for c in range(x.shape[1]):
            frames = x[rows, c]
            frames = frames - frames.mean(axis=1, keepdims=True)
            power[first : first + 256] += np.abs(np.fft.rfft(frames * taper, nfft, axis=1)) ** 2
    band = (freqs >= band_hz[0]) & (freqs <= band_hz[1])
    width = max(3, int(round((band_hz[1] - band_hz[0]) / 6 / (freqs[1] - freqs[0]))) | 1)
    floor = median_filter(power, size=(1, width), mode="nearest") + 1e-30
    at_rest = np.all(speed[starts + window // 2] <= min_speed[None, :], axis=1)
    if np.count_nonzero(at_rest) >= 5:
        floor = np.maximum(floor, power[at_rest].mean(axis=0)[None, :])
    ratio = np.log(power / floor + 1e-12)
    ratio[:, ~band] = 0.0
    return starts, ratio, freqs


def _strongest_lines(
    ratio, starts, freqs, speed, window, fs, band_hz, min_speed
) -> list[tuple[float, float, float, int]]:
    """Per joint: (score, exponent, coefficient, steady windows) of its strongest line.

    In windows where joint j moves steadily, the spectrum's log height above its local
    floor is read at fold(c * s**p) for a grid of coefficients c; a line of that joint is
    a coefficient scoring high in every such window (lines of other joints move
    differently and average out)."""
    df = freqs[1] - freqs[0]
    out = []
    curves = []
    for j in range(speed.shape[1]):
        seg = speed[starts[:, None] + np.arange(window), j]  # (windows, window)
        mean_speed = seg.mean(axis=1)
        steady = (seg.std(axis=1) <= 0.05 * np.maximum(mean_speed, 1e-12)) & (
            mean_speed > min_speed[j]
        )
        best = (0.0, 1.0, 0.0, int(steady.sum()))
        curve = (np.ones(1), np.zeros(1))
        g_all = mean_speed[steady]
        if len(g_all) < 5:
            out.append(best)
            curves.append(curve)
            continue
        rows = ratio[steady]
        for p in EXPONENTS:
            g = g_all**p
            # Lines up to 1.5 x the sample rate (folded once or twice: a log decimated
            # without anti-aliasing); beyond, coincidences of folding would pass for lines.
            coefficients = np.exp(
                np.arange(math.log(band_hz[0] / g.max()), math.log(1.5 * fs / g.max()), 0.003)
            )
            f = fold(coefficients[None, :] * g[:, None], fs)  # (W, K)
            inside = (f >= band_hz[0]) & (f <= band_hz[1])
            idx = np.clip(np.rint(f / df).astype(np.int64), 0, ratio.shape[1] - 1)
            values = np.take_along_axis(rows, idx, axis=1)
            count = inside.sum(axis=0)
            score = np.where(
                count >= max(5, 0.2 * len(g)),
                (values * inside).sum(axis=0) / np.maximum(count, 1),
                0.0,
            )
            q = int(np.argmax(score))
            if score[q] > best[0]:
                best = (float(score[q]), p, float(coefficients[q]), int(steady.sum()))
                curve = (coefficients, score)
        out.append(best)
        curves.append(curve)
    return out, curves


def fit_harmonic_map(
    x: np.ndarray,
    speed: np.ndarray,
    *,
    sample_rate_hz: float,
    band_hz: tuple[float, float],
    joint_names: tuple[str, ...],
    max_speed: np.ndarray,
    settings: "CancellerSettings | None" = None,
    max_seconds: float = 20.0,
) -> tuple[HarmonicMap, dict]:
    """Fit the speed -> line-frequency map on no-contact data (free motion or a sweep):
    (map, info). x: (N, C) band-passed channels; speed: (N, J) joint velocity held on the
    same samples. Per joint, the strongest line and the exponent from the spectra of steady
    windows (`_strongest_lines`), then the map refined on the canceller's own residual on
    at most `max_seconds` of the recording (`_MapSearch`: the constants above)."""
    x = np.asarray(x, float)
    if x.ndim == 1:
        x = x[:, None]
    speed = np.abs(np.asarray(speed, float))
    fs = float(sample_rate_hz)
    n = len(speed)
    if len(x) != n:
        raise ConfigError(f"fit_harmonic_map: {len(x)} sensor samples but {n} speed samples")
    settings = settings or CancellerSettings()
    max_speed = np.asarray(max_speed, float).reshape(-1)
    x = np.ascontiguousarray(x)
    speed = np.ascontiguousarray(speed)
    min_speed = 0.05 * max_speed
    residual_rms = np.sqrt(np.mean(x**2, axis=0)) if n else np.zeros(x.shape[1])
    window = int(2 ** round(math.log2(0.128 * fs)))
    # Spectra of at most SPECTRA_SECONDS (pieces of 8 windows spread over the recording).
    keep = _pieces(n, int(SPECTRA_SECONDS * fs), 8 * window)
    starts, ratio, freqs = _window_spectra(
        x[keep], speed[keep], min_speed, window, 4 * window, fs, band_hz
    )
    strongest, curves = _strongest_lines(
        ratio, starts, freqs, speed[keep], window, fs, band_hz, min_speed
    )
    # The refinement runs the canceller on at most `max_seconds` (0.5 s pieces spread over
    # the recording: a sweep keeps every cell).
    keep = _pieces(n, int(max_seconds * fs), int(0.5 * fs))
    # Each step's trials run side by side, a thread per core (the kernel releases the GIL):
    # the same costs, hence the same choices, as one after the other.
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    with ThreadPoolExecutor(cores or 1) as pool:
        # Without the frequency correction (it would make up for a wrong map and flatten the
        # cost) nor the guard (it would hide the bursts a wrong map makes).
        settings = dataclasses.replace(settings, pll_hz=0.0, guard_ms=0.0)
        x, speed = np.ascontiguousarray(x[keep]), np.ascontiguousarray(speed[keep])
        fixed = (fs, band_hz, tuple(joint_names), min_speed, residual_rms, settings)
        search = _MapSearch(x, speed, *fixed, _first_joints(strongest, curves), pool.map)
        search.refine()
    return search.result()


_DB = 10.0 / math.log(10.0)


def _first_joints(strongest, curves) -> list[dict]:
    """The map as lists per joint (what the search changes): orders relative to the
    strongest line (none below MIN_SCORE_DB), coefficient c, exponent p, speed-up and
    slow-down lags, and the orders worth trying (those standing highest in the spectra)."""
    joints = []
    for j, (score, p, coefficient, _) in enumerate(strongest):
        has = score * _DB >= MIN_SCORE_DB
        grid, curve = curves[j]
        ranked = []
        for order in ORDERS if has else ():
            near = np.abs(np.log(grid / (order * coefficient))) <= 0.01
            if near.any():
                ranked.append((float(curve[near].max()), order))
        candidates = [o for _, o in sorted(ranked, reverse=True)[:ORDER_CANDIDATES]]
        joints.append(
            {
                "orders": [1.0] if has else [],
                "c": coefficient,
                "p": p,
                "up": 0.02,
                "down": 0.02,
                "score": score * _DB,
                "candidates": candidates,
            }
        )
    return joints


class _MapSearch:
    """fit_harmonic_map's greedy search: `joints` (per joint: orders, c, p, up, down) are
    changed where that lowers the canceller's mean residual power on `x` (the first 10 %
    left out while the trackers settle) by MIN_GAIN_DB. Per joint in turn (`refine`): the
    line order that lowers it most while one does, the coefficients' scale, the exponent
    (the frequency at the median speed kept), the speed-up and slow-down lags; ROUNDS times."""

    def __init__(
        self, x, speed, fs, band_hz, joint_names, min_speed, rms, settings, joints, trials
    ):
        self.x, self.speed, self.fs, self.band_hz = x, speed, fs, band_hz
        self.joint_names, self.min_speed, self.residual_rms = joint_names, min_speed, rms
        self.settings = settings
        self.map_trials = trials  # map(cost, trials): a thread pool's
        self.settle = len(x) // 10
        self.joints = joints
        self.evaluations = 0
        self.current = self.start_cost = self.cost(joints)
        self.alike = False

    def build(self, joints) -> HarmonicMap:
        lj, lc = [], []
        for j, d in enumerate(joints):
            lj += [j] * len(d["orders"])
            lc += [o * d["c"] for o in d["orders"]]
        return HarmonicMap(
            joint_names=self.joint_names,
            exponent=np.array([d["p"] for d in joints]),
            tau_up_s=np.array([d["up"] for d in joints]),
            tau_down_s=np.array([d["down"] for d in joints]),
            min_speed=self.min_speed,
            line_joint=np.array(lj, np.int64),
            line_coefficient=np.array(lc, float),
            line_score_db=np.zeros(len(lc)),
            residual_rms=self.residual_rms,
        )

    def cost(self, joints) -> float:
        canceller = HarmonicCanceller(
            self.build(joints),
            sample_rate_hz=self.fs,
            band_hz=self.band_hz,
            n_channels=self.x.shape[1],
            settings=self.settings,
        )
        r = canceller.process(self.x, self.speed)[self.settle :]
        return float(np.mean(r**2)) + 1e-300

    def try_all(self, changes) -> bool:
        """changes: list of {joint: {field: value}}; keep the best if it gains enough (each
        trial its own canceller, through `map_trials`)."""
        trials = [
            [dict(d, **change.get(j, {})) for j, d in enumerate(self.joints)] for change in changes
        ]
        values = list(self.map_trials(self.cost, trials))
        self.evaluations += len(trials)
        best = None
        for value, trial in zip(values, trials):
            if best is None or value < best[0]:
                best = (value, trial)
        if best is not None and _DB * math.log(self.current / best[0]) >= MIN_GAIN_DB:
            self.current, self.joints = best
            return True
        return False

    def refine(self) -> None:
        joints = self.joints
        with_lines = [j for j, d in enumerate(joints) if d["orders"]]
        if len(with_lines) > 1:
            # Alike actuators (a multirotor's motors): every joint with the best joint's line.
            best_j = max(with_lines, key=lambda j: joints[j]["score"])
            shared = [
                dict(d, c=joints[best_j]["c"], p=joints[best_j]["p"]) if d["orders"] else dict(d)
                for d in joints
            ]
            value = self.cost(shared)
            self.evaluations += 1
            if value < self.current:
                self.current, self.joints, self.alike = value, shared, True
        speed, min_speed = self.speed, self.min_speed
        moving = [speed[:, j] > min_speed[j] for j in range(speed.shape[1])]
        median_speed = [
            float(np.median(speed[m, j])) if m.any() else 1.0 for j, m in enumerate(moving)
        ]
        # Alike actuators are refined together first, then each on its own.
        groups = ([with_lines] if self.alike else []) + [[j] for j in with_lines]
        for _ in range(ROUNDS):
            for group in groups:
                self._add_lines(group)
                self._scale(group, median_speed)
                self.try_all([{j: {"up": tau} for j in group} for tau in LAGS_S])
                self.try_all([{j: {"down": tau} for j in group} for tau in LAGS_S])

    def _add_lines(self, group) -> None:
        """The line order that lowers the residual most, while one does."""
        joints = self.joints
        while max(len(joints[j]["orders"]) for j in group) < MAX_LINES_PER_JOINT:
            tried = sorted({o for j in group for o in (1.0, *joints[j]["candidates"])})
            missing = [o for o in tried if all(o not in joints[j]["orders"] for j in group)]
            if not self.try_all(
                [{j: {"orders": joints[j]["orders"] + [o]} for j in group} for o in missing]
            ):
                break
            joints = self.joints

    def _scale(self, group, median_speed) -> None:
        """The coefficients' scale, then the exponent with it (the frequency at the median
        speed kept, then +-3 %)."""
        for per, most in ((100, 10), (400, 4)):  # scale: +-10 % by 1 %, then +-1 % by 0.25 %
            self.try_all(
                [
                    {j: {"c": self.joints[j]["c"] * (1 + k / per)} for j in group}
                    for k in range(-most, most + 1)
                    if k
                ]
            )
        joints = self.joints
        self.try_all(
            [
                {
                    j: {
                        "p": p,
                        "c": joints[j]["c"]
                        * median_speed[j] ** (joints[j]["p"] - p)
                        * (1 + k / 200),
                    }
                    for j in group
                }
                for p in EXPONENTS
                if p != joints[group[0]]["p"]
                for k in range(-6, 7)
            ]
        )

    def _below_input_db(self, residual: float) -> float:
        if len(self.x) <= self.settle:
            return 0.0
        return round(_DB * math.log(float(np.mean(self.x[self.settle :] ** 2)) / residual), 2)

    def result(self) -> tuple[HarmonicMap, dict]:
        """(the map, what the search found)."""
        joints, names = self.joints, self.joint_names
        info = {
            "residual_db": self._below_input_db(self.current),
            "start_residual_db": self._below_input_db(self.start_cost),
            "evaluations": self.evaluations,
            "seconds_used": round(len(self.x) / self.fs, 1),
            "alike_joints": self.alike,
            "joints": {
                # Orders relative to the joint's lowest line (its "fundamental").
                names[j]: {
                    "orders": sorted(round(o / min(d["orders"]), 4) for o in d["orders"])
                    if d["orders"]
                    else [],
                    "coefficient_hz": round(d["c"] * min(d["orders"]), 2) if d["orders"] else None,
                    "exponent": d["p"],
                    "tau_up_ms": 1e3 * d["up"],
                    "tau_down_ms": 1e3 * d["down"],
                    "strongest_line_db": round(d["score"], 1),
                }
                for j, d in enumerate(joints)
            },
        }
        scores = np.concatenate([[d["score"]] * len(d["orders"]) for d in joints])
        return dataclasses.replace(self.build(joints), line_score_db=scores), info


# --- The canceller ------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class CancellerSettings:
    """tracking_hz: each line tracker's bandwidth (LMS step 2 pi tracking_hz / fs); pll_hz:
    natural frequency of each joint's PLL (0: the map alone), pll_damping its damping;
    max_correction: bound of the relative frequency correction; clip_sigma: the error is
    clipped at this many running spreads, spread_s that spread's time constant; guard_ms:
    time constant of the guard's short-time powers (0: no guard)."""

    tracking_hz: float = 8.0
    pll_hz: float = 2.0
    pll_damping: float = 1.0
    max_correction: float = 0.2
    clip_sigma: float = 2.5
    spread_s: float = 0.2
    guard_ms: float = 3.0

    def __post_init__(self) -> None:
        checks = (
            ("tracking_hz", 0.0, 1000.0),
            ("pll_hz", 0.0, 100.0),
            ("pll_damping", 0.05, 10.0),
            ("max_correction", 0.0, 0.5),
            ("clip_sigma", 0.5, 100.0),
            ("spread_s", 1e-3, 100.0),
            ("guard_ms", 0.0, 1000.0),
        )
        check_ranges(self, checks, "canceller: ")

    def gains(self, sample_rate_hz: float) -> tuple[float, float, float, float, float]:
        """(LMS step, PLL proportional gain, PLL integral gain, spread rate, guard rate)
        per sample (guard rate 0: no guard)."""
        mu = TWO_PI * self.tracking_hz / sample_rate_hz
        wn = TWO_PI * self.pll_hz / sample_rate_hz
        return (
            mu,
            2.0 * self.pll_damping * wn,
            wn * wn,
            1.0 - math.exp(-1.0 / (self.spread_s * sample_rate_hz)),
            1.0 - math.exp(-1.0 / (self.guard_ms * 1e-3 * sample_rate_hz))
            if self.guard_ms > 0
            else 0.0,
        )


@numba.njit(cache=True, inline="always")
def _cos_sin_turns(t):
    """(cos, sin) of 2 pi t, t in turns: reduced to a quarter turn, then the Taylor
    polynomials to y^10 on |y| <= pi/4 (error < 3e-9, far below any line's precision);
    libm's pair per line and sample was a fifth of the canceller's time."""
    k = math.floor(4.0 * t + 0.5)
    y = TWO_PI * (t - 0.25 * k)
    y2 = y * y
    s = y * (1.0 + y2 * (-1.0 / 6.0 + y2 * (1.0 / 120.0 + y2 * (-1.0 / 5040.0 + y2 / 362880.0))))
    c = 1.0 + y2 * (
        -0.5 + y2 * (1.0 / 24.0 + y2 * (-1.0 / 720.0 + y2 * (1.0 / 40320.0 - y2 / 3628800.0)))
    )
    quadrant = int(k) & 3
    if quadrant == 0:
        return c, s
    if quadrant == 1:
        return -s, c
    if quadrant == 2:
        return -c, -s
    return s, -c


@numba.njit(cache=True, fastmath=True, nogil=True)  # nogil: the map search runs it in threads
def _cancel_kernel(x, speed, known, fs, hmap, gains, band, w, inverse, st, out, raw_lines):  # noqa: C901 (numba per-sample loop: one pass, no calls)
    """One pass over (n, C) band-passed samples; every state array is updated in place.
    out[i, c] = x[i, c] - predicted lines (scaled down where they would make the signal
    louder). See the module docstring. With `w` (n, C) (else an empty array): the same
    channels unfiltered (gravity and slow motion taken out), in which the same lines are
    tracked by weights of their own (`weights_w`) on the same references: raw_lines[i, c] =
    the lines as the unfiltered signal carries them, scaled as `out`'s and by a guard of
    their own (`power_w`: short-time powers of w and of w less its lines).

    `hmap`, `gains`, `band`, `st`: tuples of the map's arrays, the gains, the band's edges
    and the state's arrays (CancellerState's fields), unpacked below.

    One function: numba compiles it into one pass per sample over every line and channel,
    no call per sample."""
    exponent, tau_up, tau_down, min_speed, line_joint, line_coef = hmap
    mu, kp, ki, bound, clip, spread_rate, guard_rate = gains
    f_lo, f_hi = band
    lagged, correction, theta, weights, spread2, power_in, power_residual, weights_w, power_w = st
    n, C = x.shape
    J = speed.shape[1]
    L = line_coef.shape[0]
    a_up = np.empty(J)
    a_dn = np.empty(J)
    for j in range(J):
        a_up[j] = 1.0 - math.exp(-1.0 / (fs * tau_up[j])) if tau_up[j] > 0 else 1.0
        a_dn[j] = 1.0 - math.exp(-1.0 / (fs * tau_down[j])) if tau_down[j] > 0 else 1.0
    g = np.empty(J)
    pd_num = np.empty(J)
    pd_den = np.empty(J)
    active = np.zeros(L, np.bool_)
    cosv = np.empty(L)
    sinv = np.empty(L)
    nyquist = 0.5 * fs
    raw = w.shape[0] == n
    G = inverse.shape[0]
    inv_re = np.ones(L)
    inv_im = np.zeros(L)
    for i in range(n):
        for j in range(J):
            v = abs(speed[i, j]) if known[i] else lagged[j]  # no joint state: hold the speed
            lagged[j] += (a_up[j] if v > lagged[j] else a_dn[j]) * (v - lagged[j])
            s = lagged[j]
            g[j] = s ** exponent[j] if s > min_speed[j] else 0.0
            pd_num[j] = 0.0
            pd_den[j] = 0.0
        for q in range(L):
            j = line_joint[q]
            rate = line_coef[q] * g[j] * (1.0 + correction[j])  # Hz, unfolded
            folded = rate - fs * math.floor(rate / fs)
            mirrored = folded > nyquist
            if mirrored:
                folded = fs - folded
            active[q] = g[j] > 0.0 and folded >= f_lo and folded <= f_hi
            if raw and active[q] and G > 1:
                # the inverse of w's filter at the line (a mirrored line: its conjugate)
                k = int(folded / nyquist * (G - 1) + 0.5)
                inv_re[q] = inverse[k, 0]
                inv_im[q] = -inverse[k, 1] if mirrored else inverse[k, 1]
            t = theta[q] + rate / fs
            theta[q] = t - math.floor(t)
            cosv[q], sinv[q] = _cos_sin_turns(theta[q])
        for c in range(C):
            estimate = 0.0
            unfiltered = 0.0
            tracked = 0.0
            for q in range(L):
                if active[q]:
                    estimate += weights[c, q, 0] * cosv[q] + weights[c, q, 1] * sinv[q]
                    if raw:
                        wa = weights_w[c, q, 0]
                        wb = weights_w[c, q, 1]
                        tracked += wa * cosv[q] + wb * sinv[q]
                        # Re[(wa - j wb) / F e^{j phase}]
                        pr = wa * inv_re[q] + wb * inv_im[q]
                        pi = wa * inv_im[q] - wb * inv_re[q]
                        unfiltered += pr * cosv[q] - pi * sinv[q]
            e = x[i, c] - estimate
            scale = 1.0
            if guard_rate > 0.0:
                power_in[c] += guard_rate * (x[i, c] * x[i, c] - power_in[c])
                power_residual[c] += guard_rate * (e * e - power_residual[c])
                if power_residual[c] > power_in[c]:
                    scale = math.sqrt(power_in[c] / power_residual[c])
            out[i, c] = e if scale == 1.0 else x[i, c] - estimate * scale
            limit = clip * math.sqrt(spread2[c])
            ec = min(max(e, -limit), limit)
            if raw:
                # The unfiltered lines' own guard: where subtracting them would make the
                # unfiltered signal louder (lines jumping faster than their trackers follow:
                # a crash's commands), they are scaled down as the band's are.
                ew = w[i, c] - tracked
                scale_w = scale
                if guard_rate > 0.0:
                    power_w[c, 0] += guard_rate * (w[i, c] * w[i, c] - power_w[c, 0])
                    power_w[c, 1] += guard_rate * (ew * ew - power_w[c, 1])
                    if power_w[c, 1] > power_w[c, 0]:
                        scale_w = min(scale, math.sqrt(power_w[c, 0] / power_w[c, 1]))
                raw_lines[i, c] = unfiltered * scale_w
                # The unfiltered lines' own trackers, their error shrunk as the band's is
                # clipped (an event in the band slows both alike; no clipping of their own,
                # which would turn slow motion into noise at the lines).
                if ec != e:
                    ew *= ec / e
                for q in range(L):
                    if active[q]:
                        weights_w[c, q, 0] += mu * ew * cosv[q]
                        weights_w[c, q, 1] += mu * ew * sinv[q]
            spread2[c] += spread_rate * (ec * ec - spread2[c])
            for q in range(L):
                if active[q]:
                    wa = weights[c, q, 0]
                    wb = weights[c, q, 1]
                    j = line_joint[q]
                    # d(estimate)/d(joint phase): line phase = coefficient * joint phase.
                    k = TWO_PI * line_coef[q]
                    pd_num[j] += ec * k * (wb * cosv[q] - wa * sinv[q])
                    pd_den[j] += 0.5 * k * k * (wa * wa + wb * wb)
                    weights[c, q, 0] = wa + mu * ec * cosv[q]
                    weights[c, q, 1] = wb + mu * ec * sinv[q]
        if kp > 0.0:
            noise = 0.0
            for c in range(C):
                noise += spread2[c]
            for j in range(J):
                if g[j] > 0.0 and pd_den[j] > 0.0:
                    # Phase error of joint j (in joint-phase units), shrunk when its lines are weak.
                    err = pd_num[j] / (pd_den[j] + noise)
                    for q in range(L):
                        if line_joint[q] == j:
                            t = theta[q] + kp * err * line_coef[q]
                            theta[q] = t - math.floor(t)
                    correction[j] += ki * err * fs / g[j]
                    if correction[j] > bound:
                        correction[j] = bound
                    elif correction[j] < -bound:
                        correction[j] = -bound
    return out


@dataclass
class CancellerState:
    """Everything the canceller carries between chunks."""

    lagged: np.ndarray  # (J,) lagged speed
    correction: np.ndarray  # (J,) relative frequency correction
    theta: np.ndarray  # (L,) line phase, cycles
    weights: np.ndarray  # (C, L, 2) cos/sin weights
    spread2: np.ndarray  # (C,) running robust error variance
    power_in: np.ndarray  # (C,) short-time power of the input (the guard)
    power_residual: np.ndarray  # (C,) short-time power of the full residual (the guard)
    weights_w: np.ndarray  # (C, L, 2) cos/sin weights of the lines in the unfiltered signal
    power_w: np.ndarray  # (C, 2) short-time powers of the unfiltered input and of it less its lines

    def arrays(self) -> tuple:
        """The arrays in field order, as the kernel unpacks them (not copied: it updates them).
        The instance dict holds exactly the fields, in order (a per-batch call: `fields()`
        cost more than the kernel on a live node's few samples)."""
        return tuple(vars(self).values())


class HarmonicCanceller:
    """Streaming harmonic canceller for C channels keyed on J joint speeds.

    process(x (n, C), speed (n, J)) -> residual (n, C); speed NaN = hold the last one.
    The state is explicit (`state`), so any chunking gives the result of one call."""

    def __init__(
        self,
        hmap: HarmonicMap,
        *,
        sample_rate_hz: float,
        band_hz: tuple[float, float],
        n_channels: int,
        settings: CancellerSettings | None = None,
        unfiltered_inverse: np.ndarray | None = None,
    ):
        """`band_hz`: the band the input was band-passed to, where lines are tracked."""
        self.map = hmap
        self.settings = settings or CancellerSettings()
        self.sample_rate_hz = float(sample_rate_hz)
        self.band_hz = (float(band_hz[0]), float(band_hz[1]))
        self.n_channels = int(n_channels)
        # 1 / F on a grid 0..Nyquist, F the filter the unfiltered input went through
        self.unfiltered_inverse = (
            np.zeros((1, 2)) if unfiltered_inverse is None else np.asarray(unfiltered_inverse)
        )
        # (pll_hz 0: both PLL gains are 0, the map alone)
        mu, kp, ki, spread_rate, guard_rate = self.settings.gains(self.sample_rate_hz)
        bound, clip = float(self.settings.max_correction), float(self.settings.clip_sigma)
        self._gains = (mu, kp, ki, bound, clip, spread_rate, guard_rate)  # the kernel's order
        rms = float(np.mean(hmap.residual_rms)) if hmap.residual_rms.size else 1.0
        spread = np.full(self.n_channels, rms)
        self._initial_spread2 = np.maximum(spread, 1e-12) ** 2
        self.state = self.initial_state()

    def initial_state(self) -> CancellerState:
        J, L = self.map.n_joints, self.map.n_lines
        return CancellerState(
            lagged=np.zeros(J),
            correction=np.zeros(J),
            theta=np.zeros(L),
            weights=np.zeros((self.n_channels, L, 2)),
            spread2=self._initial_spread2.copy(),
            power_in=np.zeros(self.n_channels),
            power_residual=np.zeros(self.n_channels),
            weights_w=np.zeros((self.n_channels, L, 2)),
            power_w=np.zeros((self.n_channels, 2)),
        )

    def with_map(self, hmap: HarmonicMap) -> "HarmonicCanceller":
        """The same canceller on another map, mid-stream: the joints' lagged speeds and the
        error's spread and guard powers carried over; the lines (all new) start from nothing."""
        other = HarmonicCanceller(
            hmap,
            sample_rate_hz=self.sample_rate_hz,
            band_hz=self.band_hz,
            n_channels=self.n_channels,
            settings=self.settings,
            unfiltered_inverse=self.unfiltered_inverse,
        )
        for name in ("lagged", "spread2", "power_in", "power_residual", "power_w"):
            getattr(other.state, name)[:] = getattr(self.state, name)
        return other

    def process(self, x: np.ndarray, speed: np.ndarray, *, unfiltered: np.ndarray | None = None):
        """(n, C) band-passed samples and (n, J) speeds -> the residual (n, C). With
        `unfiltered` (n, C), the same samples before the band-pass (gravity and slow motion
        taken out): also the lines as they reach it, tracked there on the same references
        (the drop-in output subtracts them): (residual, lines)."""
        raw = unfiltered is not None
        x = np.ascontiguousarray(x, dtype=np.float64)
        speed = np.ascontiguousarray(speed, dtype=np.float64)
        if (
            x.ndim != 2
            or x.shape[1] != self.n_channels
            or speed.shape != (len(x), self.map.n_joints)
        ):
            raise ConfigError(
                f"canceller: expected ({len(x)}, {self.n_channels}) samples and "
                f"({len(x)}, {self.map.n_joints}) speeds, got {x.shape} and {speed.shape}"
            )
        out = np.empty_like(x)
        w = np.ascontiguousarray(unfiltered, dtype=np.float64) if raw else np.empty((0, x.shape[1]))
        if raw and w.shape != x.shape:
            raise ConfigError(f"canceller: unfiltered samples {w.shape} differ from {x.shape}")
        lines = np.empty_like(w)
        if len(x) == 0:
            return (out, lines) if raw else out
        known = np.all(np.isfinite(speed), axis=1)
        if not known.all():
            speed = np.where(known[:, None], speed, 0.0)
        m = self.map
        hmap = (m.exponent, m.tau_up_s, m.tau_down_s, m.min_speed, m.line_joint, m.line_coefficient)
        state = self.state.arrays()
        fixed = (self.sample_rate_hz, hmap, self._gains, self.band_hz, w, self.unfiltered_inverse)
        _cancel_kernel(x, speed, known, *fixed, state, out, lines)
        return (out, lines) if raw else out
