"""Flight log (npz) -> rosbag2 bag: the real recording in the form the package consumes.

    egovib real convert ../shared/real/quadcopter_ar8_flight.npz --out bags/quadcopter_ar8

Topics (robot profile ``config/robots/quadcopter.yaml``), one message per log sample,
header stamp = the log's own jittery sample time (ns, bag log time the same):

- ``/imu/data_raw`` (sensor_msgs/Imu): unfiltered gyro in ``angular_velocity``, rad/s.
  REP 145: orientation and linear acceleration unknown (covariance[0] = -1). Axes as
  logged (Betaflight's roll, pitch, yaw rates about the board's x, y, z axes); the
  firmware's sign conventions are kept, nothing is re-oriented.
- ``/imu/data_filtered`` (sensor_msgs/Imu): the gyro after Betaflight's own filters
  (RPM notches keyed on measured motor RPM, dynamic low-pass), same layout.
- ``/joint_states`` (sensor_msgs/JointState): motor1..motor4, velocity = motor command
  as a fraction of full scale (0..1; the idle command 157 is one DShot step below the
  output range and gives -0.0005), position = its time integral (trapezoid; a
  propeller's "angle" in command-seconds), no effort.

MCAP storage with zstd-compressed chunks keeps the 17 s flight at about 2 MB (13 MB of
messages uncompressed).

Data: Betaflight blackbox log LOG00037.BFL from github.com/ilya-epifanov/fc-blackbox
(src/test-data/LOG00037.BFL, licence MIT OR Apache-2.0; first posted in
github.com/gyroflow/gyroflow/issues/72), decoded with orangebox. The converter writes a
README.md with this attribution into the bag directory.
"""

from __future__ import annotations

import argparse
import hashlib
import os
from pathlib import Path

import numpy as np

from egovib_research.experiments.flight import ATTRIBUTION
from egovib_research.experiments.flight.flightlog import MOTOR_NAMES, FlightLog, load_flight_log
from egovib_research.experiments.flight.recording import FILTERED_TOPIC
from egovib_ros.bag import BagWriter
from egovib_ros.bag.codec import (
    IMU_TYPE,
    JOINT_STATE_TYPE,
    encode_imu_batch,
    encode_joint_state_batch,
)
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.outputs import atomic_output, prepare_output
from egovib_ros.robot import RobotProfile, load_profile

FRAME_ID = "imu_link"
PROFILE_NAME = "quadcopter"


def motor_positions(stamps_ns: np.ndarray, motors: np.ndarray) -> np.ndarray:
    """(N, 4) running time integral of the command fractions (trapezoid rule), 0 at the start."""
    dt = np.diff(stamps_ns).astype(np.float64) / NS_PER_S
    steps = 0.5 * (motors[1:] + motors[:-1]) * dt[:, None]
    return np.concatenate([np.zeros((1, motors.shape[1])), np.cumsum(steps, axis=0)])


def bag_readme(log: FlightLog, profile: RobotProfile, sha256: str) -> str:
    return f"""# bags/quadcopter_ar8: a real quadcopter flight as a rosbag2 bag

Real data, not a simulation: 17 s of a 5-inch FPV quadcopter ("AR8", KakuteF7 flight
controller, Betaflight 4.2.0, 6S) idling, taking off, hovering and doing two punch-outs
with flips. Robot profile: `config/robots/{PROFILE_NAME}.yaml`.

## Source and licence

{ATTRIBUTION}

Licence of the data and of this bag: **MIT OR Apache-2.0** (as the source repository).
Keep this attribution wherever the data or anything derived from it is shipped.

Converted from `quadcopter_ar8_flight.npz` (sha256 `{sha256}`) by
`egovib real convert quadcopter_ar8_flight.npz --out bags/quadcopter_ar8`
(`research/egovib_research/experiments/flight/convert.py`, `egovib real convert`).

## Topics ({log.n} messages each, one per log sample, stamps = the log's jittery sample times)

| topic | type | content |
|---|---|---|
| `{profile.sensor_topic}` | Imu | gyro before the firmware's filters, `angular_velocity`, rad/s |
| `{FILTERED_TOPIC}` | Imu | gyro after Betaflight's own filters (RPM notches, dynamic low-pass) |
| `{profile.joints_topic}` | JointState | `{", ".join(MOTOR_NAMES)}`: velocity = command (0..1), \
position = its time integral |

Imu messages follow REP 145 (orientation and linear acceleration unknown: covariance[0] =
-1), frame `{FRAME_ID}`, axes as logged by Betaflight (roll, pitch, yaw rates about the
board's x, y, z). Sample steps jitter between 0.9 and 1.25 ms around 1 ms ({log.n} samples
in {log.duration_s:.2f} s). MCAP storage, zstd-compressed chunks.
"""


def convert(
    npz: str | os.PathLike, out: str | os.PathLike, *, profile: RobotProfile | None = None
) -> dict:
    """Write the bag (atomically: nothing at `out` unless complete). Returns a summary."""

    profile = profile or load_profile(PROFILE_NAME)
    log = load_flight_log(npz)
    sha256 = hashlib.sha256(Path(npz).read_bytes()).hexdigest()
    stamps = log.stamps_ns
    field = profile.sensor_field
    raw = encode_imu_batch(stamps, log.gyro, FRAME_ID, field=field)
    filtered = encode_imu_batch(stamps, log.gyro_filtered, FRAME_ID, field=field)
    joints = encode_joint_state_batch(
        stamps, motor_positions(stamps, log.motors), log.motors, MOTOR_NAMES
    )
    with atomic_output(out, directory=True, kind="bag") as tmp:
        with BagWriter(tmp, compress=True) as bag:
            bag.add_topic(profile.joints_topic, JOINT_STATE_TYPE)
            bag.add_topic(profile.sensor_topic, IMU_TYPE)
            bag.add_topic(FILTERED_TOPIC, IMU_TYPE)
            # Joint state first at each stamp: a live denoiser has the speed before the sample.
            for i, stamp in enumerate(stamps.tolist()):
                bag.write(profile.joints_topic, stamp, joints[i])
                bag.write(profile.sensor_topic, stamp, raw[i])
                bag.write(FILTERED_TOPIC, stamp, filtered[i])
        (tmp / "README.md").write_text(bag_readme(log, profile, sha256))
    size = sum(f.stat().st_size for f in Path(out).iterdir())
    return {
        "bag": str(out),
        "samples": log.n,
        "duration_s": log.duration_s,
        "bytes": size,
        "topics": [profile.sensor_topic, FILTERED_TOPIC, profile.joints_topic],
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "npz", help="decoded flight log (e.g. ../shared/real/quadcopter_ar8_flight.npz)"
    )
    parser.add_argument(
        "--out", required=True, help="output bag directory (e.g. bags/quadcopter_ar8)"
    )
    parser.add_argument(
        "--robot",
        default=PROFILE_NAME,
        help="robot profile naming the topics and Imu field (default: quadcopter)",
    )
    parser.add_argument(
        "--force", action="store_true", help="replace a bag written by an earlier run"
    )


def run(args: argparse.Namespace) -> int:
    # before any work: never replace what egovib did not write, nor the input
    prepare_output(args.out, force=args.force, inputs=[args.npz], kind="bag")
    summary = convert(args.npz, args.out, profile=load_profile(args.robot))
    print(
        f"wrote {summary['bag']}: {summary['samples']} samples ({summary['duration_s']:.2f} s) on "
        f"{', '.join(summary['topics'])}; {summary['bytes'] / 1e6:.2f} MB"
    )
    return 0
