"""The contact detector (core.contact): events, onsets, peaks, thresholds, chunking."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from egovib_ros.core.contact import (
    MOTION_ACCEL_S,
    MOTION_HOLD_S,
    ContactDetector,
    ContactSettings,
    DetectionEnvelope,
    MotionLimits,
    joint_acceleration,
    no_contact_threshold,
)
from egovib_ros.errors import ConfigError

FS = 3000.0
BAND = (150.0, 750.0)


def taps(seconds=4.0, onsets_s=(0.5, 1.3, 1.35, 2.2, 3.1), seed=0, noise=0.05):
    """Noise plus damped 400 Hz bursts along a fixed direction (the 1.35 s one 50 ms after
    the 1.30 s one: one event, the refractory time)."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FS)
    stamps = 1_000_000_000 + np.arange(n, dtype=np.int64) * 333_333
    values = noise * rng.normal(size=(n, 3)) + [0.0, 0.0, 9.81]
    k = np.arange(int(0.04 * FS)) / FS
    burst = 3.0 * np.exp(-k / 0.006) * np.sin(2 * np.pi * 400 * k)
    direction = np.array([0.6, 0.8, 0.0])
    for onset in onsets_s:
        i = int(onset * FS)
        values[i : i + len(burst)] += burst[:, None] * direction[None, :]
    return stamps, values, [int(o * FS) for o in onsets_s]


def settings(threshold=0.5, **kw):
    return ContactSettings(sample_rate_hz=FS, band_hz=BAND, threshold=threshold, **kw)


def run(detector, stamps, values, cuts):
    events, start = [], 0
    for size in [*cuts, len(stamps)]:
        stop = min(len(stamps), start + size)
        events += detector.push(stamps[start:stop], values[start:stop])
        start = stop
    return events + detector.finish()


def test_each_tap_is_one_event_at_its_onset_with_its_peak_per_axis():
    stamps, values, onsets = taps()
    events = run(ContactDetector(settings()), stamps, values, [])
    # 1.30 and 1.35 s: within the refractory time of each other's ring-down, one event
    want = [onsets[0], onsets[1], onsets[3], onsets[4]]
    assert len(events) == 4
    for event, onset in zip(events, want):
        assert abs(event.onset_ns - stamps[onset]) <= 2_000_000  # within 2 ms of the true onset
        x, y, z = event.peak
        assert x * y > 0 and abs(y) > abs(x) > 5 * abs(z)  # along (0.6, 0.8, 0)
        assert event.report_ns - event.crossing_ns <= 10_000_000 + 333_333  # out 10 ms later
        assert event.strength > 0.5


def test_gravity_and_noise_alone_raise_nothing():
    stamps, values, _ = taps(onsets_s=())
    assert run(ContactDetector(settings(threshold=0.3)), stamps, values, []) == []


@given(st.lists(st.integers(1, 700), max_size=30))
def test_any_chunking_gives_the_same_events(cuts):
    stamps, values, _ = taps(seconds=2.5, onsets_s=(0.3, 0.9, 1.6, 2.45))
    whole = run(ContactDetector(settings()), stamps, values, [])
    assert run(ContactDetector(settings()), stamps, values, cuts) == whole
    assert len(whole) == 4  # the last one reported at the end of the stream


@given(st.lists(st.integers(1, 700), max_size=20))
def test_bad_samples_are_counted_held_and_do_not_end_detection(cuts):
    """A NaN, an inf and a spike beyond the sensor's range before the taps: counted, held at
    the last good value, no event of their own and every tap still found (one NaN in the
    band-pass state ended detection for good), for any chunking."""
    stamps, values, onsets = taps()
    values[100] = [np.nan, 0.0, 9.81]
    values[900, 2] = np.inf
    values[1200] = [1e6, 0.0, 9.81]  # the PR2's range is 78.5 m/s^2
    clean = run(ContactDetector(settings()), *taps()[:2], [])
    detector = ContactDetector(settings(sensor_range=78.5))
    events = run(detector, stamps, values, cuts)
    assert detector.samples_bad == 3
    assert [e.onset_ns for e in events] == [e.onset_ns for e in clean]
    assert all(np.isfinite(e.peak).all() for e in events)
    assert len(events) == 4 and events[0].onset_ns > stamps[onsets[0]] - 2_000_000


@given(st.lists(st.integers(1, 700), max_size=20))
def test_stamps_that_go_back_are_dropped_and_a_restarted_clock_restarts(cuts):
    """Repeated stamps (a duplicate publisher) are dropped and counted; stamps going back 2 s
    (a restarted driver) report what was pending and detect afresh: every tap found once,
    onsets at their own stamps, for any chunking."""
    stamps, values, onsets = taps()
    clean = run(ContactDetector(settings()), stamps, values, [])
    half = len(stamps) // 2  # 2 s: between the taps at 1.35 and 2.2 s
    restarted = np.concatenate([stamps[:half], stamps[half:] - 3_000_000_000])
    doubled = np.insert(restarted, [500, 501], restarted[[499, 500]])  # two repeated stamps
    twice = np.insert(values, [500, 501], values[[499, 500]], axis=0)
    detector = ContactDetector(settings())
    events = run(detector, doubled, twice, cuts)
    assert detector.samples_out_of_order == 2 and detector.restarts == 1
    assert [e.onset_ns for e in events] == [
        e.onset_ns - (3_000_000_000 if e.onset_ns >= stamps[half] else 0) for e in clean
    ]


