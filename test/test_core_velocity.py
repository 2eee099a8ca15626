"""Per-block joint velocity matched by stamps; velocity from positions (JointVelocity)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from egovib_ros.core import HELD, MATCHED, MISSING, JointVelocity, block_mean_velocity
from egovib_ros.core.velocity import SplitJointStates


def test_mean_over_span_hold_and_missing():
    t = np.array([0, 1, 2, 3, 10, 11], dtype=np.int64) * 1_000_000
    v = np.array([[1, 10], [2, 20], [3, 30], [4, 40], [5, 50], [6, 60]], dtype=float)
    first = np.array([0, 4, 40, 1], dtype=np.int64) * 1_000_000
    last = np.array([2, 5, 41, 3], dtype=np.int64) * 1_000_000
    mean, steady, status = block_mean_velocity(t, v, first, last, max_hold_ns=5_000_000)
    np.testing.assert_allclose(mean[0], [2, 20])
    np.testing.assert_allclose(mean[1], [4, 40])  # none inside: hold stamp 3 ms (1 ms old)
    assert np.isnan(mean[2]).all()  # last state 29 ms old: missing
    np.testing.assert_allclose(mean[3], [3, 30])
    assert status.tolist() == [MATCHED, HELD, MISSING, MATCHED]
    # Steadiness: first half [1] vs second half [2, 3] -> |1 - 2.5| = 1.5
    np.testing.assert_allclose(steady[0], [1.5, 15.0])


def test_one_block_path_is_bit_identical_to_vectorised():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.integers(900_000, 1_100_000, size=5000)).astype(np.int64)
    v = rng.normal(size=(5000, 2)) * [3.0, 0.04]
    first = np.sort(rng.integers(t[0], t[-1], size=300)).astype(np.int64)
    last = first + 21_000_000
    many = block_mean_velocity(t, v, first, last, max_hold_ns=50_000_000, with_steadiness=False)[0]
    for b in range(0, 300, 7):
        one = block_mean_velocity(
            t, v, first[b : b + 1], last[b : b + 1], max_hold_ns=50_000_000, with_steadiness=False
        )[0]
        np.testing.assert_array_equal(one[0], many[b])


def _positions(seed: int, n: int = 400, joints: int = 2):
    """Smooth motion of a continuous joint (reported within +-pi, so it wraps) and a
    linear one, sampled with jittering stamps."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(1_000_000 + rng.integers(-300_000, 300_000, n)).astype(np.int64)
    seconds = t / 1e9
    velocity = np.column_stack([4.0 + np.sin(3 * seconds), 0.04 * np.cos(2 * seconds)])
    position = np.column_stack(
        [4.0 * seconds - np.cos(3 * seconds) / 3, 0.02 * np.sin(2 * seconds)]
    )[:, :joints]
    position[:, 0] = (position[:, 0] + np.pi) % (2 * np.pi) - np.pi  # wraps at +-pi
    return t, position, velocity[:, :joints]


@given(st.integers(0, 1000), st.lists(st.integers(1, 60), min_size=1, max_size=12))
def test_velocity_from_positions_any_chunking_equals_whole(seed, cuts):
    t, position, _ = _positions(seed)
    whole = JointVelocity(2, source="from_position").push(
        t, position, np.full_like(position, np.nan)
    )
    jv, parts, start = JointVelocity(2, source="from_position"), [], 0
    for size in [*cuts, len(t)]:
        stop = min(len(t), start + size)
        parts.append(
            jv.push(t[start:stop], position[start:stop], np.full((stop - start, 2), np.nan))
        )
        start = stop
    np.testing.assert_array_equal(np.concatenate(parts), whole)


