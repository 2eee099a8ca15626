"""Sensor streams stamped on receipt.

A driver that stamps each message as it receives it (a USB or serial IMU read a packet at
a time) gives stamps trailing the sample times by a varying latency: steps of 0 to several
periods, which step by step read as lost samples and a wrong rate. Such a stream is told on
its first samples (`receipt_latency`) and judged against a sample clock rebuilt from the
sample count and the stamps' lower envelope (`ReceiptClock`: a gap is a stamp later than
any latency seen by 1.5 periods); its rate on the least late samples (`envelope_period`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: More than this share of steps shorter than half a period: stamps taken on receipt. A sensor
#: sampling on its own clock never gives them (lost samples only lengthen steps), and a step
#: jitter of +-30 % never reaches them.
RECEIPT_SHORT_STEPS = 0.01
#: Per sample, the rebuilt clock moves this share of a sample's lateness towards the stamps: it
#: follows a sensor clock a little off the nominal rate, which would otherwise read as gaps.
RECEIPT_LEAK = 1.0 / 64.0
#: Per sample, the latency bound forgets this share of itself (half-life ~7000 samples).
RECEIPT_FORGET = 1e-4
#: Samples in the first rate window of receipt stamps (2 ms of latency at 3 kHz: within 1 %).
RECEIPT_FIRST_WINDOW = 512


def receipt_latency(
    stamps_ns: np.ndarray, period_ns: float, *, known: bool = False
) -> float | None:
    """The latency spread (ns) of receipt stamps, from a stream's first in-order stamps;
    None when they mark sample times (steps of a period or whole periods more). `known`:
    they are receipt times, only the spread is asked."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if len(stamps) < (2 if known else 16):
        return 0.0 if known else None
    steps = np.diff(stamps)
    if not known and np.count_nonzero(steps < 0.5 * period_ns) <= RECEIPT_SHORT_STEPS * len(steps):
        return None
    count_period = (stamps[-1] - stamps[0]) / (len(stamps) - 1)
    late = (stamps - stamps[0]) - np.arange(len(stamps)) * count_period
    return float(late.max() - late.min())


def envelope_period(stamps_ns: np.ndarray, period_ns: float) -> float:
    """The sample period a window of receipt stamps shows (-1, a bridged sample: left out):
    the slope between the least late stamps of its halves (nearest their samples; the mean
    step would carry the ends' latencies), over the samples received between them (not
    the clock's guesses of lost ones, which would bridge a wrong rate into the right one)."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    stamps = stamps[stamps >= 0]
    half = len(stamps) // 2
    if half == 0:
        return float(period_ns)
    position = np.arange(len(stamps))
    estimate = float(period_ns)
    for _ in range(2):  # again with the first estimate: a clock off nominal tilts "least late"
        late = stamps - position * estimate
        i = int(np.argmin(late[:half]))
        j = half + int(np.argmin(late[half:]))
        estimate = float(stamps[j] - stamps[i]) / float(j - i)
    return estimate


class ReceiptClock:
    """The sample clock of a stream stamped on receipt, carried across chunks: `gaps(stamps)`
    gives, per in-order sample, the samples missing before it and its rebuilt time."""

    def __init__(self, period_ns: float, latency_ns: float, max_fill: int):
        self.period = float(period_ns)
        self.max_fill = int(max_fill)
        self.first_latency_ns = float(latency_ns)  # as the first samples showed it (fixed)
        self.origin: int | None = None  # ns; the clock runs in float ns after it (precision)
        # [rebuilt time of the last sample - origin, latency bound, anchored 0/1]
        self.state = np.array([0.0, float(latency_ns), 0.0])

    def restart(self) -> None:
        """A new segment (first sample, a clock jump): the next stamp anchors the clock."""
        self.state[2] = 0.0

    def rate_window(self, samples: int, *, first: bool) -> int:
        """Samples per rate window (at least `samples`): the first RECEIPT_FIRST_WINDOW, so
        the least late stamps of each half lie near their samples; every half at least two
        latencies (as the first samples showed it: any chunking cuts the same windows)."""
        need = max(samples, RECEIPT_FIRST_WINDOW if first else 0)
        return max(need, 4 * math.ceil(self.first_latency_ns / self.period))

    def gaps(self, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(missing (N,) int64, rebuilt times (N,) int64) for in-order stamps (N,)."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        if self.origin is None and len(stamps_ns):
            self.origin = int(stamps_ns[0])
        missing = np.zeros(len(stamps_ns), dtype=np.int64)
        offsets = np.zeros(len(stamps_ns))
        stamps = (stamps_ns - (self.origin or 0)).astype(np.float64)
        rates = (self.period, RECEIPT_LEAK, 1.0 - RECEIPT_FORGET, self.max_fill)
        _receipt_kernel(stamps, *rates, self.state, missing, offsets)
        return missing, np.rint(offsets).astype(np.int64) + (self.origin or 0)


@numba.njit(cache=True)
def _receipt_kernel(stamps, period, leak, keep, max_fill, state, missing, times):
    # Per sample (numba: a stream at kHz rates). grid: rebuilt time of the last sample;
    # spread: how late stamps have been recently. A stamp more than the spread and 1.5
    # periods beyond the next sample's time is late by lost samples (fewer are not told from
    # latency); one earlier than it moves the clock back (stamps never come before their
    # sample: the clock follows their lower envelope).
    grid, spread, anchored = state[0], state[1], state[2] > 0.0
    for k in range(len(stamps)):
        s = stamps[k]
        m = 0
        if not anchored:
            grid, anchored = s, True
        else:
            r = s - (grid + period)
            if r > spread + 1.5 * period:
                m = max(1, int(math.floor((r - 0.5 * spread) / period + 0.5)))
            if m > max_fill:
                grid = s  # a long gap: the segment restarts at this sample
            else:
                grid += (m + 1) * period
                late = s - grid
                if late < 0.0:
                    grid, late = s, 0.0
                else:
                    grid += leak * late
                spread = max(late, spread * keep)
        missing[k] = m
        times[k] = grid
    state[0], state[1], state[2] = grid, spread, 1.0 if anchored else 0.0
