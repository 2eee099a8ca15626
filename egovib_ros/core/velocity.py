"""Per-block joint velocity matched by time stamps (paper section 2: each block is marked
with the element-wise mean joint velocity). Joint states and sensor samples come from
independent clocks: matching is by stamps only, never by sample counts.
"""

from __future__ import annotations

import numpy as np

from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.robot import VELOCITY_SOURCES

#: Status of a block's joint velocity.
MATCHED = 0  # mean over the joint states stamped inside the block's time span
HELD = 1  # none inside; the latest earlier joint state (within max_hold) is used
MISSING = 2  # no usable joint state: velocity is NaN, the block is not denoised/calibrated


def block_mean_velocity(
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    t_first_ns: np.ndarray,
    t_last_ns: np.ndarray,
    *,
    max_hold_ns: int,
    with_steadiness: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean joint velocity over [t_first, t_last] per block: (mean (B, J), steadiness
    (B, J), status (B,)). Steadiness: |mean of the first half of the block's joint states -
    mean of the second| (not inflated by encoder quantisation, unlike the spread). Each
    block sums a zero-padded row of fixed width, so its result does not depend on the
    other blocks of the call (streaming and batch give the same numbers)."""
    t_first_ns = np.asarray(t_first_ns, dtype=np.int64)
    t_last_ns = np.asarray(t_last_ns, dtype=np.int64)
    joint_stamps_ns = np.asarray(joint_stamps_ns, dtype=np.int64)
    joint_velocity = np.asarray(joint_velocity, dtype=np.float64)
    n_blocks = len(t_first_ns)
    if n_blocks == 1 and not with_steadiness and len(joint_stamps_ns):
        return one_block_mean_velocity(
            joint_stamps_ns, joint_velocity, int(t_first_ns[0]), int(t_last_ns[0]), max_hold_ns
        )
    n_joints = joint_velocity.shape[1] if joint_velocity.ndim == 2 else 0
    mean = np.full((n_blocks, n_joints), np.nan)
    steadiness = np.full((n_blocks, n_joints), np.nan)
    status = np.full(n_blocks, MISSING, dtype=np.int8)
    if n_blocks == 0 or len(joint_stamps_ns) == 0:
        return mean, steadiness, status

    start = np.searchsorted(joint_stamps_ns, t_first_ns, side="left")
    stop = np.searchsorted(joint_stamps_ns, t_last_ns, side="right")
    count = stop - start
    inside = count > 0
    if inside.any():
        width = _row_width(int(count.max()))
        offsets = np.arange(width)
        idx = start[inside, None] + offsets[None, :]
        valid = offsets[None, :] < count[inside, None]
        # Multiplying by the 0/1 mask is exact for finite velocities.
        rows = joint_velocity[np.minimum(idx, len(joint_velocity) - 1)] * valid[:, :, None]
        n = count[inside, None].astype(np.float64)
        mean[inside] = rows.sum(axis=1) / n
        if with_steadiness:
            # Halves: first floor(n/2) states vs the rest (a single state is perfectly steady).
            half = count[inside] // 2
            first_half = offsets[None, :] < half[:, None]
            sum_first = (rows * first_half[:, :, None]).sum(axis=1)
            sum_second = (rows * (~first_half & valid)[:, :, None]).sum(axis=1)
            n_first = np.maximum(half, 1)[:, None].astype(np.float64)
            n_second = (count[inside] - half)[:, None].astype(np.float64)
            steadiness[inside] = np.where(
                half[:, None] > 0, np.abs(sum_first / n_first - sum_second / n_second), 0.0
            )
        status[inside] = MATCHED

    # Blocks with no joint state inside their span: hold the previous one if recent enough.
    empty = ~inside
    if empty.any():
        prev = start[empty] - 1
        ok = prev >= 0
        age = np.where(
            ok, t_first_ns[empty] - joint_stamps_ns[np.maximum(prev, 0)], np.iinfo(np.int64).max
        )
        ok &= age <= max_hold_ns
        rows_empty = np.flatnonzero(empty)[ok]
        mean[rows_empty] = joint_velocity[prev[ok]]
        steadiness[rows_empty] = 0.0
        status[rows_empty] = HELD
    return mean, steadiness, status


def _row_width(max_count: int) -> int:
    # A fixed minimum width keeps numpy's summation order identical for B = 1 and B > 1.
    return max(32, int(np.ceil(max_count / 8.0)) * 8)


def one_block_mean_velocity(joint_stamps_ns, joint_velocity, t_first, t_last, max_hold_ns):
    """The streaming case (one block per hop) with few numpy calls: a slice's rows summed
    one after another, as the padded-row sum above, so the numbers are identical."""
    start = int(joint_stamps_ns.searchsorted(t_first, side="left"))
    stop = int(joint_stamps_ns.searchsorted(t_last, side="right"))
    nan = np.full((1, joint_velocity.shape[1]), np.nan)
    if stop > start:
        mean = joint_velocity[start:stop].sum(axis=0) / float(stop - start)
        return mean[None], nan, np.array([MATCHED], np.int8)
    if start > 0 and t_first - int(joint_stamps_ns[start - 1]) <= max_hold_ns:
        held = joint_velocity[start - 1][None].copy()
        return held, np.zeros_like(held), np.array([HELD], np.int8)
    return nan, nan.copy(), np.array([MISSING], np.int8)


class JointVelocity:
    """Joint velocities from JointState columns, for drivers that publish positions only.
    `source`: "measured" (NaN stays NaN: the framer drops it), "from_position", or "auto"
    (measured where finite, else from positions).

    The backward difference of each joint's own positions over their stamps, as the PR2
    derives velocity from its encoders (a block's mean telescopes to displacement / time);
    a step beyond +-pi is wrapped into (-pi, pi] (a continuous joint crossing the cut; in
    REP 103 units nothing else moves pi between joint states). A joint absent from a message
    stays NaN, its next difference spanning back to its previous position; its first
    position has none. Any chunking gives the same."""

    def __init__(self, n_joints: int, *, source: str = "auto"):
        if source not in VELOCITY_SOURCES:
            raise ValueError(f"velocity source must be one of {VELOCITY_SOURCES}, got {source!r}")
        self.source = source
        self._last_t = np.full(n_joints, np.iinfo(np.int64).min, np.int64)
        self._last_p = np.full(n_joints, np.nan)
        self.derived = 0  # velocities taken from positions

    def push(self, stamps_ns: np.ndarray, position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """(M, J) velocities for M joint states (stamps (M,), positions and velocities (M, J),
        NaN where a message lacks a value)."""
        velocity = np.asarray(velocity, dtype=np.float64)
        if self.source == "measured" or not len(stamps_ns):
            return velocity
        position = np.asarray(position, dtype=np.float64)
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        if self.source == "auto" and np.isfinite(velocity).all():
            # Every velocity measured (the common driver): nothing to derive, only the last
            # position of each joint to keep (a live node calls this every few ms).
            if np.isfinite(position[-1]).all():
                self._last_p[:] = position[-1]
                self._last_t[:] = stamps_ns[-1]
                return velocity
            finite = np.isfinite(position)
            seen = finite.any(axis=0)
            last = len(position) - 1 - np.argmax(finite[::-1], axis=0)
            self._last_p[seen] = position[last[seen], np.flatnonzero(seen)]
            self._last_t[seen] = stamps_ns[last[seen]]
            return velocity
        derived = np.full(position.shape, np.nan)
        for j in range(position.shape[1]):
            rows = np.flatnonzero(np.isfinite(position[:, j]))
            if not len(rows):
                continue
            p = np.concatenate([[self._last_p[j]], position[rows, j]])
            t = np.concatenate([[self._last_t[j]], stamps_ns[rows]])
            step = np.diff(p)
            step = np.where(np.abs(step) > np.pi, (step + np.pi) % (2 * np.pi) - np.pi, step)
            dt = np.diff(t).astype(np.float64) / NS_PER_S
            first = t[:-1] == np.iinfo(np.int64).min
            with np.errstate(divide="ignore", invalid="ignore"):
                derived[rows, j] = np.where((dt > 0) & ~first, step / dt, np.nan)
            self._last_p[j], self._last_t[j] = p[-1], t[-1]
        if self.source == "from_position":
            self.derived += int(np.isfinite(derived).sum())
            return derived
        use = ~np.isfinite(velocity) & np.isfinite(derived)
        self.derived += int(use.sum())
        return np.where(use, derived, velocity)


class SplitJointStates:
    """Joint states published one message per joint (or controller) with one stamp: the
    messages of one stamp whose joints do not overlap are joined into one row. Rows of one
    stamp that repeat a joint stay (a stuck clock: the framer drops them); a row with none
    of the joints repeating the stamp before it (another controller's) is dropped.

    `push` holds back the last stamp's rows while a joint is missing (the next message may
    complete them), `flush` gives them at the end; partial messages that never share a
    stamp are held for the first PROBE_STAMPS stamps only. Offline and live alike, before
    velocities are derived and missing joints held (`hold_missing_joints`)."""

    #: Partial stamps held without anything to join before holding stops.
    PROBE_STAMPS = 10

    def __init__(self) -> None:
        self._tail: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._joining = False  # a stamp has come in several messages: hold the last one
        self._holding = True  # hold partial last stamps (probing, or joining)
        self._unjoined = 0  # stamps held that had nothing to join
        self._last_stamp: int | None = None  # of the last row given out
        self._last_present: np.ndarray | None = None

    @property
    def held_from_ns(self) -> int | None:
        """The stamp of the rows held back (None: none); later stamps may still come."""
        return None if self._tail is None else int(self._tail[0][0])

    def push(
        self, stamps: np.ndarray, position: np.ndarray, velocity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        held = 0
        if self._tail is not None:
            held = len(self._tail[0])
            stamps, position, velocity = (
                np.concatenate([a, b]) for a, b in zip(self._tail, (stamps, position, velocity))
            )
            self._tail = None
        n = len(stamps)
        if n == 0:
            return stamps, position, velocity
        present = ~(np.isnan(position) & np.isnan(velocity))
        if (
            not held
            and not self._joining
            and stamps[0] != self._last_stamp
            and (n == 1 or (stamps[1:] != stamps[:-1]).all())
            and present.all()
        ):
            # Whole messages, one per stamp (the common driver; a live node's every few ms):
            # nothing to join or hold back.
            self._last_stamp, self._last_present = int(stamps[-1]), present[-1]
            return stamps, position, velocity
        if self._last_stamp is not None and stamps[0] == self._last_stamp:
            # the stamp of a row already given out: it cannot be joined any more
            if not present[0].any():  # another controller's message: nothing of ours
                stamps, position, velocity, present = (
                    stamps[1:], position[1:], velocity[1:], present[1:]
                )  # fmt: skip
                n -= 1
            elif not (present[0] & self._last_present).any():
                self._joining = self._holding = True  # split messages after all: hold
        if n == 0:
            return stamps, position, velocity
        starts = np.flatnonzero(np.r_[True, stamps[1:] != stamps[:-1]])
        per_run = np.add.reduceat(present.astype(np.int64), starts, axis=0)  # (R, J)
        sizes = np.diff(np.r_[starts, n])
        joined = (sizes > 1) & (per_run.max(axis=1) <= 1)  # disjoint joints in one stamp
        if joined.any():
            self._joining = self._holding = True
        elif held and not self._joining and n > held and stamps[held] != stamps[0]:
            self._unjoined += 1  # the stamp held had nothing to join
            self._holding = self._unjoined < self.PROBE_STAMPS
        if self._holding and not (per_run[-1] > 0).all():  # the last stamp may still grow
            last = starts[-1]
            self._tail = (stamps[last:], position[last:], velocity[last:])
            stamps, position, velocity, present = (
                stamps[:last], position[:last], velocity[:last], present[:last]
            )  # fmt: skip
            starts, sizes, joined = starts[:-1], sizes[:-1], joined[:-1]
            n = last
        if n == 0:
            return stamps, position, velocity
        if joined.any():
            position, velocity = position.copy(), velocity.copy()
            with np.errstate(invalid="ignore"):  # fmax skips NaN: each joint from its own row
                position[starts[joined]] = np.fmax.reduceat(position, starts, axis=0)[joined]
                velocity[starts[joined]] = np.fmax.reduceat(velocity, starts, axis=0)[joined]
            run = np.repeat(np.arange(len(starts)), sizes)
            keep = ~joined[run] | (np.arange(n) == starts[run])
            stamps, position, velocity = stamps[keep], position[keep], velocity[keep]
        self._last_stamp = int(stamps[-1])
        self._last_present = ~(np.isnan(position[-1]) & np.isnan(velocity[-1]))
        return stamps, position, velocity

    def flush(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The rows held back (the last stamp's), joined as far as they go; None if none."""
        if self._tail is None:
            return None
        empty = tuple(a[:0] for a in self._tail)
        holding, self._holding = self._holding, False  # the end: nothing more can come
        try:
            return self.push(*empty)
        finally:
            self._holding = holding


def hold_missing_joints(
    position: np.ndarray, velocity: np.ndarray, last: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Partial JointStates: a joint a message lacks (NaN position and velocity) keeps its
    last published value; `last` (2, J) carries them across batches (None: NaN until first
    seen). Returns (position, velocity, last); offline and live alike."""
    if not len(position):
        return position, velocity, last
    present = ~(np.isnan(position) & np.isnan(velocity))
    if present.all():
        return position, velocity, np.stack([position[-1], velocity[-1]])
    both = np.stack([position, velocity], axis=1)  # (M, 2, J)
    start = last if last is not None else np.full(both.shape[1:], np.nan)
    rows = np.where(present[:, None, :], np.arange(len(both))[:, None, None], -1)
    newest = np.maximum.accumulate(rows, axis=0)  # the last row holding each joint
    filled = np.where(
        newest >= 0, np.take_along_axis(both, np.maximum(newest, 0), axis=0), start[None]
    )
    return filled[:, 0], filled[:, 1], filled[-1]
