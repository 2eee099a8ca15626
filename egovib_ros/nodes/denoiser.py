"""denoiser: streaming ego-vibration removal as a ROS 2 node (docs/live_nodes.md).

The `method` (paper, cancel, hybrid) is built by the function `egovib denoise --method`
uses, so live equals offline; topics, Imu field, joints and rate come from the noise
model's robot profile. Each output Imu is its input message with the profile's field
replaced by the cleaned value (a drop-in replacement), so input messages are held until
their samples come out. With method paper, `oversubtraction` and `floor` change live; with
`adapt` (cancel, hybrid) the model goes on learning while no contact is seen, served by
`~/save_model` and `~/reset_model` (std_srvs/Trigger).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import replace
from math import nan
from pathlib import Path

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import Imu
from std_srvs.srv import Trigger

from egovib_ros.bag.codec import replace_imu_field
from egovib_ros.core import NoiseModel
from egovib_ros.core.adapt import AdaptSettings
from egovib_ros.core.held import output_rows
from egovib_ros.core.methods import METHODS, make_denoiser, resolve_method
from egovib_ros.core.stream import RateWatch
from egovib_ros.core.subtraction import MAX_FLOOR, MAX_OVERSUBTRACTION
from egovib_ros.errors import ConfigError, EgovibError, RateError
from egovib_ros.gap.advice import noise_gain_from_report
from egovib_ros.nodes.common import (
    Health,
    Param,
    StreamInput,
    declare_parameters,
    run_node,
    stream_counters,
    stream_publisher,
)
from egovib_ros.outputs import atomic_output

LIVE = ("oversubtraction", "floor")
#: The model-coverage WARN looks at the blocks of the last this many seconds ...
COVERAGE_WINDOW_S = 10.0
#: ... and clears once their share on unmeasured cells is below this x the limit.
COVERAGE_CLEAR_FRACTION = 0.5
MODEL_PARAMETERS = (
    Param(
        "model",
        "",
        "noise-model file (.npz) from `egovib calibrate` or the calibrator node; the robot "
        "profile it carries gives topics, Imu field, joints and rate",
    ),
    Param(
        "channels",
        "per_axis",
        "per_axis: clean each axis (drop-in replacement) | combined: the paper's "
        "1-D signal in x, y = z = 0",
        choices=("per_axis", "combined"),
    ),
    Param(
        "method",
        "",
        "empty: the model's default (hybrid where the model carries it) | hybrid: "
        "speed-locked harmonic cancellation, then a low-latency gain (4 ms band-passed; the "
        "drop-in output the look-ahead its split needs, 4-10 ms) | paper: the paper's block "
        "spectral subtraction (a block of delay) | cancel: the cancellation alone (no delay)",
        choices=("", *METHODS),
    ),
)
PARAMETERS = MODEL_PARAMETERS + (
    Param(
        "output",
        "dropin",
        "dropin (default): the raw field minus the estimated ego-vibration (gravity and motion "
        "below the band kept; hybrid: the look-ahead its split needs) | bandpassed: the "
        "cleaned band-passed signal; channels combined is always band-passed",
        choices=("dropin", "bandpassed"),
    ),
    Param(
        "oversubtraction",
        1.0,
        "alpha in max(|Y| - alpha N, beta N); changes live",
        read_only=False,
        range=(0.0, MAX_OVERSUBTRACTION),
    ),
    Param(
        "floor",
        0.0,
        "beta in max(|Y| - alpha N, beta N); changes live",
        read_only=False,
        range=(0.0, MAX_FLOOR),
    ),
    Param(
        "joint_lag",
        0.0,
        "seconds the vibration trails the joint states (`egovib gap` timing advice, as "
        "`egovib denoise --joint-lag`); negative: it leads them",
        range=(-1.0, 1.0),
    ),
    Param(
        "noise_gain",
        "",
        "an `egovib gap` report with a drift verdict: its noise level change over time "
        "applied from the stream's start, as `egovib denoise --noise-gain`",
    ),
    Param(
        "batch_samples",
        32,
        "process every this many sensor samples (default: paper, the model's hop, counted "
        "from the first, i.e. as soon as a block completes; cancel and hybrid, as soon as "
        "2 ms of samples wait)",
        range=(1, 100_000),
    ),
    Param(
        "joint_wait",
        0.02,
        "seconds of stream time a completed block waits for the joint states covering it "
        "(longer: exact for replays whose joint states may lag, at the cost of latency)",
        range=(0.0, 10.0),
    ),
    Param(
        "flush_after_idle",
        0.5,
        "seconds without input after which the samples held for overlap-add are "
        "published (0 = never)",
        range=(0.0, 3600.0),
    ),
    Param(
        "stale_after",
        1.5,
        "seconds without input before /diagnostics reports STALE (reported at the "
        "next 1 Hz report)",
        range=(0.1, 3600.0),
    ),
    Param(
        "adapt",
        False,
        "learn the model online while the contact detector sees no contact (methods cancel "
        "and hybrid; as `egovib denoise --adapt`): the residual table's cells at the speeds "
        "met, calibrated or not, and the harmonic map's corrections and amplitudes",
    ),
    Param(
        "forget_s",
        AdaptSettings().forget_s,
        "with adapt: the forgetting time (s of contact-free time at a speed)",
        range=(0.01, 1e6),
    ),
    Param(
        "save_model",
        "",
        "where the ~/save_model service writes the adapted model (empty: <model>_adapted.npz "
        "beside the model)",
    ),
    Param(
        "unmeasured_warn_fraction",
        0.25,
        "WARN when more than this share of the blocks of the last 10 s fell on cells the "
        "calibration did not measure (full and free-motion models; a superposition model "
        "fills the cells off the axes by Eq. 6 by design); the WARN clears below half of it",
        range=(0.0, 1.0),
    ),
)


class CoverageWarning:
    """Whether to WARN about model coverage: the share of the last COVERAGE_WINDOW_S of
    blocks (or samples) on unmeasured cells exceeds `limit`; once on, until that share falls
    below COVERAGE_CLEAR_FRACTION x `limit` (a free-motion model's share hovers around any
    limit from one second to the next: hysteresis, not a flip every report)."""

    def __init__(self, limit: float):
        self.limit = float(limit)
        self._reports: deque = deque()  # (monotonic time, counted, unmeasured) per report
        self.share = 0.0
        self.active = False

    def update(self, counted: int, unmeasured: int, now: float | None = None) -> bool:
        """Add a report's counts (`now`: its monotonic time); whether to WARN."""
        now = time.monotonic() if now is None else now
        self._reports.append((now, counted, unmeasured))
        while now - self._reports[0][0] > COVERAGE_WINDOW_S:
            self._reports.popleft()
        total = sum(r[1] for r in self._reports)
        self.share = sum(r[2] for r in self._reports) / total if total else 0.0
        if self.active:
            self.active = self.share >= COVERAGE_CLEAR_FRACTION * self.limit
        else:
            self.active = self.share > self.limit
        return self.active


