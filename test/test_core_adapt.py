"""core.adapt: the model learning online while the contact detector sees no contact (the
residual table's cells, the harmonic map's corrections and amplitudes), gated, bounded,
reset on request, saved in the model, and the same for any chunking."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal
from synthetic import TWO_MOTOR_FS, two_motor_profile, two_motor_recording

from egovib_ros.core import calibrate_arrays
from egovib_ros.core.adapt import (
    ADAPT_PREFIX,
    MIN_POINT_SPANS,
    AdaptSettings,
    Candidate,
    CellLearner,
    ContactGate,
    HarmonicLearner,
    LineFinder,
    TransientGate,
    describe_learnt,
    learnt_state,
)
from egovib_ros.core.contact import ContactSettings
from egovib_ros.core.harmonic import HarmonicMap
from egovib_ros.core.methods import (
    DETECTOR_PREFIX,
    MethodCalibration,
    calibrate_detection,
    calibrate_methods,
    denoise_batch_method,
    make_denoiser,
)
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.errors import ConfigError, ModelFileError

FS = TWO_MOTOR_FS
PROFILE = two_motor_profile("two_motor_adapt")


def recording(
    speeds, *, seed: int, dwell_s: float = 1.5, level=1.0, taps_per_s: float = 0.0, tap_peak=4.0
):
    """Two motors (synthetic.two_motor_recording) dwelling on each (m1, m2) of `speeds` for
    `dwell_s` (0.1 s ramps between), all times `level` (a number or a function of time in
    s), jittery stamps."""
    rng = np.random.default_rng(seed)
    per = int(dwell_s * FS)
    target = np.repeat(np.asarray(speeds, float), per, axis=0)
    n = len(target)
    ramp = signal.butter(1, 3.0, fs=FS, output="sos")
    speed = signal.sosfilt(ramp, target - target[0], axis=0) + target[0]
    steps = 1.0 + rng.uniform(-0.2, 0.2, n)
    t = np.round(np.cumsum(steps) * 1e6).astype(np.int64)  # the stamps, less their start
    seconds = (t - t[0]) / 1e9
    gain = level(seconds) if callable(level) else np.full(n, float(level))
    mixing = np.random.default_rng(99).normal(size=(4, 3))
    return two_motor_recording(
        speed, steps, rng, mixing=mixing, gain=gain, taps_per_s=taps_per_s, tap_peak=tap_peak
    )


def arrays(rec):
    return rec["t"], rec["accel"], rec["tj"], rec["velocity"]


CALIBRATED = [(a, b) for a in (0.3, 0.4, 0.5) for b in (0.3, 0.4, 0.5)]


@pytest.fixture(scope="module")
def model() -> NoiseModel:
    """Calibrated at speeds 0.3-0.5 of each motor only, with its detector thresholds."""
    rec = recording(CALIBRATED * 2, seed=1, dwell_s=1.2)
    paper, _ = calibrate_arrays(*arrays(rec), profile=PROFILE, sweep="free")
    full, _ = calibrate_methods(paper, *arrays(rec))
    full, _ = calibrate_detection(full, *arrays(rec))
    return full


def residual_power(model: NoiseModel, cell, channel: str = "x") -> float:
    """The residual table's expected power of `channel` at grid cell `cell` (all bins)."""
    residual = MethodCalibration.from_model(model).residual
    point = np.array([[residual.grid[j][i] for j, i in enumerate(cell)]])
    mean, _, _ = residual.lookup(point, include_std=False)
    high, _, _ = residual.lookup(point, include_std=True)
    c = residual.channels.index(channel)
    return float((mean[0, c] ** 2 + (high[0, c] - mean[0, c]) ** 2).sum())


def learnt_power(adapted: NoiseModel, cell, channel: str = "x") -> float | None:
    residual, _ = learnt_state(adapted)
    rows = np.flatnonzero(np.all(residual["cells"] == np.asarray(cell), axis=1))
    if not len(rows):
        return None
    c = adapted.channels.index(channel)
    return float(residual["power"][rows[0], c].sum())


def run_adapting(model, rec, **options):
    denoiser = make_denoiser(model, "hybrid", adapt=AdaptSettings(**options))
    stamps, values, _ = denoiser.run_arrays(*arrays(rec), 30.0)
    return denoiser, stamps, values