@given(st.integers(0, 1000), st.lists(st.integers(1, 60), min_size=1, max_size=12))
def test_auto_any_chunking_equals_whole_with_measured_stretches(seed, cuts):
    # Drivers that measure velocity most of the time: chunks whose velocities are all
    # measured take the short path (nothing derived, the last positions kept); a later
    # chunk with gaps must still derive from those positions as one call over all would.
    t, position, velocity = _positions(seed)
    velocity = velocity.copy()
    rng = np.random.default_rng(seed)
    velocity[rng.uniform(size=velocity.shape) < 0.1] = np.nan
    velocity[: len(t) // 3] = np.where(
        np.isnan(velocity[: len(t) // 3]), 0.5, velocity[: len(t) // 3]
    )
    position[rng.uniform(size=position.shape) < 0.05] = np.nan
    whole = JointVelocity(2, source="auto").push(t, position, velocity)
    jv, parts, start = JointVelocity(2, source="auto"), [], 0
    for size in [*cuts, len(t)]:
        stop = min(len(t), start + size)
        parts.append(jv.push(t[start:stop], position[start:stop], velocity[start:stop]))
        start = stop
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_velocity_from_positions_unwraps_and_matches_the_motion():
    t, position, velocity = _positions(3)
    derived = JointVelocity(2, source="from_position").push(
        t, position, np.full((len(t), 2), np.nan)
    )
    assert np.isnan(derived[0]).all()  # the first position has no difference
    # a backward difference: the mean velocity over the step, across the +-pi cut too
    seconds = t / 1e9
    mid = 0.5 * (seconds[1:] + seconds[:-1])
    want = np.column_stack([4.0 + np.sin(3 * mid), 0.04 * np.cos(2 * mid)])
    error = np.abs(derived[1:] - want) / np.abs(want).max(axis=0)
    assert error.max() < 2e-3, error.max(axis=0)


def test_auto_takes_the_measured_velocity_where_there_is_one():
    t, position, velocity = _positions(4)
    measured = velocity.copy()
    measured[::3, 0] = np.nan  # some messages without velocity for joint 0
    jv = JointVelocity(2, source="auto")
    out = jv.push(t, position, measured)
    np.testing.assert_array_equal(out[1::3], measured[1::3])
    assert np.isfinite(out[3::3, 0]).all() and jv.derived == len(out[3::3])
    assert np.array_equal(
        JointVelocity(2, source="measured").push(t, position, measured), measured, equal_nan=True
    )


def test_split_publishers_differentiate_each_joint_over_its_own_messages():
    """Each joint in its own JointState (NaN where a message lacks it): a joint's difference
    spans back to its own previous position, not to the other publisher's message."""
    t, position, _ = _positions(5)
    split = np.full_like(position, np.nan)
    split[0::2, 0], split[1::2, 1] = position[0::2, 0], position[1::2, 1]
    out = JointVelocity(2, source="from_position").push(t, split, np.full_like(split, np.nan))
    alone0 = JointVelocity(1, source="from_position").push(
        t[0::2], position[0::2, :1], np.full((len(t[0::2]), 1), np.nan)
    )
    np.testing.assert_array_equal(out[0::2, 0], alone0[:, 0])
    assert np.isnan(out[1::2, 0]).all() and np.isnan(out[0::2, 1]).all()


def _per_joint_messages(seed: int, n: int = 120, joints: int = 3):
    """Joint states as per-joint drivers publish them: each stamp's joints in separate
    messages (in a random order, sometimes two joints together), and the rows one
    JointState per stamp would have given."""
    rng = np.random.default_rng(seed)
    rows_t, rows_p, whole_t, whole_p = [], [], [], []
    for k in range(n):
        stamp = 1_000_000 * (k + 1)
        p = rng.normal(size=joints)
        order = rng.permutation(joints)
        groups = np.split(
            order, np.sort(rng.choice(np.arange(1, joints), rng.integers(0, joints), replace=False))
        )
        for g in groups:
            row = np.full(joints, np.nan)
            row[g] = p[g]
            rows_t.append(stamp)
            rows_p.append(row)
        whole_t.append(stamp)
        whole_p.append(p)
    t, p = np.array(rows_t, np.int64), np.array(rows_p)
    return t, p, p * 10.0, np.array(whole_t, np.int64), np.array(whole_p)


@given(st.integers(0, 1000), st.lists(st.integers(1, 40), min_size=1, max_size=12))
def test_split_joint_messages_join_into_one_row_per_stamp_for_any_chunking(seed, cuts):
    """One message per joint with one stamp: one row per stamp with every joint, however
    the messages are cut into batches (the last stamp held until it is complete or the end)."""
    t, p, v, want_t, want_p = _per_joint_messages(seed)
    split, parts, start = SplitJointStates(), [], 0
    for size in [*cuts, len(t)]:
        stop = min(len(t), start + size)
        parts.append(split.push(t[start:stop], p[start:stop], v[start:stop]))
        start = stop
    held = split.flush()
    parts += [held] if held is not None else []
    got_t, got_p, got_v = (np.concatenate([part[i] for part in parts]) for i in range(3))
    np.testing.assert_array_equal(got_t, want_t)
    np.testing.assert_array_equal(got_p, want_p)
    np.testing.assert_array_equal(got_v, want_p * 10.0)


def test_a_stamp_that_repeats_a_joint_is_left_to_the_stuck_clock_check():
    """Two messages of one stamp that both carry a joint are not one message split up:
    they are passed on as they are (the framer drops the second, counted)."""
    nan = np.nan
    t = np.array([5, 5, 6], np.int64)
    p = np.array([[1.0, nan], [2.0, 3.0], [4.0, 5.0]])
    got = SplitJointStates().push(t, p, p)
    np.testing.assert_array_equal(got[0], t)
    np.testing.assert_array_equal(got[1], p)


def test_partial_messages_that_never_share_a_stamp_are_held_only_while_probing():
    """An arm and a gripper publishing at their own times: every row lacks a joint, none
    shares a stamp; after PROBE_STAMPS stamps they go out as they come (no latency)."""
    nan = np.nan
    split = SplitJointStates()
    out = []
    for k in range(40):
        row = np.array([[float(k), nan]]) if k % 2 else np.array([[nan, float(k)]])
        got = split.push(np.array([1000 * k], np.int64), row, row)
        out.append(len(got[0]))
    assert out[: SplitJointStates.PROBE_STAMPS] == [0] + [1] * (SplitJointStates.PROBE_STAMPS - 1)
    assert out[SplitJointStates.PROBE_STAMPS + 1 :] == [1] * (39 - SplitJointStates.PROBE_STAMPS)
    assert split.flush() is None


def test_a_message_without_our_joints_at_a_stamp_already_given_is_dropped():
    """The arm broadcaster (every joint) and a wheel broadcaster (none of ours) stamping a
    tick alike, pushed message by message as a live node takes them: one row per stamp."""
    nan = np.nan
    split, rows = SplitJointStates(), []
    for k in range(20):
        for row in (np.array([[1.0 * k, 2.0 * k]]), np.array([[nan, nan]])):
            rows.append(split.push(np.array([1000 * k], np.int64), row, row)[0])
    held = split.flush()
    stamps = np.concatenate(rows + ([held[0]] if held is not None else []))
    np.testing.assert_array_equal(stamps, 1000 * np.arange(20))
