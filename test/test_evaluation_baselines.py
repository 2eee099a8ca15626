"""Every baseline runs on the same data through the real core and returns the right
shape and delay."""

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import signal

from egovib_research.experiments import scoring
from egovib_ros.bag import Recording
from egovib_ros.core import calibrate_arrays
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.core.methods import SAMPLE_METHODS, has_method_calibration, make_denoiser
from egovib_ros.evaluation import baselines, metrics
from egovib_ros.evaluation.stream import method_names
from egovib_ros.sim.pr2 import MAX_SPEED, grid_values

FS = 3000.0


def _recording(velocity_of_t, duration_s, *, taps=(), seed=0):
    """Velocity-dependent band-limited vibration (+ optional decaying taps on x) with
    joint states."""
    rng = np.random.default_rng(seed)
    n, m = int(duration_s * FS), int(duration_s * 1000)
    accel_t = (np.arange(n) * 1e9 / FS).astype(np.int64)
    joint_t = (np.arange(m) * 1e6).astype(np.int64)
    velocity = velocity_of_t(joint_t / 1e9)
    v_at_accel = np.stack([np.interp(accel_t, joint_t, velocity[:, j]) for j in range(2)], axis=1)
    sos = signal.butter(4, [250, 600], btype="bandpass", fs=FS, output="sos")
    level = (
        0.05
        + np.abs(v_at_accel[:, 0]) / MAX_SPEED[0]
        + 0.5 * np.abs(v_at_accel[:, 1]) / MAX_SPEED[1]
    )
    ego = signal.sosfilt(sos, rng.normal(size=(n, 3)), axis=0) * level[:, None]
    contact = np.zeros((n, 3))
    for onset in taps:
        k = np.arange(min(240, n - onset))
        contact[onset : onset + k.size, 0] = (
            4.0 * np.exp(-k / 30.0) * np.sin(2 * np.pi * 420 * k / FS)
        )
    return Recording(
        accel_t,
        ego + contact + [0.0, 0.0, 9.81],
        joint_t,
        np.cumsum(velocity, 0) / 1e3,
        velocity,
        contact=contact,
        ego=ego,
    )


@dataclass
class Context:
    model: object
    model_short: object = None
    noise_clip: np.ndarray | None = None


def run_method(name: str, rec, ctx: Context) -> np.ndarray:
    """(N,) output of method `name` on the recording `rec`: its stream fed it at once."""
    gate = None
    if name == "noisereduce" and ctx.noise_clip is not None:
        gate = baselines.gate_threshold(ctx.noise_clip)
    stream = baselines.method_stream(name, model=ctx.model, model_short=ctx.model_short, gate=gate)
    raw = combined_bandpassed(rec.sensor, ctx.model.robot_profile())
    parts = [
        stream.push_joint_states(rec.joint_stamps_ns, rec.joint_velocity),
        stream.push(rec.sensor_stamps_ns, rec.sensor, raw),
        stream.finish(),
    ]
    return np.concatenate(parts)


def delay_ms(name: str, ctx: Context) -> float:
    return baselines.method_stream(name, model=ctx.model, model_short=ctx.model_short).delay_ms


@pytest.fixture(scope="module")
def context():
    grid = (grid_values(0), grid_values(1))
    cells = [(a, 0.0) for a in grid[0]] + [(0.0, b) for b in grid[1] if b != 0]
    dwell = 0.5
    sweep = _recording(
        lambda t: np.array(cells)[np.minimum((t / dwell).astype(int), len(cells) - 1)],
        dwell * len(cells),
        seed=1,
    )
    arrays = (sweep.sensor_stamps_ns, sweep.sensor, sweep.joint_stamps_ns, sweep.joint_velocity)
    model, _ = calibrate_arrays(*arrays, sweep="superposition")
    model_short, _ = calibrate_arrays(*arrays, sweep="superposition", block_length=32, hop=16)
    clip = combined_bandpassed(sweep.sensor, model.robot_profile())
    return Context(model=model, model_short=model_short, noise_clip=clip)


@pytest.fixture(scope="module")
def moving():
    return _recording(
        lambda t: np.stack([1.5 * np.sin(0.9 * t), 0.02 * np.sin(0.6 * t + 1)], axis=1),
        6.0,
        taps=(3000, 7500, 12000),
        seed=2,
    )


def test_every_method_runs_with_shape_and_delay(context, moving):
    names = method_names(
        None,
        calibration=context.noise_clip is not None,
        model_short=context.model_short,
        model=context.model,
    )
    # cancel and hybrid only when the model was calibrated for them (this one was not)
    assert not has_method_calibration(context.model)
    assert names == [m for m in baselines.METHOD_LABELS if m not in SAMPLE_METHODS]
    raw = combined_bandpassed(moving.sensor, context.model.robot_profile())
    for name in names:
        out = run_method(name, moving, context)
        assert out.shape == (len(moving.sensor),), name
        assert np.all(np.isfinite(out)), name
        delay = delay_ms(name, context)
        assert delay is not None and delay >= 0.0
    assert np.array_equal(run_method("bandpass", moving, context), raw)
    # the block's first sample waits for the rest of it: the paper's denoiser's own delay
    assert delay_ms("paper", context) == pytest.approx(63 / 3.0)
    assert delay_ms("paper_L32", context) == pytest.approx(31 / 3.0)
    assert delay_ms("paper", context) == make_denoiser(context.model, "paper").delay_ms
    assert delay_ms("bandpass", context) == 0.0


def test_subtraction_methods_reduce_noise_in_order(context, moving):
    """More subtraction, less residual noise: Boll (mean) > paper (mean + std) outside contacts."""
    reference = combined_bandpassed(moving.contact, context.model.robot_profile())
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    noise = {
        name: scoring.noise_mean(run_method(name, moving, context), seg.no_contact_mask)
        for name in ("bandpass", "boll", "paper", "wiener")
    }
    assert noise["bandpass"] > noise["boll"] > noise["paper"]
    assert noise["wiener"] < noise["bandpass"]


def test_denoised_output_is_aligned_with_input_stamps(context, moving):
    """The core's output sample k carries input stamp k: no shift against the clean reference."""
    reference = combined_bandpassed(moving.contact, context.model.robot_profile())
    for name in ("paper", "per_axis", "paper_L32", "wiener"):
        lag = metrics.LagCorrelation()
        lag.push(reference, run_method(name, moving, context))
        assert lag.lag() == 0, name


def test_wiener_rule_gain_between_zero_and_one_and_stateful():
    rng = np.random.default_rng(4)
    magnitude = rng.uniform(0, 3, size=(50, 33, 1))
    noise = np.full_like(magnitude, 1.0)
    rule = baselines.WienerRule()
    cleaned = rule(magnitude, noise)
    assert np.all(cleaned >= 0) and np.all(cleaned <= magnitude + 1e-12)
    # Feeding the same blocks in two batches gives the same result as one batch.
    split = baselines.WienerRule()
    parts = np.concatenate([split(magnitude[:17], noise[:17]), split(magnitude[17:], noise[17:])])
    assert np.allclose(parts, cleaned)


def test_methods_needing_extra_data_say_so(context, moving):
    bare = Context(model=context.model)
    names = method_names(None, calibration=False, model_short=None, model=bare.model)
    assert "paper_L32" not in names and "noisereduce" not in names
    with pytest.raises(ValueError, match="32-sample"):
        run_method("paper_L32", moving, bare)
    with pytest.raises(ValueError, match="no noise threshold"):
        run_method("noisereduce", moving, bare)
    with pytest.raises(ValueError, match="unknown method"):
        run_method("magic", moving, bare)
