"""contact_detector: contact events, live, from the denoiser's output or the raw stream
(docs/live_nodes.md).

The detector of `egovib detect` (core.contact), so live and offline events agree, with its
threshold fixed at start by the same rule (evaluation.contacts.detection_threshold) and
raised, as offline, where the joint states (the profile's topic) show motion beyond the
calibration's (a sample waits for them at most JOINT_WAIT_S after its arrival). One
geometry_msgs/Vector3Stamped per event on `contact_events`: stamp = the onset, frame_id =
the sensor's, vector = the band-passed vector at the event's peak. Its latency is counted
from the onset stamp, or from the arrival of the onset's sample when the stamps are not on
this machine's clock (a replay, sim time): `latency_from` says which.
"""

from __future__ import annotations

import struct
import time
from collections import deque

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from rclpy.node import Node

from egovib_ros.core import NoiseModel
from egovib_ros.core.contact import FALSE_ALARMS_PER_MIN, ContactDetector, ContactSettings
from egovib_ros.errors import ConfigError
from egovib_ros.evaluation.contacts import (
    DETECT_METHODS,
    check_detect_method,
    detection_threshold,
)
from egovib_ros.nodes.common import (
    Health,
    Param,
    StreamInput,
    declare_parameters,
    run_node,
)
from egovib_ros.nodes.convert import ns_to_stamp

#: Onset stamps further than this from the wall clock are not on it (a replay, sim time).
REPLAYED_S = 10.0
#: How long a sample waits for the joint states that decide its threshold (as the
#: denoiser's framer waits for them).
JOINT_WAIT_S = 0.02

PARAMETERS = (
    Param("model", "", "noise-model file (.npz): the robot profile (topics, field, band, rate)"),
    Param(
        "source",
        "denoised",
        "denoised: the denoiser's output topic | raw: the sensor topic itself",
        choices=("denoised", "raw"),
    ),
    Param(
        "method",
        "",
        "the denoiser method producing the input (its threshold): empty for the model's "
        "default (hybrid where the model carries it, as the denoiser runs by default) | paper "
        "| cancel | hybrid; raw for source raw",
        choices=("", *DETECT_METHODS),
    ),
    Param("threshold", 0.0, "envelope threshold (0: from no-contact data)", range=(0.0, 1e9)),
    Param(
        "calibration_bag",
        "",
        "no-contact bag to set the threshold from (default: the threshold stored in the model, "
        "else the bag the model was calibrated from)",
    ),
    Param(
        "false_alarms_per_min",
        FALSE_ALARMS_PER_MIN,
        "false-alarm budget on the no-contact data (the model's thresholds: 1 a minute; 0: "
        "1.1 x its largest envelope)",
        range=(0.0, 600.0),
    ),
    Param("stale_after", 1.5, "seconds without input before STALE", range=(0.1, 3600.0)),
)


def frame_of(raw: bytes) -> str:
    """The header frame_id of a serialised Imu (little-endian CDR)."""
    length = struct.unpack_from("<I", raw, 12)[0]
    return raw[16 : 16 + max(0, length - 1)].decode(errors="replace")