def test_learns_speeds_beyond_the_calibration_and_a_louder_robot(model):
    # speeds the calibration never saw (0.8), and the calibrated 0.4 twice as loud
    rec = recording([(0.8, 0.8)] * 4 + [(0.4, 0.4)] * 4, seed=2, level=lambda s: 1 + (s > 6))
    denoiser, _, _ = run_adapting(model, rec, forget_s=2.0, max_rate_db_s=30.0)
    adapted = denoiser.adapted_model()
    stats = denoiser.adaptation_stats
    assert stats.blocks_learnt > 200 and stats.cells_new >= 1 and stats.cells_learnt >= 2
    residual, harmonic = learnt_state(adapted)
    new = {tuple(c) for c in residual["cells"][residual["new"]].tolist()}
    assert (8, 8) in new and (4, 4) not in new  # marked: never calibrated / calibrated
    truth = recording([(0.8, 0.8)] * 4 + [(0.4, 0.4)] * 4, seed=3, level=2.0)
    paper, _ = calibrate_arrays(*arrays(truth), profile=PROFILE, sweep="free")
    real, _ = calibrate_methods(
        paper, *arrays(truth), harmonic=MethodCalibration.from_model(model).harmonic
    )
    loud = recording([(0.8, 0.8)] * 4, seed=4)
    paper, _ = calibrate_arrays(*arrays(loud), profile=PROFILE, sweep="free")
    beyond, _ = calibrate_methods(
        paper, *arrays(loud), harmonic=MethodCalibration.from_model(model).harmonic
    )

    def db(a, b):
        return 10 * math.log10(a / b)

    # the unseen cell: from the fill (the nearest calibrated cell) to within 1.5 dB of what
    # a calibration there measures
    fill, learnt, measured = (
        residual_power(model, (8, 8)),
        learnt_power(adapted, (8, 8)),
        residual_power(beyond, (8, 8)),
    )
    assert abs(db(learnt, measured)) < 1.5 < abs(db(fill, measured))
    # the calibrated cell followed the robot getting louder (+6 dB) most of the way
    before, after = residual_power(model, (4, 4)), learnt_power(adapted, (4, 4))
    assert 4.0 < db(after, before) < 7.5
    assert abs(db(after, residual_power(real, (4, 4)))) < 2.0
    # the harmonic map: corrections and amplitudes where the joints dwelt
    assert harmonic is not None and (harmonic["blocks"] > 0).sum() >= 2
    assert np.isfinite(harmonic["correction"][harmonic["blocks"] > 0]).all()


def test_a_saved_adapted_model_denoises_as_the_adapted_table_and_goes_on_learning(model, tmp_path):
    rec = recording([(0.8, 0.8)] * 3, seed=5)
    denoiser, _, _ = run_adapting(model, rec, forget_s=2.0)
    adapted = denoiser.adapted_model()
    path = tmp_path / "adapted.npz"
    adapted.save(path)
    loaded = NoiseModel.load(path)
    assert loaded.extras[DETECTOR_PREFIX + "hybrid"] == model.extras[DETECTOR_PREFIX + "hybrid"]
    before, after = learnt_state(adapted), learnt_state(loaded)
    for part in range(2):
        for key, value in before[part].items():
            assert np.array_equal(after[part][key], value, equal_nan=True), key
    # without adapt, the learnt cells are in its table: the same expected powers as the
    # table the adapting denoiser ended with
    fixed = make_denoiser(loaded, "hybrid")
    velocity = np.array([[0.8, 0.8], [0.75, 0.82], [0.4, 0.4], [0.1, 0.9]])
    ended = denoiser._table.rows(velocity)
    again = fixed._table.rows(velocity)
    assert np.array_equal(ended[0], again[0]) and np.array_equal(ended[1], again[1])
    assert not fixed.adapting and fixed.adaptation_stats.cells_learnt == before[0]["new"].size
    # with adapt, it goes on from there: its blocks add to the saved ones
    more, _, _ = run_adapting(loaded, recording([(0.8, 0.8)] * 2, seed=6), forget_s=2.0)
    cell = np.all(learnt_state(more.adapted_model())[0]["cells"] == [8, 8], axis=1)
    saved = np.all(before[0]["cells"] == [8, 8], axis=1)
    assert learnt_state(more.adapted_model())[0]["blocks"][cell][0] > before[0]["blocks"][saved][0]