class HeldInput:
    """Input messages kept until their samples are output (for the drop-in output and the
    wall-clock latency). The core outputs a subsequence of the input in arrival order:
    it drops out-of-order samples and never outputs gap fill."""

    def __init__(self):
        self.stamps = np.zeros(0, dtype=np.int64)
        self.arrival = np.zeros(0, dtype=np.int64)
        self.raws: list[bytes] = []

    def add(self, stamps: np.ndarray, raws: list[bytes], arrival: np.ndarray) -> None:
        self.stamps = np.concatenate([self.stamps, stamps])
        self.arrival = np.concatenate([self.arrival, arrival])
        self.raws.extend(raws)

    def take(self, stamps: np.ndarray) -> tuple[list[bytes], np.ndarray]:
        """The input messages (and arrival times) of the output samples `stamps`; held
        messages before them are discarded (the core dropped them)."""
        if not len(stamps):
            return [], np.zeros(0, dtype=np.int64)
        rows = output_rows(self.stamps, stamps)  # in arrival order, also across a clock jump
        raws = [self.raws[i] for i in rows]
        arrival = self.arrival[rows]
        cut = int(rows[-1]) + 1
        self.stamps, self.arrival, self.raws = (
            self.stamps[cut:],
            self.arrival[cut:],
            self.raws[cut:],
        )
        return raws, arrival

    def clear(self) -> int:
        n = len(self.raws)
        self.stamps, self.arrival, self.raws = self.stamps[:0], self.arrival[:0], []
        return n


