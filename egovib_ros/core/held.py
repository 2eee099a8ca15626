"""Which held input samples the core's output samples are: the core outputs a subsequence
of its input (it drops out-of-order and bad samples, never outputs gap fill); a consumer
pairing each output with its input message (the drop-in output, live and offline) holds
the input stamps in feeding order and asks which rows the output stamps are.
"""

from __future__ import annotations

import numpy as np


def output_rows(held_stamps: np.ndarray, out_stamps: np.ndarray) -> np.ndarray:
    """Rows of `held_stamps` (feeding order) that the output stamps are, in output order (a
    stamp held twice: its first row after the previous answer; rows skipped were dropped).
    RuntimeError when an output stamp has no held row (a bug of the caller)."""
    held_stamps = np.asarray(held_stamps, dtype=np.int64)
    out_stamps = np.asarray(out_stamps, dtype=np.int64)
    k = len(out_stamps)
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    if len(held_stamps) >= k and np.array_equal(held_stamps[:k], out_stamps):
        return np.arange(k, dtype=np.int64)  # nothing dropped: the usual case
    if np.all(held_stamps[1:] >= held_stamps[:-1]) and np.all(out_stamps[1:] > out_stamps[:-1]):
        # stamps in order (no clock jump): each found by binary search
        rows = np.searchsorted(held_stamps, out_stamps, side="left")
        found = rows < len(held_stamps)
        found[found] = held_stamps[rows[found]] == out_stamps[found]
        if not found.all():
            _unmatched(int(out_stamps[~found][0]))
        return rows.astype(np.int64)
    # stamps that go back (a restarted clock): a forward scan
    held, rows, i = held_stamps.tolist(), [], 0
    for stamp in out_stamps.tolist():
        while i < len(held) and held[i] != stamp:
            i += 1
        if i == len(held):
            _unmatched(stamp)
        rows.append(i)
        i += 1
    return np.asarray(rows, dtype=np.int64)


def _unmatched(stamp: int):
    raise RuntimeError(f"output sample stamped {stamp} has no held input sample (internal error)")