def test_never_learns_from_a_contact_and_the_taps_leave_the_cells_as_they_were(model):
    """Strong taps every 0.5 s: no block within the guard time of one is learnt, and the
    taps raise no cell: a calibrated one ends where it ends without them (within 0.5 dB),
    a new one (rising from the fill at the bounded rate, on fewer blocks) below."""
    speeds = [(0.4, 0.4)] * 3 + [(0.8, 0.8)] * 3
    with_taps = recording(speeds, seed=7, taps_per_s=2.0, tap_peak=6.0)
    without = recording(speeds, seed=7)
    committed, above = [], []
    denoiser = make_denoiser(model, "hybrid", adapt=AdaptSettings(forget_s=2.0, guard_s=0.1))
    adaptation = denoiser._adaptation
    commit, push = adaptation.cells.commit, adaptation.gate.push

    def spy_commit(candidate):
        committed.append((candidate.first_ns, candidate.last_ns))
        commit(candidate)

    def spy_push(stamps, values):  # the gate's runs above its threshold, as they end
        push(stamps, values)
        for run in adaptation.gate._intervals:
            if run not in above:
                above.append(run)

    adaptation.cells.commit, adaptation.gate.push = spy_commit, spy_push
    denoiser.run_arrays(*arrays(with_taps), 30.0)
    onsets = with_taps["t"][with_taps["onsets"]]
    first, last = np.array(committed).T
    runs = np.array([(a, b) for a, b in above])
    ms = 1_000_000
    for onset in onsets:
        # the detector saw every tap: a run above its threshold within 10 ms of the onset
        assert np.any((runs[:, 0] <= onset + 10 * ms) & (runs[:, 1] >= onset - 10 * ms))
        # and nothing from 50 ms before a tap to 60 ms after it (e^-7.5 of it left) is learnt
        assert not np.any((first < onset + 60 * ms) & (last > onset - 50 * ms))
    for a, b in runs:  # no block within the guard time of anything above the threshold
        assert not np.any((first <= b + 100 * ms) & (last >= a - 100 * ms))
    stats = denoiser.adaptation_stats
    assert stats.contacts >= len(onsets) and stats.blocks_gated > 0 and stats.blocks_learnt > 50
    clean, _, _ = run_adapting(model, without, forget_s=2.0, guard_s=0.1)
    tapped = [learnt_power(denoiser.adapted_model(), cell) for cell in ((4, 4), (8, 8))]
    quiet = [learnt_power(clean.adapted_model(), cell) for cell in ((4, 4), (8, 8))]
    assert abs(10 * math.log10(tapped[0] / quiet[0])) < 0.5
    assert tapped[1] < quiet[1]


def test_a_cell_changes_at_most_max_rate_db_s():
    """A cell fed blocks 20 dB louder than it holds rises by max_rate_db_s per second of its
    blocks (hop / fs each), per bin; the mean by half of it in dB."""
    residual = SimpleNamespace(
        channels=("combined", "x", "y", "z"),
        block_length=32,
        hop=16,
        window=np.hanning(32),
        sample_rate_hz=FS,
        grid=(np.linspace(0, 1, 11),),
        grid_shape=(11,),
        n_joints=1,
        cells=np.zeros((0, 1), np.int64),
        _cell_ids=np.zeros(0, np.int64),
    )
    settings = AdaptSettings(forget_s=1000.0, max_rate_db_s=6.0)
    learner = CellLearner(residual, settings)
    quiet = np.full((4, 17), 0.1)
    learner._add(3, np.array([3]), quiet, quiet**2, 0.0, 0, True)
    loud = Candidate(0, 1, 3, np.array([3]), np.full((4, 17), 1.0))
    per_block_db = 6.0 * 16 / FS
    for k in range(1, 41):
        before = learner.power[0].copy()
        learner.commit(loud)
        step = 10 * np.log10(learner.power[0] / before)
        assert np.all(step <= per_block_db + 1e-9)
        assert np.allclose(10 * np.log10(learner.power[0] / quiet**2), k * per_block_db)
    assert np.all(learner.mean[0] <= np.sqrt(learner.power[0]))
    assert learner.blocks[0] == 40 and learner.changed == {0}