#: How often the per-sample methods run, in seconds of samples: their output exists a fixed
#: delay after each sample, so waiting for more samples only adds latency (2 ms: what a
#: driver's own batching typically adds; shorter costs CPU in per-call overhead).
PER_SAMPLE_BATCH_S = 0.002


def default_batch_samples(model: NoiseModel, method: str) -> int:
    """The paper's method: one hop (a batch ends exactly when a block completes); cancel and
    hybrid: PER_SAMPLE_BATCH_S of samples."""
    if method == "paper":
        return model.hop
    return max(1, round(PER_SAMPLE_BATCH_S * model.sample_rate_hz))


class Denoiser(Node):
    def __init__(self):
        super().__init__("denoiser")
        first = declare_parameters(self, MODEL_PARAMETERS)
        if not first["model"]:
            raise ConfigError("denoiser: parameter 'model' (noise-model path) is required")
        self.model = NoiseModel.load(first["model"])
        self.profile = self.model.robot_profile()
        self.method = resolve_method(self.model, first["method"] or None)
        rest = PARAMETERS[len(MODEL_PARAMETERS) :]
        if self.method != "paper":  # their settings are fixed at start: advertised read-only
            rest = tuple(replace(p, read_only=True) if p.name in LIVE else p for p in rest)
        batch_samples = default_batch_samples(self.model, self.method)
        params = declare_parameters(self, rest, defaults={"batch_samples": batch_samples})
        self.channels = first["channels"]
        self.flush_after_idle_s = params["flush_after_idle"]
        self.coverage = CoverageWarning(params["unmeasured_warn_fraction"])
        self.output = params["output"] if self.channels == "per_axis" else "bandpassed"
        self.adapt = AdaptSettings(forget_s=params["forget_s"]) if params["adapt"] else None
        model_path = Path(first["model"])
        self.save_model_path = Path(
            params["save_model"] or model_path.with_name(model_path.stem + "_adapted.npz")
        )
        # the same construction as `egovib denoise --method` (bad combinations: one line)
        self._options = dict(
            channels=self.channels,
            output=self.output,
            oversubtraction=params["oversubtraction"],
            floor=params["floor"],
            joint_wait_s=params["joint_wait"],
            joint_lag_s=params["joint_lag"],
            noise_gain_db=noise_gain_from_report(params["noise_gain"], where="noise_gain"),
            source=self.resolve_topic_name(self.profile.node_sensor_topic),
            **({} if self.adapt is None else {"adapt": self.adapt}),
        )
        self.denoiser = make_denoiser(self.model, self.method, **self._options)
        self._rate_watch: RateWatch | None = None  # after a rate refusal: is it back?
        self.rate_recoveries = 0
        self.add_on_set_parameters_callback(self._on_set_parameters)
        if self.adapt is not None:
            self.create_service(Trigger, "~/save_model", self._on_save_model)
            self.create_service(Trigger, "~/reset_model", self._on_reset_model)

        self.input = StreamInput(
            self,
            self.profile,
            batch_samples=params["batch_samples"],
            on_batch=self._process,
            on_joint_state=self._on_joint_state,
            from_first=self.method == "paper",  # its blocks complete every hop from the first
        )
        self.pub = stream_publisher(self, Imu, self.profile.node_denoised_topic)
        self.health = Health(
            self, hardware_id=self.profile.name, stale_after_s=params["stale_after"]
        )
        self.held = HeldInput()
        # Output waiting for the core's rate check: (messages, values, arrival) per chunk.
        self._startup: list[tuple] = []
        self._rate_proven = False
        self._blocks_held_back = False
        self._last_input = time.monotonic()
        self._flushed = True
        self.samples_published = 0
        self.samples_withheld = 0  # input samples not published because of an ERROR
        self.stream_error: str | None = None
        self.missing_joints: list[str] = []
        self._latency_ms: list[np.ndarray] = []
        self._last_report = (time.monotonic(), 0, 0, 0)
        self.create_timer(0.05, self._on_idle_check)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f"denoising {self.input.sensor_topic} ({self.profile.sensor_field}, "
            f"{self.model.sample_rate_hz:g} Hz) -> {self.pub.topic_name} (method {self.method}, "
            f"{self.channels}"
            + (f", adapting, forgetting time {self.adapt.forget_s:g} s" if self.adapt else "")
            + "), "
            f"joints {list(self.profile.joint_names)} from "
            f"{self.input.joints_topic}, model {first['model']}"
        )

    # --- parameters --------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        """oversubtraction and floor take effect from the next block (rclpy has already
        checked their ranges and refused read-only parameters)."""
        changes = {p.name: p.value for p in params if p.name in LIVE}
        if not changes:
            return SetParametersResult(successful=True)
        try:
            self.denoiser.set_subtraction(**changes)
        except EgovibError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        settings = self.denoiser.subtraction
        self.get_logger().info(
            f"oversubtraction {settings.oversubtraction:g}, floor {settings.floor:g}"
        )
        return SetParametersResult(successful=True)

    # --- adaptation ------------------------------------------------------------------------
    def _on_save_model(self, request, response):
        """~/save_model: the model as adapted so far, written to `save_model` atomically."""
        try:
            model = self.denoiser.adapted_model()
            with atomic_output(self.save_model_path) as tmp:
                model.save(tmp)
        except (EgovibError, OSError) as exc:
            response.success, response.message = False, str(exc)
            self.get_logger().error(f"save_model: {exc}")
            return response
        stats = self.denoiser.adaptation_stats
        response.success = True
        response.message = (
            f"wrote {self.save_model_path}: {stats.cells_learnt} cells learnt online "
            f"({stats.cells_new} never calibrated), {stats.blocks_learnt} blocks, "
            f"{stats.lines_found} harmonic lines found online"
        )
        self.get_logger().info(response.message)
        return response

    def _on_reset_model(self, request, response):
        """~/reset_model: back to the calibrated model (learning goes on)."""
        self.denoiser.reset_adaptation()
        response.success, response.message = True, "back to the calibrated model"
        self.get_logger().info(f"reset_model: {response.message}")
        return response

    def _adapt_values(self) -> dict:
        """/diagnostics: what the adaptation counted (a model that learnt before, without
        adapt: its cells learnt online too)."""
        stats = getattr(self.denoiser, "adaptation_stats", None)
        values = {"adapt": self.adapt is not None}
        if self.adapt is not None:
            values["forget_s"] = self.adapt.forget_s
        if stats is not None:
            values.update(
                cells_learnt_online=stats.cells_learnt,
                cells_new_online=stats.cells_new,
                adapt_blocks_learnt=stats.blocks_learnt,
                adapt_blocks_gated=stats.blocks_gated,
                adapt_contacts=stats.contacts,
                adapt_harmonic_points=stats.harmonic_points,
                adapt_map_refits=stats.map_refits,
                adapt_lines_found=stats.lines_found,
                adapt_resets=stats.resets,
            )
        return values

    # --- input ---------------------------------------------------------------------------
    def _on_joint_state(self) -> None:
        # A completed block waits for the joint state covering its end: release it now
        # rather than at the next batch of samples (that would add up to a hop of delay).
        # Before the first sensor sample, take joint states as they come: a joint they lack
        # is an ERROR before any output (and is reported while the sensor is silent).
        if self._blocks_held_back or self.input.sensor_messages == 0:
            self._publish(self._push_joints())
            self._blocks_held_back = self.denoiser.samples_pending >= self.model.block_length

    def _process(self) -> None:
        """Decode what arrived; joint states first (they cover the new samples) and the
        samples in one pass of the core; publish."""
        self._last_input = time.monotonic()
        self._flushed = False
        joints = self._take_joints()
        batch = self.input.take_sensor()
        if batch is None or not len(batch.stamps_ns):
            released = None if joints is None else self.denoiser.push_joint_states(*joints)
        elif self.stream_error is not None:  # the core refuses this stream
            if joints is not None:
                self.denoiser.push_joint_states(*joints)
            self.samples_withheld += len(batch.stamps_ns)
            if self._rate_watch is not None and self._rate_watch.push(batch.stamps_ns):
                self._restart()  # its rate is back: from the next batch on
            return
        else:
            self.held.add(batch.stamps_ns, batch.raws, batch.arrival_ns)
            none = (np.zeros(0, np.int64), np.zeros((0, self.model.n_joints)))
            try:
                released = self.denoiser.push(*(joints or none), batch.stamps_ns, batch.values)
            except EgovibError as exc:
                self._refuse(str(exc), rate=isinstance(exc, RateError))
                return
        self._publish(released)
        # a completed block held back (more than a block of input not yet output)?
        self._blocks_held_back = self.denoiser.samples_pending >= self.model.block_length

    def _take_joints(self, *, final: bool = False):
        """(stamps, velocity) of the joint states received so far, or None.
        `final`: the input has gone quiet, the last stamp's held joint states come too."""
        batch = self.input.take_joints(final=final)
        # Output is withheld while any named joint is missing, also while joint states
        # arrive and none decodes (no row at all).
        self.missing_joints = self.input.missing_joints()
        if batch is None or not len(batch.stamps_ns):
            return None
        return batch.stamps_ns, batch.velocity

    def _push_joints(self, *, final: bool = False):
        """Joint states received so far into the core; the output they release (or None)."""
        joints = self._take_joints(final=final)
        return None if joints is None else self.denoiser.push_joint_states(*joints)

    def _refuse(self, reason: str, *, rate: bool) -> None:
        """The core refused the stream (e.g. its rate does not fit the model): publish nothing;
        for a rate that changed (`rate`), until it is back (`_restart`)."""
        reason += self.input.publishers_note()
        self.get_logger().error(
            f"{reason}: publishing nothing" + (" until the rate is back" if rate else "")
        )
        self.stream_error = reason
        self.samples_withheld += self.held.clear() + sum(len(r) for r, _, _ in self._startup)
        self._startup = []
        if rate:
            receipt = self.denoiser.sensor_stamps == "receipt"
            self._rate_watch = RateWatch(self.denoiser.settings, receipt=receipt)

    def _restart(self) -> None:
        """The stream's rate fits the model again (a burst at another rate has passed): the
        denoiser starts afresh, as on a new stream (its settings as they are now)."""
        live = getattr(self.denoiser, "subtraction", None)  # paper: as set at run time
        if live is not None:
            self._options.update(oversubtraction=live.oversubtraction, floor=live.floor)
        self.denoiser = make_denoiser(self.model, self.method, **self._options)
        self.get_logger().warning(
            f"{self.input.sensor_topic}: the sensor rate fits the model again: denoising "
            f"restarted ({self.samples_withheld} samples withheld so far)"
        )
        self.stream_error, self._rate_watch = None, None
        self._rate_proven = False
        self.rate_recoveries += 1

    def _publish(self, chunk, *, end_of_stream: bool = False) -> None:
        if self.stream_error is not None:
            return
        if chunk is not None and len(chunk):
            raws, arrival = self.held.take(chunk.stamps_ns)
            if self.missing_joints:
                self.samples_withheld += len(raws)  # no output claimed as denoised
                return
            self._startup.append((raws, chunk.values, arrival))
        if not self._rate_proven:
            # The core measures the stream's rate on its first samples; nothing is published
            # before that has passed (a stream at the wrong rate gives no output at all).
            if not self.denoiser.stats.rate_checked and not end_of_stream:
                return
            self._rate_proven = True
        pending, self._startup = self._startup, []
        for raws, values, arrival in pending:
            if values.shape[1] == 1:  # docs/INTERFACES.md: combined signal in x, y = z = 0
                values = np.concatenate([values, np.zeros((len(values), 2))], axis=1)
            for data in replace_imu_field(raws, values, self.profile.sensor_field):
                self.pub.publish(data)
            self.samples_published += len(raws)
            # latency on this machine's clock: input message received -> its output published
            self._latency_ms.append((time.monotonic_ns() - arrival) / 1e6)

    def _on_idle_check(self) -> None:
        idle = time.monotonic() - self._last_input
        if self.input.sensor_pending and idle > 0.02:
            self._process()
        elif not self._flushed and self.flush_after_idle_s > 0 and idle > self.flush_after_idle_s:
            self._flushed = True
            self._publish(self._push_joints(final=True))
            self._publish(self.denoiser.flush(), end_of_stream=True)
        # The stream stopping or coming back is reported at once, not at the next 1 Hz report.
        last = self.input.last_sensor_s
        if last is not None and self.health.level in ("ok", "warn", "stale"):
            stale = time.monotonic() - last >= self.health.stale_after_s
            if stale != (self.health.level == "stale"):
                self._publish_diagnostics()

    # --- health ----------------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        stats = self.denoiser.stats
        inp = self.input
        now = time.monotonic()
        last_t, last_in, last_out, last_joints = self._last_report
        period = max(now - last_t, 1e-3)
        self._last_report = (now, inp.sensor_messages, self.samples_published, inp.joint_messages)
        joint_rate_hz = (inp.joint_messages - last_joints) / period
        latency = np.concatenate(self._latency_ms) if self._latency_ms else np.zeros(0)
        self._latency_ms = []
        # paper counts blocks; cancel and hybrid work sample by sample
        unit = "blocks" if self.method == "paper" else "samples"
        # cancel and hybrid also process the samples bridged into gaps (and count them
        # unmeasured or out of grid): counted in the total too, so no share exceeds 1
        total = stats.blocks if unit == "blocks" else stats.samples_in + stats.gap_filled_samples
        counters = {
            **stream_counters(inp, stats),
            unit: total,
            **{
                f"{unit}_{key}": getattr(stats, f"{unit}_{key}") or 0
                for key in ("no_joint_state", "out_of_grid", "unmeasured")
            },
        }
        grown = self.health.changes(counters)
        blocks = max(grown[unit], 1)
        fractions = {
            key: grown[f"{unit}_{key}"] / blocks
            for key in ("no_joint_state", "out_of_grid", "unmeasured")
        }
        # A superposition model fills the cells off the axes by Eq. 6 by design: reported,
        # not warned about; a full or free-motion model falls back there.
        by_design = self.model.measured == "superposition"
        coverage_warn = (
            self.coverage.update(grown[unit], grown[f"{unit}_unmeasured"]) and not by_design
        )
        joint_age = now - inp.last_joint_s if inp.last_joint_s is not None else float("nan")
        values = {
            "input_rate_hz": (inp.sensor_messages - last_in) / period,
            "output_rate_hz": (self.samples_published - last_out) / period,
            "samples_in": inp.sensor_messages,
            "samples_published": self.samples_published,
            "samples_withheld": self.samples_withheld,
            "rate_recoveries": self.rate_recoveries,  # restarts once a changed rate was back
            **counters,
            "joint_states_in": inp.joint_messages,
            "joint_state_age_s": joint_age,
            **inp.velocity_values(),
            **inp.publisher_counts(),
            "output_subscribers": self.pub.get_subscription_count(),
            **{f"{key}_fraction": value for key, value in fractions.items()},
            "unmeasured_fraction_window": self.coverage.share,
            "latency_p50_ms": float(np.percentile(latency, 50)) if len(latency) else float("nan"),
            "latency_p99_ms": float(np.percentile(latency, 99)) if len(latency) else float("nan"),
            "latency_max_ms": float(latency.max()) if len(latency) else float("nan"),
            "model_rate_hz": self.model.sample_rate_hz,
            "joint_lag_s": self.denoiser.settings.joint_lag_s,
            # "receipt": a driver's arrival stamps, counted on a rebuilt sample clock
            "sensor_stamps": self.denoiser.sensor_stamps,
            "method": self.method,
            "channels": self.channels,
            "output": self.output,
            "oversubtraction": (
                self.denoiser.subtraction.oversubtraction if self.method == "paper" else nan
            ),
            "floor": self.denoiser.subtraction.floor if self.method == "paper" else nan,
            **self._adapt_values(),
        }
        missing = inp.missing_joints_error("cannot denoise, publishing nothing")
        errors = [e for e in (self.stream_error, missing) if e]
        warnings = self._warnings(grown, unit, fractions, coverage_warn, joint_rate_hz)
        stale = self.health.stale_message(inp.last_sensor_s, inp.sensor_topic)
        self.health.publish(
            errors=errors, stale=stale, warnings=warnings, ok="denoising", values=values
        )

    def _warnings(self, grown, unit, fractions, coverage_warn, joint_rate_hz) -> list[str]:
        """The /diagnostics warnings of one report: what grew since the last one."""
        inp = self.input
        warnings = []
        if inp.joint_messages == 0 and inp.sensor_messages > 0:
            warnings.append(
                f"no joint state on {inp.joints_topic}: passing the "
                f"{'input' if self.output == 'dropin' else 'band-passed signal'} through"
            )
        elif grown[f"{unit}_no_joint_state"]:
            notes = [inp.clock_note(), self._joint_rate_note(joint_rate_hz)]
            warnings.append(
                f"{grown[f'{unit}_no_joint_state']} {unit} without joint state (passed through"
                + "".join(f"; {note}" for note in notes if note)
                + ")"
            )
        for key, text in (
            ("undecodable_messages", "undecodable messages"),
            ("samples_bad", "bad samples"),
            ("samples_out_of_order", "samples out of order"),
            ("gap_filled_samples", "missing samples bridged"),
            ("stream_restarts", "stream restarts (a gap, a run of bad samples, or a clock jump)"),
            ("joint_states_dropped", "joint states dropped"),
        ):
            if grown[key]:
                warnings.append(f"{grown[key]} {text}")
        warnings += inp.stamp_notes(grown)
        if grown[f"{unit}_out_of_grid"]:
            warnings.append(
                f"{fractions['out_of_grid']:.0%} of {unit} beyond the model's velocity grid"
            )
        if coverage_warn:
            warnings.append(
                f"{self.coverage.share:.0%} of {unit} in the last {COVERAGE_WINDOW_S:g} s on "
                f"cells the calibration did not measure"
            )
        return warnings

    def _joint_rate_note(self, rate_hz: float) -> str:
        """Why samples go without joint state when the joint states come too seldom: each is
        held at most max_hold_s (a 10 Hz driver leaves half of every 100 ms without)."""
        hold_s = self.denoiser.settings.max_hold_s
        if rate_hz <= 0 or 1.0 / rate_hz <= hold_s:
            return ""
        return (
            f"joint states come every {1000 / rate_hz:.0f} ms, and one is held at most "
            f"{1000 * hold_s:.0f} ms"
        )

    def close(self) -> None:
        stats = self.denoiser.stats
        adapted = getattr(self.denoiser, "adaptation_stats", None)
        if self.adapt is not None and adapted is not None:
            print(
                f"denoiser: adapted, {adapted.blocks_learnt} blocks learnt, "
                f"{adapted.blocks_gated} left out for contacts, cells learnt online "
                f"{adapted.cells_learnt} ({adapted.cells_new} never calibrated), harmonic "
                f"lines found online {adapted.lines_found}",
                flush=True,
            )
        # every sample received is one of these (the core's look-ahead and framing hold the
        # last few at a stop: they are never output, and said so)
        inside = (
            len(self.held.raws)
            + sum(len(raws) for raws, _, _ in self._startup)
            + self.input.sensor_pending
        )
        line = (
            f"denoiser: samples in {self.input.sensor_messages}, "
            f"published {self.samples_published}, withheld {self.samples_withheld}, "
            f"dropped as bad or out of order {stats.samples_bad + stats.dropped_out_of_order}, "
            f"not yet output at the stop {inside}, undecodable "
            f"{self.input.undecodable_sensor + self.input.undecodable_joints}, "
            f"restarts {stats.resets}"
        )
        if stats.blocks is not None:
            line += f", blocks out of grid {stats.blocks_out_of_grid}/{stats.blocks}"
        print(line, flush=True)


def main(args: list[str] | None = None) -> int:
    return run_node(Denoiser, args)


if __name__ == "__main__":
    raise SystemExit(main())