class ContactDetectorNode(Node):
    def __init__(self):
        super().__init__("contact_detector")
        params = declare_parameters(self, PARAMETERS)
        if not params["model"]:
            raise ConfigError("contact_detector: parameter 'model' (noise-model path) is required")
        self.model = NoiseModel.load(params["model"])
        self.profile = self.model.robot_profile()
        self.source = params["source"]
        self.method = check_detect_method(
            self.model, "raw" if self.source == "raw" else (params["method"] or None)
        )
        self.budget = params["false_alarms_per_min"]
        try:
            found = detection_threshold(
                self.model,
                self.method,
                threshold=params["threshold"] or None,
                calibration=params["calibration_bag"] or None,
                false_alarms_per_min=self.budget,
            )
        except ConfigError as exc:
            raise ConfigError(
                f"contact_detector: {exc}; set calibration_bag or threshold"
            ) from None
        self.threshold, self.threshold_source, self.calibration_rate, self.motion = found
        self.detector = ContactDetector(
            ContactSettings.for_model(self.model, self.threshold),
            motion=self.motion,
        )
        topic = (
            self.profile.node_denoised_topic
            if self.source == "denoised"
            else self.profile.node_sensor_topic
        )
        # (last stamp, arrival) of the recent batches (a deque: a batch every 2 ms)
        self._arrivals: deque[tuple[int, int]] = deque(maxlen=2000)
        self.latency_from = ""
        # every message waits for the 2 ms timer (batch_samples: never due on its own)
        self.input = StreamInput(
            self,
            self.profile,
            batch_samples=2**62,
            on_batch=lambda: None,
            from_first=False,
            sensor_topic=topic,
        )
        self.pub = self.create_publisher(Vector3Stamped, "contact_events", 100)
        self.health = Health(
            self, hardware_id=self.profile.name, stale_after_s=params["stale_after"]
        )
        self.frame_id: str | None = None
        self.samples = self.events = 0
        self._last_input: float | None = None
        self._started = time.monotonic()
        self._latency_ms: list[float] = []
        self.create_timer(0.002, self._process)  # batches of ~2 ms: latency small, cost low
        self.create_timer(1.0, self._publish_diagnostics)
        raised = (
            f", x{self.motion.factor:.3g} where the joints move beyond the calibration"
            if self.motion is not None
            else ""
        )
        self.get_logger().info(
            f"contact events from {self.input.sensor_topic} ({self.profile.sensor_field}, after "
            f"{self.method}), threshold {self.threshold:.4g} ({self.threshold_source}{raised}) "
            f"-> {self.pub.topic_name}"
        )

    def _process(self) -> None:
        events = []
        joints = self.input.take_joints()
        if joints is not None and len(joints.stamps_ns):
            events += self.detector.push_joints(joints.stamps_ns, joints.velocity)
        batch = self.input.take_sensor()
        if batch is not None:
            self._last_input = time.monotonic()
        if batch is not None and len(batch.stamps_ns):
            if self.frame_id is None:
                self.frame_id = frame_of(batch.raws[0])
            self.samples += len(batch.stamps_ns)
            # on the wall clock: the first message's arrival, as monotonic ns
            arrived = int(batch.arrival_ns[0]) - time.monotonic_ns() + time.time_ns()
            self._arrivals.append((int(batch.stamps_ns.max()), arrived))
            events += self.detector.push(batch.stamps_ns, batch.values)
        if self.motion is not None:  # what waited JOINT_WAIT_S for joint states goes on
            waited = time.time_ns() - int(JOINT_WAIT_S * 1e9)
            arrivals = reversed(self._arrivals)
            ready = next((last for last, arrived in arrivals if arrived <= waited), None)
            if ready is not None:
                events += self.detector.release(ready)
        for event in events:
            msg = Vector3Stamped()
            msg.header.stamp = ns_to_stamp(event.onset_ns)
            msg.header.frame_id = self.frame_id
            msg.vector.x, msg.vector.y, msg.vector.z = event.peak
            self.pub.publish(msg)
            self.events += 1
            self._latency_ms.append(self._latency(event.onset_ns) / 1e6)

    def _latency(self, onset_ns: int) -> int:
        """Now minus the onset stamp if that is on this machine's clock, else minus the
        arrival of the onset's sample (ns)."""
        now = time.time_ns()
        if abs(now - onset_ns) <= REPLAYED_S * 1e9:
            self.latency_from = "onset stamp"
            return now - onset_ns
        self.latency_from = "arrival of the onset's sample (replayed: stamps not on this clock)"
        arrived = next((t for last, t in self._arrivals if last >= onset_ns), None)
        return now - (arrived if arrived is not None else self._arrivals[-1][1])

    def close(self) -> None:
        """What it saw, said at the end (Ctrl-C) as every node says it."""
        minutes = max((time.monotonic() - self._started) / 60.0, 1e-9)
        print(
            f"contact_detector: samples in {self.samples}, events {self.events} "
            f"({self.events / minutes:.1f} a minute, threshold {self.threshold:.4g}, raised on "
            f"{self.detector.samples_motion} samples), undecodable "
            f"{self.input.undecodable_sensor}, bad {self.detector.samples_bad}, out of order "
            f"{self.detector.samples_out_of_order}, restarts {self.detector.restarts}",
            flush=True,
        )

    def _publish_diagnostics(self) -> None:
        minutes = max((time.monotonic() - self._started) / 60.0, 1e-9)
        latency = np.asarray(self._latency_ms[-1000:])
        values = {
            "samples_in": self.samples,
            "undecodable_messages": self.input.undecodable_sensor,
            "samples_beyond_calibration_motion": self.detector.samples_motion,
            "samples_bad": self.detector.samples_bad,
            "samples_out_of_order": self.detector.samples_out_of_order,
            "stream_restarts": self.detector.restarts,
            "events": self.events,
            "events_per_min": round(self.events / minutes, 3),
            "method": self.method,
            "threshold": self.threshold,
            "false_alarm_budget_per_min": self.budget,
            "calibration_false_alarms_per_min": (
                self.calibration_rate if self.calibration_rate is not None else float("nan")
            ),
            "latency_p50_ms": float(np.percentile(latency, 50)) if len(latency) else float("nan"),
            "latency_p99_ms": float(np.percentile(latency, 99)) if len(latency) else float("nan"),
            "latency_from": self.latency_from,
            # DDS matches (0 publishers: nobody publishes the input, e.g. a wrong remapping)
            "input_publishers": self.input.publisher_counts()["sensor_publishers"],
            "event_subscribers": self.pub.get_subscription_count(),
        }
        grown = self.health.changes(
            {
                "undecodable": self.input.undecodable_sensor,
                "bad": self.detector.samples_bad,
                "out_of_order": self.detector.samples_out_of_order,
                "restarts": self.detector.restarts,
            }
        )
        texts = {
            "undecodable": "undecodable messages",
            "out_of_order": "samples out of order (dropped)",
            "restarts": "stream restarts (stamps went back: detection restarted)",
            "bad": "bad samples (non-finite or beyond the sensor's range: held at the last good "
            "value)",
        }
        warnings = [f"{grown[key]:.0f} {text}" for key, text in texts.items() if grown[key]]
        self.health.publish(
            stale=self.health.stale_message(self._last_input, self.input.sensor_topic),
            warnings=warnings,
            ok=f"{self.events} events",
            values=values,
        )


def main(args: list[str] | None = None) -> int:
    return run_node(ContactDetectorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