def test_threshold_from_no_contact_data_and_its_false_alarm_rate():
    stamps, values, _ = taps(seconds=30.0, onsets_s=())
    envelope = DetectionEnvelope(settings()).process(values)[1]
    strict, rate = no_contact_threshold(envelope, sample_rate_hz=FS, false_alarms_per_min=0)
    assert strict == pytest.approx(1.1 * envelope.max()) and rate == 0.0
    # the default budget (1 a minute): 1.1 x the level the envelope stays above 20 ms a minute
    default, rate = no_contact_threshold(envelope, sample_rate_hz=FS)
    assert default == pytest.approx(1.1 * np.quantile(envelope, 1 - 0.02 / 60))
    assert default < strict and rate <= 1.0
    # one burst in the no-contact data (a sweep's speed step) does not set the default
    burst = envelope.copy()
    burst[1000:1030] = 10 * envelope.max()
    assert no_contact_threshold(burst, sample_rate_hz=FS)[0] < 1.2 * default
    budget, rate = no_contact_threshold(envelope, sample_rate_hz=FS, false_alarms_per_min=30)
    assert budget < default and rate > 0  # a larger budget: a lower threshold, what it gives
    # on the same data, the detector raises as many events as stated
    events = run(ContactDetector(settings(threshold=budget)), stamps, values, [])
    assert len(events) <= rate * 0.5 + 1e-9


def test_settings_are_validated():
    with pytest.raises(ConfigError, match="threshold"):
        settings(threshold=float("nan"))
    with pytest.raises(ConfigError, match="report_after_s"):
        settings(report_after_s=-1)


# --- motion beyond the calibration's ------------------------------------------------------
LIMITS = MotionLimits(speed_low=(-1.0, -1.0), speed_high=(1.0, 1.0), accel=50.0, factor=6.0)


def joints(stamps_s=(0.0, 4.0), fast=((1.2, 1.5),)):
    """1 kHz joint states over `stamps_s`: both joints at 0.5, the first at 2 within each
    span of `fast` (beyond its speed, and a step of 1.5 in 1 ms: beyond the acceleration)."""
    t = np.arange(*stamps_s, 0.001)
    velocity = np.full((len(t), 2), 0.5)
    for a, b in fast:
        velocity[(t >= a) & (t < b), 0] = 2.0
    return 1_000_000_000 + np.round(t * 1e9).astype(np.int64), velocity


def interleaved(detector, stamps, values, joint_stamps, velocity, cuts):
    """Samples and joint states pushed in time order, cut at `cuts` (sensor samples)."""
    events, start = [], 0
    for size in [*cuts, len(stamps)]:
        stop = min(len(stamps), start + size)
        if stop > start:
            upto = np.searchsorted(joint_stamps, stamps[stop - 1], side="right")
            done = np.searchsorted(joint_stamps, stamps[start], side="left") if start else 0
            events += detector.push_joints(joint_stamps[done:upto], velocity[done:upto])
            events += detector.push(stamps[start:stop], values[start:stop])
        start = stop
    events += detector.push_joints(joint_stamps[upto:], velocity[upto:])
    return events + detector.finish()


def test_beyond_the_calibrations_motion_the_threshold_rises_for_a_while():
    """The tap at 1.30 s falls where a joint runs faster than calibration saw: at 6 x the
    threshold (3.0, over the taps' 2.1) it is not an event; the others are, as without
    limits. The acceleration alone (a step within the speeds) raises it too, MOTION_HOLD_S
    after the step."""
    stamps, values, onsets = taps()
    plain = run(ContactDetector(settings()), stamps, values, [])
    assert len(plain) == 4
    detector = ContactDetector(settings(), motion=LIMITS)
    events = interleaved(detector, stamps, values, *joints(), [])
    assert [e.onset_ns for e in events] == [
        e.onset_ns for e in plain if e.onset_ns != plain[1].onset_ns
    ]
    # 1.2-1.5 s too fast, then the step back down: 10 ms of joint states beyond the
    # acceleration (a change over MOTION_ACCEL_S), then MOTION_HOLD_S
    marked_s = 0.3 + MOTION_ACCEL_S - 0.001 + MOTION_HOLD_S
    assert detector.samples_motion == pytest.approx(marked_s * FS, abs=3)
    # the threshold stays raised MOTION_HOLD_S after the last joint state beyond: a step to
    # a speed within the limits (0.5 -> -0.9 in 1 ms) marks 10 ms + MOTION_HOLD_S
    joint_stamps, velocity = joints(fast=())
    velocity[(joint_stamps >= 1_000_000_000 + 1_299_000_000), 0] = -0.9
    detector = ContactDetector(settings(), motion=LIMITS)
    events = interleaved(detector, stamps, values, joint_stamps, velocity, [])
    # the 1.30 s tap falls inside it, and the 1.35 s one (without limits, part of the 1.30 s
    # event) that rings on past it continues it: no event where the raising ends
    assert [round((e.onset_ns - stamps[0]) / 1e9, 2) for e in events] == [0.5, 2.2, 3.1]
    assert detector.samples_motion == pytest.approx(MOTION_HOLD_S * FS + 0.01 * FS, abs=3)


