"""denoiser: streaming spectral subtraction (egovib_ros.core.StreamingDenoiser) as a ROS 2 node.

Subscribes `joint_states` and `accelerometer/raw` as raw CDR bytes (decoded in batches
of `batch_samples`), publishes `accelerometer/denoised` with the stamps of the input
samples, and node health on /diagnostics (~1 Hz). A bad message is counted and dropped,
never fatal. With no joint state yet the band-passed signal is passed through (logged
and reported as a warning). After `flush_after_idle` seconds without input the samples
still held for overlap-add are emitted, so that a replayed bag comes out whole.
"""
from __future__ import annotations

import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState

from egovib_ros.constants import (ACCEL_FRAME, JOINT_NAMES, TOPIC_DENOISED, TOPIC_DIAGNOSTICS,
                                  TOPIC_JOINT_STATES, TOPIC_RAW)
from egovib_ros.core import NoiseModel, StreamingDenoiser
from egovib_ros.errors import ConfigError, EgovibError
from egovib_ros.nodes.common import declare, run_node, sensor_subscription, stream_publisher_qos
from egovib_ros.ros_convert import (decode_imu_messages, decode_joint_state_messages,
                                    diagnostic_array, encode_imu_batch)

_NS = 1_000_000_000


class StreamGaps:
    """Counts samples missing from a stream whose stamps should be evenly spaced."""

    def __init__(self, rate_hz: float):
        self.period_ns = _NS / rate_hz
        self.last_ns: int | None = None
        self.missing = 0

    def update(self, stamps_ns: np.ndarray) -> None:
        if not len(stamps_ns):
            return
        previous = stamps_ns[:1] if self.last_ns is None else np.array([self.last_ns])
        steps = np.round(np.diff(np.concatenate([previous, stamps_ns])) / self.period_ns)
        self.missing += int(np.sum(np.clip(steps - 1, 0, None)))
        self.last_ns = int(stamps_ns[-1])