def test_reset_returns_to_the_calibrated_model_and_learning_goes_on(model):
    rec = recording([(0.8, 0.8)] * 3, seed=8)
    denoiser, _, _ = run_adapting(model, rec, forget_s=2.0)
    fresh = make_denoiser(model, "hybrid")
    assert not np.array_equal(denoiser._table.base._table, fresh._table._table)
    denoiser.reset_adaptation()
    assert np.array_equal(denoiser._table.base._table, fresh._table._table)
    assert np.array_equal(denoiser._table.base._measured, fresh._table._measured)
    stats = denoiser.adaptation_stats
    assert stats.resets == 1 and stats.cells_learnt == 0 and stats.harmonic_points == 0
    assert learnt_state(denoiser.adapted_model())[0]["cells"].shape == (0, 2)
    denoiser.run_arrays(*arrays(recording([(0.8, 0.8)] * 2, seed=9)), 30.0)
    assert denoiser.adaptation_stats.cells_learnt >= 1


@settings(max_examples=8, deadline=None)
@given(
    st.sampled_from(["cancel", "hybrid"]),
    st.lists(st.integers(min_value=1, max_value=700), min_size=1, max_size=8),
    st.sampled_from([("per_axis", "dropin"), ("per_axis", "bandpassed"), ("combined", None)]),
    st.booleans(),
)
def test_streaming_equals_batch_for_any_chunking_while_adapting(
    model, blind, method, cuts, layout, finding_lines
):
    channels, output = layout
    model = blind if finding_lines else model
    rec = recording([(0.4, 0.4), (0.8, 0.7), (0.8, 0.7)], seed=10, taps_per_s=2.0, dwell_s=1.0)
    keep = np.ones(len(rec["t"]), bool)
    keep[1200:1230] = False  # a long gap: the segment ends and restarts
    t, accel, tj, velocity = rec["t"][keep], rec["accel"][keep], rec["tj"], rec["velocity"]
    adapt = AdaptSettings(forget_s=1.0, guard_s=0.05, max_rate_db_s=40.0)
    options = dict(channels=channels, output=output, adapt=adapt)
    batch = make_denoiser(model, method, **options)  # denoise_batch_method's one run
    want_t, want, _ = batch.run_arrays(t, accel, tj, velocity, 30.0)
    denoiser = make_denoiser(model, method, **options)
    edges = np.r_[np.unique(np.clip(np.cumsum(cuts), 1, len(t))), len(t)]
    got_t, got, j_pos, start = [], [], 0, 0
    for stop in np.unique(edges):
        limit = int(np.searchsorted(tj, t[stop - 1] + 21_000_000, side="right"))
        for a in range(j_pos, limit, 7):  # joint states in small batches
            chunk = denoiser.push_joint_states(
                tj[a : min(a + 7, limit)], velocity[a : min(a + 7, limit)]
            )
            got_t.append(chunk.stamps_ns)
            got.append(chunk.values)
        j_pos = max(j_pos, limit)
        chunk = denoiser.push_sensor(t[start:stop], accel[start:stop])
        got_t.append(chunk.stamps_ns)
        got.append(chunk.values)
        start = stop
    chunk = denoiser.push_joint_states(tj[j_pos:], velocity[j_pos:])
    got_t.append(chunk.stamps_ns)
    got.append(chunk.values)
    chunk = denoiser.flush()
    got_t.append(chunk.stamps_ns)
    got.append(chunk.values)
    assert np.array_equal(np.concatenate(got_t), want_t)
    assert np.array_equal(np.concatenate(got), want)
    assert denoiser.adaptation_stats == batch.adaptation_stats
    learnt = denoiser._adaptation.extras()
    for key, value in batch._adaptation.extras().items():
        assert np.array_equal(learnt[key], value, equal_nan=True), key
    if method == "hybrid":
        assert denoiser.adaptation_stats.blocks_learnt > 0
    if finding_lines:
        assert denoiser.adaptation_stats.map_refits > 0


@pytest.fixture(scope="module")
def blind(model) -> NoiseModel:
    """As a quadcopter calibrated at idle: `model` with no line in its harmonic map."""
    cal = MethodCalibration.from_model(model)
    bare = HarmonicMap(
        **{**vars(cal.harmonic), "line_joint": [], "line_coefficient": [], "line_score_db": []}
    )
    return model.replace(
        extras={**model.extras, **dataclasses.replace(cal, harmonic=bare).to_extras()}
    )