@given(st.lists(st.integers(1, 3000), max_size=8))
def test_with_motion_limits_any_chunking_gives_the_same_events(cuts):
    stamps, values, _ = taps()
    joint_stamps, velocity = joints(fast=((1.2, 1.5), (3.05, 3.06)))
    whole = ContactDetector(settings(), motion=LIMITS)
    expected = whole.push_joints(joint_stamps, velocity) + run(whole, stamps, values, [])
    detector = ContactDetector(settings(), motion=LIMITS)
    assert interleaved(detector, stamps, values, joint_stamps, velocity, cuts) == expected
    assert detector.samples_motion == whole.samples_motion


@given(st.lists(st.integers(1, 6000), max_size=6))
def test_a_looped_recording_gives_the_same_events_whichever_stream_comes_first(cuts):
    """A bag's loop: sensor and joint clocks restart together; the second copy reads its
    own joint states whether all joint states came first, or each copy's in time."""
    stamps, values, _ = taps()
    joint_stamps, velocity = joints(fast=((1.2, 1.5), (3.05, 3.06)))
    back = 3_000_000_000  # 4 s of data, restarted 3 s back: a jump of the clock
    loop = np.concatenate([stamps, stamps[-1] + 333_333 - back + (stamps - stamps[0])])
    twice = np.vstack([values, values])
    joint_loop = np.concatenate(
        [joint_stamps, stamps[-1] + 333_333 - back + joint_stamps - joint_stamps[0]]
    )
    joint_twice = np.vstack([velocity, velocity])
    first = ContactDetector(settings(), motion=LIMITS)
    expected = first.push_joints(joint_loop, joint_twice) + run(first, loop, twice, cuts)
    assert first.restarts == 1
    one = ContactDetector(settings(), motion=LIMITS)
    once = one.push_joints(joint_stamps, velocity) + run(one, stamps, values, [])
    assert len(expected) == 2 * len(once)  # each copy as the recording alone
    assert first.samples_motion == 2 * one.samples_motion
    timed = ContactDetector(settings(), motion=LIMITS)
    events = interleaved(
        timed, loop[: len(stamps)], twice[: len(stamps)], joint_stamps, velocity, cuts
    )
    assert [e.onset_ns for e in events] == [e.onset_ns for e in once]


def test_a_sample_waits_for_its_joint_states_or_its_release():
    """Without joint states up to its stamp a sample is not decided; `release` (live, after
    waiting for them) or the end decides it at what the joint states say by then."""
    stamps, values, _ = taps(onsets_s=(0.5,))
    waiting = ContactDetector(settings(), motion=LIMITS)
    assert waiting.push(stamps, values) == [] and waiting.onsets_settled == 0
    assert len(waiting.finish()) == 1  # the end decides what is left, at the base threshold
    live = ContactDetector(settings(), motion=LIMITS)
    assert live.push(stamps, values) == [] and len(live.release(int(stamps[-1]))) == 1


def test_motion_limits_are_validated():
    with pytest.raises(ConfigError, match="factor"):
        MotionLimits(speed_low=(0.0,), speed_high=(1.0,), accel=1.0, factor=0.5)
    with pytest.raises(ConfigError, match="one low and one high"):
        MotionLimits(speed_low=(0.0,), speed_high=(1.0, 2.0), accel=1.0, factor=2.0)
    with pytest.raises(ConfigError, match="accel"):
        MotionLimits(speed_low=(0.0,), speed_high=(1.0,), accel=float("nan"), factor=2.0)


def test_joint_acceleration_is_taken_over_motion_accel_s():
    """The summed change of speeds since the last state MOTION_ACCEL_S or more before, over
    the time between them: jitter in the joint stamps (two states 0.1 ms apart) does not
    make an acceleration, NaN speeds are left out, and a ramp reads the same at 50 Hz as at
    1 kHz (a fixed divisor read 50 Hz joint states twice as fast)."""
    t = np.array([0, 5, 10, 10.1, 20, 30], float) * 1e6
    velocity = np.array([[0, 0], [0, 0], [0.1, np.nan], [0.1, 0], [0.3, 0], [0.3, 0.2]])
    accel = joint_acceleration(t.astype(np.int64), velocity)
    assert accel.tolist() == pytest.approx([0, 0, 10, 0.1 / 0.0101, 20, 20])
    for rate in (50, 1000):
        stamps = np.arange(0, 1e9, 1e9 / rate).astype(np.int64)
        ramp = np.stack([2.0 * stamps / 1e9, np.zeros(len(stamps))], axis=1)  # 2 rad/s^2
        first = int(np.ceil(MOTION_ACCEL_S * rate))  # the first with a state far enough back
        assert joint_acceleration(stamps, ramp)[first:] == pytest.approx(2.0), rate