class Denoiser(Node):
    def __init__(self):
        super().__init__("denoiser")
        model_path = declare(self, "model", "", "noise-model file (.npz) from egovib calibrate or the calibrator")
        channels = declare(self, "channels", "per_axis",
                           "per_axis: clean each axis | combined: the paper's 1-D signal in x, y = z = 0")
        oversubtraction = float(declare(self, "oversubtraction", 1.0, "alpha in max(|Y| - alpha N, beta N)"))
        floor = float(declare(self, "floor", 0.0, "beta in max(|Y| - alpha N, beta N)"))
        self.batch_samples = int(declare(self, "batch_samples", 32,
                                         "process every this many accelerometer samples (32 = one hop: as soon as a block completes)"))
        self.flush_after_idle_s = float(declare(self, "flush_after_idle", 0.5,
                                                "seconds without input after which held samples are emitted"))
        self.frame_id = declare(self, "frame_id", ACCEL_FRAME, "frame_id of the published Imu messages")
        if not model_path:
            raise ConfigError("denoiser: parameter 'model' (noise-model path) is required")
        if channels not in ("per_axis", "combined"):
            raise ConfigError(f"denoiser: channels must be per_axis or combined, not {channels!r}")
        self.model = NoiseModel.load(model_path)
        self.denoiser = StreamingDenoiser(self.model, channels=channels,
                                          oversubtraction=oversubtraction, floor=floor)
        self.channels = channels

        self.pub = self.create_publisher(Imu, TOPIC_DENOISED, stream_publisher_qos())
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        sensor_subscription(self, Imu, TOPIC_RAW, self._on_accel)
        sensor_subscription(self, JointState, TOPIC_JOINT_STATES, self._on_joint_state)
        self._accel_raw: list[bytes] = []
        self._joint_raw: list[bytes] = []
        self._accel_count = 0
        self._held = False
        self._last_input = time.monotonic()
        self._flushed = True
        self.bad_accel = 0
        self.bad_joint = 0
        self.joint_states_in = 0
        self.samples_published = 0
        self.gaps = StreamGaps(self.model.sample_rate_hz)
        self._latency_ms: list[np.ndarray] = []
        self._passthrough_reported = False
        self._last_diag = (time.monotonic(), 0)
        self.create_timer(0.05, self._on_idle_check)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"denoising {self.resolve_topic_name(TOPIC_RAW)} -> "
                               f"{self.resolve_topic_name(TOPIC_DENOISED)} ({channels}) with {model_path}")

    # --- input ----------------------------------------------------------------------
    def _on_joint_state(self, data: bytes) -> None:
        self._joint_raw.append(data)
        if self._held:
            # A completed block waits for the joint state covering its end: release it now
            # rather than at the next batch of samples (that would add up to a hop of delay).
            self._process_joints()
            self._update_held()

    def _on_accel(self, data: bytes) -> None:
        self._accel_raw.append(data)
        self._accel_count += 1
        # Counted from the first sample, like the blocks: with batch_samples = hop a batch
        # ends exactly when a block completes, so no sample waits for the next batch.
        if self._accel_count % self.batch_samples == 0:
            self._process()

    def _process(self) -> None:
        """Decode what arrived, push joint states first (they cover the new blocks), publish."""
        self._last_input = time.monotonic()
        self._flushed = False
        self._process_joints()
        if self._accel_raw:
            raws, self._accel_raw = self._accel_raw, []
            stamps, accel, n_bad = decode_imu_messages(raws, TOPIC_RAW)
            self.bad_accel += n_bad
            self.gaps.update(stamps)
            self._publish(self._push(self.denoiser.push_accel, stamps, accel, "accel"))
        self._update_held()

    def _process_joints(self) -> None:
        if self._joint_raw:
            raws, self._joint_raw = self._joint_raw, []
            stamps, _, velocity, n_bad = decode_joint_state_messages(raws, JOINT_NAMES)
            self.bad_joint += n_bad
            self.joint_states_in += len(stamps)
            self._publish(self._push(self.denoiser.push_joint_states, stamps, velocity, "joint"))

    def _update_held(self) -> None:
        """Is a completed block held back (more than a block of input not yet output)?"""
        stats = self.denoiser.stats
        self._held = stats["samples_in"] - stats["samples_out"] >= self.model.block_length

    def _push(self, push, stamps: np.ndarray, values: np.ndarray, kind: str):
        """Push into the core; a batch it rejects is counted and dropped, not fatal."""
        if not len(stamps):
            return None
        try:
            return push(stamps, values)
        except EgovibError as exc:
            if kind == "accel":
                self.bad_accel += len(stamps)
            else:
                self.bad_joint += len(stamps)
            self.get_logger().warning(f"dropped {len(stamps)} samples: {exc}", throttle_duration_sec=5.0)
            return None

    def _publish(self, chunk) -> None:
        if chunk is None or not len(chunk):
            return
        values = chunk.values
        if values.shape[1] == 1:           # CONTRACT: combined signal in x, y = z = 0
            values = np.concatenate([values, np.zeros((len(values), 2))], axis=1)
        for data in encode_imu_batch(chunk.stamps_ns, values, self.frame_id):
            self.pub.publish(data)
        self.samples_published += len(chunk)
        # Latency: node clock at publish minus the stamp of each sample published.
        self._latency_ms.append((self.get_clock().now().nanoseconds - chunk.stamps_ns) / 1e6)

    def _on_idle_check(self) -> None:
        idle = time.monotonic() - self._last_input
        if self._accel_raw and idle > 0.02:
            self._process()
        elif not self._flushed and self.flush_after_idle_s > 0 and idle > self.flush_after_idle_s:
            self._flushed = True
            self._publish(self.denoiser.flush())

    # --- health ---------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        stats = self.denoiser.stats
        now = time.monotonic()
        last_t, last_in = self._last_diag
        rate = (stats["samples_in"] - last_in) / (now - last_t) if now > last_t else 0.0
        self._last_diag = (now, stats["samples_in"])
        latency = np.concatenate(self._latency_ms) if self._latency_ms else np.zeros(0)
        self._latency_ms = []
        blocks = max(stats["blocks"], 1)
        passthrough = self.joint_states_in == 0 and stats["samples_in"] > 0
        if passthrough and not self._passthrough_reported:
            self.get_logger().warning("no joint state yet: passing the band-passed signal through")
            self._passthrough_reported = True
        drops = self.bad_accel + self.bad_joint + stats["dropped_out_of_order"] + self.gaps.missing
        values = {
            "input_rate_hz": rate, "samples_in": stats["samples_in"],
            "samples_published": self.samples_published, "missing_samples": self.gaps.missing,
            "bad_messages": self.bad_accel + self.bad_joint,
            "dropped_out_of_order": stats["dropped_out_of_order"],
            "joint_states_in": self.joint_states_in,
            "latency_p50_ms": float(np.percentile(latency, 50)) if len(latency) else float("nan"),
            "latency_p99_ms": float(np.percentile(latency, 99)) if len(latency) else float("nan"),
            "out_of_grid_fraction": stats["blocks_out_of_grid"] / blocks,
            "no_joint_state_fraction": stats["blocks_no_joint_state"] / blocks,
            "channels": self.channels,
        }
        if passthrough:
            level, message = "warn", "no joint state: passing the band-passed signal through"
        elif drops:
            level, message = "warn", f"{drops} samples dropped or missing so far"
        else:
            level, message = "ok", "denoising"
        self.pub_diag.publish(diagnostic_array(self.get_clock().now().nanoseconds,
                                               [("denoiser", level, message, values)]))

    def close(self) -> None:
        stats = self.denoiser.stats
        print(f"denoiser: samples in {stats['samples_in']}, published {self.samples_published}, "
              f"missing {self.gaps.missing}, bad messages {self.bad_accel + self.bad_joint}, "
              f"out of grid blocks {stats['blocks_out_of_grid']}/{stats['blocks']}", flush=True)


def main(args: list[str] | None = None) -> int:
    return run_node(Denoiser, args)


if __name__ == "__main__":
    raise SystemExit(main())