def test_lines_the_calibration_never_showed_are_found_at_speeds_beyond_it(blind):
    # 6 s: the line finder refits at 0.5, 1, 2 and 4 s of data (9 s added one at 8 s, ~3 s
    # of CPU; both find 8 lines, the late residual 0.45 of the blind map's)
    rec = recording([(0.8, 0.7)] * 3 + [(0.9, 0.8)], seed=12, taps_per_s=1.0)
    options = dict(adapt=AdaptSettings(), output="bandpassed")
    denoiser = make_denoiser(blind, "cancel", **options)
    stamps, found, _ = denoiser.run_arrays(*arrays(rec), 30.0)
    stats = denoiser.adaptation_stats
    assert stats.map_refits >= 1 and stats.lines_found >= 2
    fixed = denoise_batch_method(*arrays(rec), blind, method="cancel", output="bandpassed")[1]
    # the second half, lines found by then: less left than with the blind map (about 2 dB;
    # the calibrated map's 3.5)
    late = slice(len(found) // 2, None)
    assert np.mean(found[late] ** 2) < 0.75 * np.mean(fixed[late] ** 2)
    # any chunking switches maps at the same sample
    chunked = make_denoiser(blind, "cancel", **options)
    got = [chunked.push_joint_states(rec["tj"], rec["velocity"]).values]
    for part in np.array_split(np.arange(len(rec["t"])), 7):
        got.append(chunked.push_sensor(rec["t"][part], rec["accel"][part]).values)
    got.append(chunked.flush().values)
    assert np.array_equal(np.concatenate(got), found)
    # saved: the found map is the model's map, marked as found online
    adapted = denoiser.adapted_model()
    assert MethodCalibration.from_model(adapted).harmonic.n_lines == stats.lines_found
    assert describe_learnt(adapted)["lines_found"] == stats.lines_found
    again = make_denoiser(adapted, "cancel", **options)  # goes on: the same joints open
    assert again._adaptation.lines.open.all() and again.adaptation_stats.lines_found > 0
    denoiser.reset_adaptation()
    assert denoiser.adaptation_stats.lines_found == 0
    assert denoiser._canceller.map.n_lines == 0


def test_a_joint_without_lines_beyond_the_calibration_is_refitted_a_few_times_only(blind):
    cal = MethodCalibration.from_model(blind)
    finder = LineFinder(cal.harmonic, blind, cal.residual, cal.canceller)
    rng = np.random.default_rng(3)
    piece = int(0.04 * FS)
    for _ in range(int(14.0 / 0.04)):  # 14 s of broadband noise at 0.9, beyond 0.5
        finder.push(rng.standard_normal((piece, 3)), np.full((piece, 2), 0.9))
        assert finder.at_update() is None
    # at 0.5, 1, 2 and 4 s of data (twice that is more than the 8 s kept), then only at
    # new speeds
    assert finder.refits == 4 and finder.lines_found == 0
    for _ in range(30):
        finder.push(rng.standard_normal((piece, 3)), np.full((piece, 2), 1.2))
        finder.at_update()
    assert finder.refits == 5


def test_the_gate_clears_a_block_only_once_the_output_passed_its_guard_time():
    settings = ContactSettings(sample_rate_hz=FS, band_hz=(60.0, 450.0), threshold=0.5)
    gate = ContactGate(settings, guard_s=0.05, prefiltered=True, summed=False)
    t = 10**9 + np.arange(400, dtype=np.int64) * 1_000_000  # 1 ms apart
    x = np.zeros(400)
    x[200:210] = 5.0  # above the threshold around 200-215 ms
    gate.push(t[:100], x[:100, None])
    assert gate.decide(int(t[10]), int(t[40])) is True  # passed by 50 ms: clear
    assert gate.decide(int(t[40]), int(t[70])) is None  # not passed yet
    gate.push(t[100:], x[100:, None])
    assert gate.decide(int(t[40]), int(t[70])) is True
    assert gate.decide(int(t[130]), int(t[160])) is False  # within 50 ms of the contact
    assert gate.decide(int(t[220]), int(t[240])) is False
    assert gate.decide(int(t[290]), int(t[320])) is True
    assert gate.contacts == 1
    gate.end_segment()
    assert gate.decide(int(t[290]), int(t[320])) is None


def test_the_line_finders_gate_takes_a_lasting_level_as_noise_and_a_transient_as_contact():
    settings = ContactSettings(sample_rate_hz=FS, band_hz=(60.0, 450.0), threshold=0.5)
    gate = TransientGate(settings, guard_s=0.02, prefiltered=True, summed=False)
    rng = np.random.default_rng(0)
    t = 10**9 + np.arange(3000, dtype=np.int64) * 1_000_000  # 1 ms apart
    x = 3.0 * rng.standard_normal(3000)  # lines the model misses: 6x the detector's threshold
    x[2000:2010] += 60.0  # a tap
    for a in range(0, 3000, 40):  # pushed as the updates push it
        gate.push(t[a : a + 40], x[a : a + 40, None])
    # the first push (no level yet: the detector's threshold alone) and the tap
    assert gate.contacts == 2
    assert gate.decide(int(t[1000]), int(t[1040])) is True
    assert gate.decide(int(t[1960]), int(t[1990])) is False
    plain = ContactGate(settings, guard_s=0.02, prefiltered=True, summed=False)
    plain.push(t, x[:, None])
    assert plain.decide(int(t[1000]), int(t[1040])) is False


def test_the_harmonic_map_learns_where_the_speed_is_steady_and_starts_the_stream_from_it():
    hmap = SimpleNamespace(
        n_joints=1,
        n_lines=2,
        line_joint=np.array([0, 0]),
        min_speed=np.array([0.05]),
    )
    state = SimpleNamespace(
        lagged=np.array([0.45]),
        correction=np.array([0.0]),
        weights=np.ones((3, 2, 2)),
        weights_w=np.ones((3, 2, 2)),
    )
    canceller = SimpleNamespace(
        state=state, n_channels=3, settings=SimpleNamespace(max_correction=0.2)
    )
    learner = HarmonicLearner(hmap, (np.linspace(0, 1, 11),), canceller, AdaptSettings())
    # at speed 0.4 correction 0.01, amplitudes 1; at 0.5 correction 0.05, amplitudes 2; a
    # span whose speed moved by more than half a step teaches nothing
    for speed, before, correction, amplitude in (
        (0.4, 0.4, 0.01, 1.0), (0.5, 0.5, 0.05, 2.0), (0.5, 0.3, 0.5, 9.0)
    ):  # fmt: skip
        now = (np.array([speed]), np.array([correction]), np.full((2, 3), amplitude))
        for _ in range(MIN_POINT_SPANS):
            learner.commit((0, 1, np.array([before]), now), 0.1)
    assert learner.updates == 2 * MIN_POINT_SPANS
    assert np.flatnonzero(learner.blocks[0]).tolist() == [4, 5]
    assert learner.correction[0, 5] == pytest.approx(0.05) and learner.amplitude[0, 5, 0] == 2.0
    learner.warm_start()  # the stream's start at 0.45: half way between the learnt points
    assert state.correction[0] == pytest.approx(0.03)
    state.correction[:] = 0.0
    learner.warm_start()  # once only
    assert state.correction[0] == 0.0
    fresh = HarmonicLearner(hmap, (np.linspace(0, 1, 11),), canceller, AdaptSettings())
    state.lagged[:] = 0.9  # beyond what the map learnt: nothing
    fresh.load({"correction": learner.correction, "amplitude": learner.amplitude,
                "blocks": learner.blocks})  # fmt: skip
    fresh.warm_start()
    assert state.correction[0] == 0.0


def test_bad_settings_and_models_are_one_line_errors(model):
    with pytest.raises(ConfigError, match="adapt: forget_s"):
        AdaptSettings(forget_s=0.0)
    with pytest.raises(ConfigError, match="adapt: threshold"):
        AdaptSettings(threshold=-1.0)
    with pytest.raises(ConfigError, match="method paper: adapt"):
        make_denoiser(model, "paper", adapt=AdaptSettings())
    bare = model.replace(
        extras={k: v for k, v in model.extras.items() if not k.startswith(DETECTOR_PREFIX)}
    )
    with pytest.raises(ConfigError, match="threshold for method hybrid"):
        make_denoiser(bare, "hybrid", adapt=AdaptSettings())
    assert make_denoiser(bare, "hybrid", adapt=AdaptSettings(threshold=1.0)).adapting
    broken = model.replace(extras={**model.extras, ADAPT_PREFIX + "residual.cells": np.zeros(3)})
    with pytest.raises(ModelFileError, match="lack"):
        make_denoiser(broken, "hybrid")
