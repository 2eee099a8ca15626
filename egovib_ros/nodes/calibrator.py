"""calibrator: live calibration of the noise model (core.CalibrationAccumulator;
docs/live_nodes.md).

Blocks go to the velocity cells of the robot profile's grid by the *measured* joint
velocities, so nothing is needed from a driver (`grid`: a sweep, free motion or auto). A
checkpoint is written atomically at each new sweep cell or every `checkpoint_period` s of
free motion, and resumed from; one that cannot be written is an ERROR, retried. At
shutdown the model is written to `output` (else beside the temporary files, named).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
from rclpy.node import Node

from egovib_ros.bag.recording import Recording
from egovib_ros.core import CalibrationAccumulator, NoiseModel
from egovib_ros.core.stream import RateWatch
from egovib_ros.errors import ConfigError, EgovibError, RateError
from egovib_ros.nodes.common import (
    ROBOT_PARAM,
    Health,
    Param,
    StreamInput,
    declare_parameters,
    run_node,
    stream_counters,
)
from egovib_ros.outputs import atomic_output
from egovib_ros.robot import load_profile

# The two topics come on separate DDS readers: on a busy machine (e.g. while another
# process starts) joint states can fall well behind the samples. Calibration has no latency
# to keep, so blocks wait up to this long (stream time) for the joint states covering them.
JOINT_WAIT_S = 2.0
SWEEPS = ("full", "superposition")
PARAMETERS = (
    ROBOT_PARAM,
    Param("output", "noise_model.npz", "noise-model file written at shutdown"),
    Param(
        "grid",
        "full",
        "full | superposition: a sweep over grid velocities; free: any no-contact motion "
        "(each steady block to its nearest cell); auto: decide from the data",
        choices=("full", "superposition", "free", "auto"),
    ),
    Param(
        "joint_lag",
        0.0,
        "seconds the vibration trails the joint states (`egovib gap` timing advice, as "
        "`egovib calibrate --joint-lag`); negative: it leads them",
        range=(-1.0, 1.0),
    ),
    Param(
        "methods",
        "all",
        "all: at shutdown also fit what methods cancel and hybrid need and the contact "
        "detector's thresholds, on the samples kept (as `egovib calibrate`); paper: the "
        "paper's table and the detector's thresholds only",
        choices=("all", "paper"),
    ),
    Param(
        "keep_seconds",
        600.0,
        "seconds of the stream kept for that fit at shutdown (the first ones)",
        range=(1.0, 7200.0),
    ),
    Param("checkpoint", "", "checkpoint model path; empty = <output stem>.checkpoint.npz"),
    Param("resume", True, "resume from the checkpoint if it exists"),
    Param("batch_samples", 96, "sensor samples collected before processing", range=(1, 100_000)),
    Param(
        "checkpoint_period", 10.0, "free motion: seconds between checkpoints", range=(0.1, 3600.0)
    ),
    Param(
        "retry_period",
        5.0,
        "seconds between attempts to write a checkpoint that failed",
        range=(0.1, 3600.0),
    ),
    Param(
        "stale_after",
        1.5,
        "seconds without input before /diagnostics reports STALE",
        range=(0.1, 3600.0),
    ),
)


def coverage_text(cov: dict) -> str:
    """How much of the grid the model measured, for the summary line: a sweep names the
    cells it missed; free motion only counts the cells measured (never "missing: none" for
    a grid mostly unmeasured)."""
    measured = f"{cov['cells_measured']} of {cov['cells_total']} grid cells measured"
    if "cells_expected" not in cov:
        return f"{measured} (free motion: the rest are unmeasured)"
    missing = cov["missing_cells"]
    shown = ", ".join(f"[{m}]" for m in missing[:20]) or "none"
    if len(missing) > 20:
        shown += f" and {len(missing) - 20} more"
    return (
        f"{cov['cells_covered']}/{cov['cells_expected']} cells of the {cov['mode']} sweep "
        f"covered ({measured}); sweep cells missing: {shown}"
    )


class Calibrator(Node):
    def __init__(self):
        super().__init__("calibrator")
        params = declare_parameters(self, PARAMETERS)
        self.profile = load_profile(params["robot"] or None)
        self.output = params["output"]
        self.grid = params["grid"]
        out = Path(self.output)  # default checkpoint: beside it, OUTPUT.checkpoint.npz
        self.checkpoint = params["checkpoint"] or str(out.with_name(out.stem + ".checkpoint.npz"))
        self.checkpoint_period_s = params["checkpoint_period"]
        self.methods = params["methods"]
        self.joint_lag_s = params["joint_lag"]
        # the stream itself, for what is fitted at shutdown on whole arrays (the methods'
        # line map and gains, the detector's thresholds): at most keep_seconds of it
        self._keep = int(params["keep_seconds"] * self.profile.rate_hz)
        self._kept_sensor: list[tuple[np.ndarray, np.ndarray]] = []
        self._kept_joints: list[tuple[np.ndarray, np.ndarray]] = []
        self._kept = 0
        self.retry_period_s = params["retry_period"]
        self.input = StreamInput(
            self, self.profile, batch_samples=params["batch_samples"], on_batch=self._process
        )
        # the same framing as `egovib calibrate` (a positive lag also waits that much longer)
        framing = dict(
            joint_wait_s=JOINT_WAIT_S,
            joint_lag_s=params["joint_lag"],
            source=self.input.sensor_topic,
        )
        if params["resume"] and os.path.exists(self.checkpoint):
            self.acc = self._resume(NoiseModel.load(self.checkpoint), framing)
        else:
            self.acc = CalibrationAccumulator(profile=self.profile, sweep=self.grid, **framing)
        self.health = Health(
            self, hardware_id=self.profile.name, stale_after_s=params["stale_after"]
        )
        self._counts = self._cell_count_map()
        self._blocks_used = self.acc.stats.blocks_used
        self._current_cell: tuple[int, ...] | None = None
        self._checkpoint_due = False
        self._last_checkpoint = time.monotonic()
        self._retry_at = 0.0
        self.checkpoint_error: str | None = None
        self.checkpoints_written = 0
        self.checkpoint_failures = 0
        self.stream_error: str | None = None
        self._rate_watch: RateWatch | None = None  # after a rate refusal: is it back?
        self.samples_withheld = 0
        self.rate_recoveries = 0
        self._last_input = time.monotonic()
        self._last_report = (time.monotonic(), 0)
        self._blocks_reported = (0, 0)  # blocks without joint state, all blocks: last report
        self.create_timer(0.25, self._on_timer)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f"calibrating {self.profile.name} ({self.grid} grid, joints "
            f"{list(self.profile.joint_names)}) from {self.input.sensor_topic} "
            f"({self.profile.sensor_field}) and {self.input.joints_topic} into "
            f"{self.output} (checkpoint {self.checkpoint})"
        )

    def _resume(self, model: NoiseModel, framing: dict) -> CalibrationAccumulator:
        where = self.checkpoint
        if (
            model.joint_names != self.profile.joint_names
            or model.grid_shape != self.profile.grid_shape
        ):
            raise ConfigError(
                f"{where}: checkpoint of joints {list(model.joint_names)} on a {model.grid_shape} "
                f"grid, but robot {self.profile.name!r} has {list(self.profile.joint_names)} on "
                f"{self.profile.grid_shape}"
            )
        if self.grid != "auto" and model.measured != self.grid:
            raise ConfigError(
                f"{where}: checkpoint of a {model.measured} calibration, but grid is {self.grid}"
            )
        acc = CalibrationAccumulator.from_model(model, **framing)
        coverage = model.coverage()
        self.get_logger().info(
            f"resumed from {where}: {coverage['cells_measured']} cells, {coverage['blocks']} blocks"
        )
        return acc

    # --- input ------------------------------------------------------------------------
    def _process(self, *, final: bool = False) -> None:
        """Push what arrived, joint states first; the core holds each block until the
        joint states covering it are in (at most JOINT_WAIT_S). `final`: at the end, the
        last stamp's held joint states too."""
        self._last_input = time.monotonic()
        joints = self.input.take_joints(final=final)
        # while refused for its rate, joint states wait for nothing (a new framer follows)
        if joints is not None and len(joints.stamps_ns) and self._rate_watch is None:
            self.acc.push_joint_states(joints.stamps_ns, joints.velocity)
            if self._kept < self._keep:
                self._kept_joints.append((joints.stamps_ns.copy(), joints.velocity.copy()))
        batch = self.input.take_sensor()
        if batch is not None and len(batch.stamps_ns) and self._rate_watch is not None:
            # refused for its rate: nothing is gathered until two windows fit again
            self.samples_withheld += len(batch.stamps_ns)
            if self._rate_watch.push(batch.stamps_ns) is None:
                return
            self.acc.restart_stream()
            self.stream_error, self._rate_watch = None, None
            self.rate_recoveries += 1
            self.get_logger().warning(
                f"{self.input.sensor_topic}: the sensor rate fits the model again: calibration "
                f"goes on ({self.samples_withheld} samples withheld so far)"
            )
        elif batch is not None and len(batch.stamps_ns):
            try:
                self.acc.push_sensor(batch.stamps_ns, batch.values)
            except EgovibError as exc:  # e.g. a stream at another rate than the profile's
                self.get_logger().error(
                    f"dropped {len(batch.stamps_ns)} samples: {exc}", throttle_duration_sec=5.0
                )
                self.stream_error = str(exc) + self.input.publishers_note()
                if isinstance(exc, RateError):  # until the rate is back (a burst passes)
                    self.samples_withheld += len(batch.stamps_ns)
                    self._rate_watch = RateWatch(
                        self.acc.settings, receipt=self.acc.sensor_stamps == "receipt"
                    )
            else:  # what the methods are fitted on at shutdown: the stream as gathered
                if self._kept < self._keep:
                    self._kept_sensor.append((batch.stamps_ns.copy(), batch.values.copy()))
                    self._kept += len(batch.stamps_ns)
        self._track_cells()

    def _cell_count_map(self) -> dict[tuple[int, ...], int]:
        cells, counts = self.acc.cell_counts()
        return {tuple(int(i) for i in cell): int(n) for cell, n in zip(cells, counts)}

    def _track_cells(self) -> None:
        """A sweep's cell is complete when blocks start landing in another one: checkpoint
        then (free motion visits cells in any order: every checkpoint_period)."""
        used = self.acc.stats.blocks_used
        if used == self._blocks_used:
            return
        self._blocks_used = used
        if self.acc.mode not in SWEEPS:  # free motion: _on_timer checkpoints
            return
        counts = self._cell_count_map()
        grown = {cell: n - self._counts.get(cell, 0) for cell, n in counts.items()}
        if grown and max(grown.values()) > 0:
            newest = max(grown, key=grown.get)
            if self._current_cell is not None and newest != self._current_cell:
                expected = self._expected_cells()
                covered = sum(1 for cell in expected if counts.get(cell, 0) > 0)
                self.get_logger().info(
                    f"cell [{self._velocity_text(self._current_cell)}] done: "
                    f"{counts.get(self._current_cell, 0)} blocks; coverage {covered}/"
                    f"{len(expected)} cells"
                )
                self._checkpoint_due = True
            self._current_cell = newest
        self._counts = counts

    def _velocity_text(self, cell: tuple[int, ...]) -> str:
        return ", ".join(f"{self.acc.grid[j][i]:+.3g}" for j, i in enumerate(cell))

    def _expected_cells(self) -> list[tuple[int, ...]]:
        return [tuple(int(i) for i in cell) for cell in self.acc.expected_cell_list()]

    def _on_timer(self) -> None:
        if self.input.sensor_pending and time.monotonic() - self._last_input > 0.05:
            self._process()
        if (
            self.acc.mode not in SWEEPS
            and self.acc.stats.blocks_used
            and time.monotonic() - self._last_checkpoint >= self.checkpoint_period_s
        ):
            self._checkpoint_due = True
        if self._checkpoint_due and time.monotonic() >= self._retry_at:
            self._write_checkpoint()

    # --- output -----------------------------------------------------------------------
    def _write_checkpoint(self) -> None:
        try:
            self.write_model(self.checkpoint)
        except (OSError, EgovibError) as exc:
            self.checkpoint_failures += 1
            self._retry_at = time.monotonic() + self.retry_period_s
            reason = getattr(exc, "strerror", None) or str(exc)
            message = (
                f"cannot write checkpoint {self.checkpoint} ({reason}); statistics kept in memory, "
                f"retrying every {self.retry_period_s:g} s"
            )
            if message != self.checkpoint_error:
                self.get_logger().error(message)
            self.checkpoint_error = message
            return
        if self.checkpoint_error:
            self.get_logger().info(f"checkpoint {self.checkpoint} written again")
        self.checkpoint_error = None
        self._checkpoint_due = False
        self._last_checkpoint = time.monotonic()
        self.checkpoints_written += 1

    def write_model(self, path: str, model: NoiseModel | None = None) -> None:
        """Write `model` (default: the one accumulated so far) to `path`, atomically."""
        model = model or self.acc.to_model(source=f"live:{self.input.sensor_topic}")
        with atomic_output(path) as tmp:
            model.save(tmp)

    def fitted_model(self) -> tuple[NoiseModel, str]:
        """The final model: the table, and on the samples kept what `egovib calibrate` fits
        beside it (methods cancel and hybrid with `methods: all`, the contact detector's
        thresholds), so the model feeds the denoiser's default method and the
        contact_detector alone. What was fitted, in words (or why not)."""
        from egovib_ros.core.methods import (  # deferred: numba compiles at shutdown, not at start
            calibrate_detection,
            calibrate_methods,
            rest_detection_warning,
            short_detection_warning,
        )
        from egovib_ros.gap.advice import joint_lag_of  # deferred: the gap's imports
        from egovib_ros.gap.simref import own_lag, with_own_lag

        model = self.acc.to_model(source=f"live:{self.input.sensor_topic}")
        if not self._kept_sensor or not self._kept_joints:
            return model, "no samples kept"
        stamps, values = (np.concatenate(p) for p in zip(*self._kept_sensor))
        joint_stamps, velocity = (np.concatenate(p) for p in zip(*self._kept_joints))
        joint_stamps = joint_stamps + int(round(self.joint_lag_s * 1e9))
        arrays = (stamps, values, joint_stamps, velocity)
        source = self.input.sensor_topic
        try:
            fitted = []
            if self.methods == "all":
                model, _ = calibrate_methods(model, *arrays, source=source)
                fitted.append("methods cancel and hybrid")
            model, thresholds = calibrate_detection(model, *arrays, source=source)
            fitted.append(
                "detector thresholds " + ", ".join(f"{m} {t:.3g}" for m, t in thresholds.items())
            )
            model = with_own_lag(model, _recording(model, arrays))
            lag = own_lag(model)
            if lag is not None:
                fitted.append(f"its joint lag {round(1000 * joint_lag_of(lag)):+d} ms")
            short = short_detection_warning(len(stamps) / self.profile.rate_hz)
            rest = rest_detection_warning(stamps, joint_stamps, velocity, self.profile.max_speed)
            fitted += [warning for warning in (short, rest) if warning]
        except EgovibError as exc:
            return model, f"the paper's table only ({exc})"
        return model, f"on {len(stamps) / self.profile.rate_hz:.0f} s kept: " + "; ".join(fitted)

    def coverage(self) -> dict:
        counts = self._cell_count_map()
        values = list(counts.values())
        result = {
            "mode": self.acc.mode,
            "cells_measured": len(counts),
            "cells_total": int(np.prod(self.profile.grid_shape, dtype=np.float64)),
            "blocks": int(sum(values)),
            "min_blocks": min(values) if values else 0,
        }
        if self.acc.mode in SWEEPS:
            expected = self._expected_cells()
            missing = [cell for cell in expected if counts.get(cell, 0) == 0]
            result.update(
                cells_expected=len(expected),
                cells_covered=len(expected) - len(missing),
                min_blocks=min((counts.get(c, 0) for c in expected), default=0),
                missing_cells=[self._velocity_text(c) for c in missing],
            )
        return result

    def _publish_diagnostics(self) -> None:
        cov = self.coverage()
        stats = self.acc.stats
        inp = self.input
        now = time.monotonic()
        last_t, last_in = self._last_report
        self._last_report = (now, inp.sensor_messages)
        counters = stream_counters(inp, stats)
        grown = self.health.changes(counters)
        values = {
            "input_rate_hz": (inp.sensor_messages - last_in) / max(now - last_t, 1e-3),
            "samples_in": inp.sensor_messages,
            "joint_states_in": inp.joint_messages,
            **inp.velocity_values(),
            **inp.publisher_counts(),
            "mode": cov["mode"],
            "cells_measured": cov["cells_measured"],
            "cells_total": cov["cells_total"],
            "cells_expected": cov.get("cells_expected", cov["cells_total"]),
            "cells_covered": cov.get("cells_covered", cov["cells_measured"]),
            "missing_cells": len(cov.get("missing_cells", [])),
            "blocks": cov["blocks"],
            "min_blocks": cov["min_blocks"],
            "blocks_rejected": sum(stats.rejected.values()),
            **{f"rejected_{k}": v for k, v in stats.rejected.items()},
            **counters,
            "sensor_stamps": self.acc.sensor_stamps,
            "checkpoints_written": self.checkpoints_written,
            "checkpoint_failures": self.checkpoint_failures,
            "samples_withheld": self.samples_withheld,  # while refused for its rate
            "rate_recoveries": self.rate_recoveries,
        }
        missing = inp.missing_joints_error("no block can be used")
        errors = [e for e in (self.stream_error, self.checkpoint_error, missing) if e]
        warnings = [f"{grown[key]} {key.replace('_', ' ')}" for key in counters if grown[key]]
        warnings += inp.stamp_notes(grown)
        # Most blocks since the last report set aside for want of a joint state: no cell
        # learns from them (a few at the start, before the first joint state, are normal).
        seen = (stats.rejected.get("no_joint_state", 0), cov["blocks"] + values["blocks_rejected"])
        no_joint, total = (now_ - before for now_, before in zip(seen, self._blocks_reported))
        if no_joint > 0.5 * total:
            warnings.append(
                f"{no_joint} of {total} blocks without joint state, not used"
                + (f" ({note})" if (note := inp.clock_note()) else "")
            )
        self._blocks_reported = seen
        if cov["mode"] in SWEEPS:
            ok = f"{cov['cells_covered']}/{cov['cells_expected']} cells covered"
        else:
            ok = f"{cov['cells_measured']} cells measured ({cov['mode']})"
        self.health.publish(
            errors=errors,
            stale=self.health.stale_message(inp.last_sensor_s, inp.sensor_topic),
            warnings=warnings,
            ok=ok,
            values=values,
        )

    def close(self) -> int:
        """Write the final model and report coverage; 1 if no block was collected, 2 if the
        model could not be written where asked (it is then saved elsewhere, named)."""
        self._process(final=True)
        self.acc.flush()
        cov = self.coverage()
        rejected = {k: v for k, v in self.acc.stats.rejected.items() if v}
        if cov["blocks"] == 0:
            aside = ", ".join(f"{k} {v}" for k, v in rejected.items())
            print(
                "calibrator: no usable block (steady, with joint states): no model written"
                + (f"; blocks set aside: {aside}" if aside else ""),
                flush=True,
            )
            return 1
        # the fit takes seconds to minutes (every method, on all the node kept): say so first
        print(f"calibrator: fitting on {cov['blocks']} blocks ...", flush=True)
        model, fitted = self.fitted_model()
        try:
            self.write_model(self.output, model)
        except (OSError, EgovibError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc)
            fallback = Path(tempfile.gettempdir()) / f"{Path(self.output).stem}.{os.getpid()}.npz"
            try:
                self.write_model(str(fallback), model)
            except (OSError, EgovibError):
                lost = f"cannot write {self.output} ({reason}) nor {fallback}: the model is lost"
                if os.path.exists(self.checkpoint):
                    lost += f"; the last checkpoint is {self.checkpoint}"
                raise ConfigError(lost) from None
            raise ConfigError(
                f"cannot write {self.output} ({reason}); the model was saved to {fallback}"
            ) from None
        if os.path.exists(self.checkpoint):
            os.remove(self.checkpoint)
        # one line that ends whole: the blocks set aside by reason, not a dict's repr
        aside = ", ".join(f"{reason.replace('_', ' ')} {n}" for reason, n in rejected.items())
        print(
            f"calibrator: wrote {self.output} ({cov['mode']}): {coverage_text(cov)}, "
            f"{cov['blocks']} blocks (min {cov['min_blocks']} per "
            f"{'sweep' if 'cells_expected' in cov else 'measured'} cell)"
            + (f"; blocks set aside: {aside}" if aside else "")
            + f"; bad samples: {self.acc.stats.samples_bad}",
            flush=True,
        )
        print(f"calibrator: fitted {fitted}", flush=True)
        return 0


def _recording(model: NoiseModel, arrays: tuple) -> Recording:
    """The kept samples as the Recording `egovib calibrate` reads (no positions: the lag
    scan needs velocities only)."""
    stamps, values, joint_stamps, velocity = arrays
    return Recording(
        stamps, values, joint_stamps, np.zeros_like(velocity), velocity, tuple(model.joint_names)
    )


def main(args: list[str] | None = None) -> int:
    return run_node(Calibrator, args)


if __name__ == "__main__":
    raise SystemExit(main())
