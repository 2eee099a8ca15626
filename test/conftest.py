"""Shared fixtures for the tests that run real ROS 2 nodes over real DDS.

Every such test gets a private random ROS_DOMAIN_ID with localhost-only discovery,
starts the nodes as separate processes (the venv's console scripts) and stops them
all at the end, also when the test fails.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
import random
import re
import signal
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

from egovib_research.tools.orchestration import RELIABLE_INPUT_DEPTH, NodeGroup
from egovib_research.tools.watcher import Watcher
from egovib_ros.core import methods

#: History of this process's stream writers and queue of its readers (10 s at 3 kHz):
#: reliable links that lose nothing on a loaded machine (nodes.common.stream_publisher).
LOSSLESS_DEPTH = RELIABLE_INPUT_DEPTH

# Property-based tests: "ci" (default) is deterministic and short enough for `make test`;
# HYPOTHESIS_PROFILE=long draws many more examples for a local run.
settings.register_profile("ci", max_examples=20, derandomize=True, deadline=None, database=None)
settings.register_profile("long", max_examples=300, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# A shell that starts a job in the background (`make test &`, a CI runner's script) starts it
# with SIGINT ignored, and every process it starts inherits that: the nodes would then ignore
# the Ctrl-C the tests send them (and a node test would wait for an exit that never comes).
# Python installs its own handler only where SIGINT was not ignored: here it is, explicitly.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


#: Fixtures that start ROS 2 processes or a DDS participant: a test using one is a node test.
NODE_FIXTURES = {"nodes", "ros_client", "ros_domain", "feeder"}


#: Test files outside `make check`'s fast lane: they run whole commands as processes, the
#: experiments or the simulators for tens of seconds (measured with `pytest --durations`).
SLOW_FILES = re.compile(
    r"test_(cli|commands|experiments|tools)_.*|test_(faults|walkthrough|bag_conformance|"
    r"bag_properties|bag_denoise|sim_robot|gap_advice|gap_change|gap_writeback|gap_diagnose|"
    r"gap_effects|gap_pipeline|gap_report|evaluation_stream|evaluation_contacts|core_receipt|"
    r"viz_model_show|outputs)\.py"
)


def pytest_collection_modifyitems(items):
    """Mark every test that runs ROS 2 over DDS `nodes`, whatever its file: `make test` runs
    them after the others. Mark the tests of SLOW_FILES `slow`: `make check` leaves them
    (and the node tests) out."""
    for item in items:
        if NODE_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.nodes)
        if SLOW_FILES.fullmatch(item.path.name):
            item.add_marker(pytest.mark.slow)


class NodeProcesses(NodeGroup):
    """orchestration.NodeGroup, addressed by process handle as the tests like it."""

    def __init__(self, domain_id: int, log_dir: Path):
        super().__init__(log_dir, domain_id)

    def start(
        self, executable: str, params: dict | None = None, *, log_name: str | None = None, **options
    ):
        """Run `executable --ros-args -p name:=value ...`; output goes to a log file.
        `options`: remap, namespace, env (see NodeGroup.start)."""
        return super().start(
            f"{log_name or executable}.{len(self.procs)}", executable, params, **options
        )

    def _name(self, proc: subprocess.Popen) -> str:
        return next(name for name, p in self.procs.items() if p is proc)

    def log(self, proc: subprocess.Popen) -> str:
        return super().log(self._name(proc))

    def stop(self, proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 60.0) -> int:
        """Send `sig` (Ctrl-C by default) and wait; kill if it does not end in time (a
        calibrator fits the model on Ctrl-C: seconds, more beside another node test)."""
        return super().stop(self._name(proc), timeout, sig)

    def wait_for_log(self, proc: subprocess.Popen, text: str, timeout: float = 60.0) -> None:
        """Until `text` is in the process's log; fails at once if the process ended."""
        deadline = time.monotonic() + timeout
        while text not in self.log(proc):
            assert time.monotonic() < deadline and proc.poll() is None, self.log(proc)
            time.sleep(0.1)

    def cleanup(self) -> None:
        self.close()


@pytest.fixture(scope="session", autouse=True)
def harmonic_fits_once(tmp_path_factory):
    """Every calibration of a method fits the harmonic map (core.methods calls
    fit_harmonic_map: a deterministic search, ~2-8 s a call, a fifth of the suite's CPU).
    Thirty of the suite's ~50 calls fit data an earlier call fitted already: the 25 file
    layouts of one bag, the same sweep calibrated in several tests. The fit is kept per
    test session, shared by the xdist workers, keyed by the bytes of every input: equal
    inputs get the map they give, anything that differs by one bit is fitted afresh.
    test_core_harmonic calls the fit itself (core.harmonic), never this copy."""
    root = tmp_path_factory.getbasetemp()
    shared = (root.parent if "PYTEST_XDIST_WORKER" in os.environ else root) / "harmonic_fits"
    shared.mkdir(exist_ok=True)
    fit = methods.fit_harmonic_map

    def fit_once(x, speed, **options):
        key = hashlib.sha256(pickle.dumps((np.asarray(x), np.asarray(speed), options)))
        path = shared / f"{key.hexdigest()}.pkl"
        # one lock per input: a worker that needs a fit the other is making waits for it
        # (both workers calibrate the shared sweep as the session starts)
        with open(path.with_suffix(".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if path.exists():
                return pickle.loads(path.read_bytes())
            result = fit(x, speed, **options)
            partial = path.with_suffix(f".{os.getpid()}")
            partial.write_bytes(pickle.dumps(result))
            os.replace(partial, path)  # a reader sees all of it or nothing
            return result

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(methods, "fit_harmonic_map", fit_once)
        yield


@pytest.fixture
def ros_domain(monkeypatch) -> int:
    """A random private ROS domain, localhost discovery, for this test and its nodes. Under
    pytest-xdist each worker draws from its own residue class (worker k of n: domains = k
    mod n), so node tests running side by side never share a domain."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    domain_id = random.SystemRandom().randrange(1, 200)
    domain_id += (int(worker.removeprefix("gw")) - domain_id) % workers
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return domain_id


@pytest.fixture
def nodes(ros_domain, tmp_path):
    procs = NodeProcesses(ros_domain, tmp_path)
    try:
        yield procs
    finally:
        procs.cleanup()


@pytest.fixture
def ros_client(ros_domain):
    """An rclpy node in the test process (own context, the test's domain), spun on demand."""
    client = Watcher("test_client")
    try:
        yield client
    finally:
        client.close()


class Feeder:
    """Publishes a robot's sensor stream (Imu, one message per sample, the profile's field)
    and JointStates from the test process in real time, 10 ms at a time, and keeps what it
    sent. JointStates carry `joint_names` (default: the profile's joints among ten others,
    in an order of their own, as a real robot's joint_state_broadcaster does), positions
    (the velocities integrated over the stamps) and velocities, or with `positions_only` an
    empty velocity field (as many real drivers). `keep_messages`: keep every message sent
    as (topic, stamp, bytes) in `messages` (to write the same stream into a bag).
    `undecodable_joints`: every JointState cut to half its bytes (a broken driver);
    `joint_clock_offset_s`: JointStates stamped by a clock this far ahead (sim vs wall time);
    `receipt_stamps`: sensor messages stamped as a USB driver reads them (1 ms frames, each
    message at its frame's end plus 0-0.2 ms of host latency), not at their samples;
    `joint_rate_hz`: how often JointStates are published (1 kHz)."""

    def __init__(
        self,
        client,
        profile,
        *,
        namespace: str = "",
        joint_names=None,
        velocity=None,
        rate_hz: float | None = None,
        seed: int = 0,
        split_joints: bool = False,
        positions_only: bool = False,
        keep_messages: bool = False,
        undecodable_joints: bool = False,
        joint_clock_offset_s: float = 0.0,
        receipt_stamps: bool = False,
        joint_rate_hz: float = 1000.0,
    ):
        from sensor_msgs.msg import Imu, JointState

        from egovib_ros.nodes.common import stream_publisher_qos

        prefix = f"{namespace.rstrip('/')}/" if namespace else ""
        self.client, self.profile = client, profile
        qos = stream_publisher_qos(depth=LOSSLESS_DEPTH)
        self.raw_pub = client.node.create_publisher(Imu, prefix + profile.node_sensor_topic, qos)
        self.joint_pub = client.node.create_publisher(
            JointState, prefix + profile.node_joints_topic, qos
        )
        self.rate_hz = rate_hz or profile.rate_hz
        self.joint_names = list(joint_names) if joint_names is not None else many_joints(profile)
        speeds = {
            **{n: 0.1 * k for k, n in enumerate(self.joint_names)},  # other joints: anything
            **{n: 0.3 * vmax for n, vmax in zip(profile.joint_names, profile.max_speed)},
            **(velocity or {}),
        }
        self.velocity = np.array([speeds[name] for name in self.joint_names])
        self.split_joints = split_joints  # two publishers, each with half of the joints
        self.positions_only = positions_only
        self.undecodable_joints = undecodable_joints
        self.joint_clock_offset_ns = int(round(joint_clock_offset_s * 1e9))
        self.receipt_stamps = receipt_stamps
        self.joint_rate_hz = joint_rate_hz
        self.last_receipt = 0
        self.last_publish_s = time.monotonic()  # when the last message went out
        self.messages: list[tuple[str, int, bytes]] | None = [] if keep_messages else None
        self.position = np.zeros(len(self.joint_names))  # of the last joint state sent
        self.last_joint_stamp: int | None = None
        self.rng = np.random.default_rng(seed)
        self.stamp0 = time.time_ns()
        self.next_index = 0
        self.stamps: list[np.ndarray] = []
        self.values: list[np.ndarray] = []

    def wait_for_subscribers(self, node: str, timeout: float = 60.0, count: int = 1) -> bool:
        """Until both sides of both links to `node` (its /diagnostics status name) have
        matched: these writers see its readers, and its report says its readers see
        publishers. DDS matches each side on its own; a reliable sample sent before the
        reader's side has matched is dropped there and resent only if the writer still
        holds it when the reader asks, so a guessed delay could lose the start on a busy
        machine. `count`: the readers these writers must see (other nodes beside `node`)."""
        return self.client.spin_until(
            lambda: (
                self.raw_pub.get_subscription_count() >= count
                and self.joint_pub.get_subscription_count() >= count
                and matched(self.client, node, sensor_publishers=1, joint_state_publishers=1)
            ),
            timeout,
        )

    def run_until(self, predicate, at_most_s: float = 3.0, then_wait_s: float = 30.0) -> bool:
        """Publish 0.1 s at a time until `predicate()` holds, for at most `at_most_s` of
        stream (e.g. until a report's window is past the start of the stream), then wait up
        to `then_wait_s` more without publishing: a node with a backlog on a busy machine
        reports what it received seconds late. Returns `predicate()`."""
        fed = 0.0
        while not predicate() and fed < at_most_s:
            self.run(0.1)
            fed += 0.1
        return self.client.spin_until(predicate, then_wait_s)

    def publish_joint_state(self) -> None:
        """One JointState stamped just before the stream: the node knows the joints before
        the first sensor sample (else it passes samples through until joint states come)."""
        from egovib_ros.bag.codec import encode_joint_state_batch

        stamps = np.array([self.stamp0 - 1_000_000])
        for data in encode_joint_state_batch(
            stamps,
            self._positions(stamps, self.velocity[None]),
            None if self.positions_only else self.velocity[None],
            self.joint_names,
        ):
            self._publish(self.joint_pub, data)

    def _positions(self, stamps: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """Joint positions at `stamps`: each step adds velocity x the time since the last
        joint state (the backward difference of the positions gives the velocities back)."""
        previous = self.last_joint_stamp if self.last_joint_stamp is not None else stamps[0]
        dt = np.diff(np.concatenate([[previous], stamps])).astype(np.float64) / 1e9
        position = self.position + np.cumsum(velocity * dt[:, None], axis=0)
        self.position, self.last_joint_stamp = position[-1], int(stamps[-1])
        return position

    def _publish(self, publisher, data: bytes) -> None:
        if self.undecodable_joints and publisher is self.joint_pub:
            data = bytes(data)[: len(data) // 2]
        publisher.publish(data)
        self.last_publish_s = time.monotonic()
        if self.messages is not None:
            self.messages.append((publisher.topic_name, header_stamp_ns(data), data))

    def run(self, seconds: float, *, skip_s: float = 0.0) -> None:
        """Publish `seconds` of white noise at constant joint velocities; `skip_s` first jumps
        the stamps (a restart after a gap)."""
        self.next_index += int(round(skip_s * self.rate_hz))
        n = int(round(seconds * self.rate_hz))
        index = self.next_index + np.arange(n)
        stamps = self.stamp0 + (index * (1e9 / self.rate_hz)).astype(np.int64)
        joint_stamps = stamps[:: max(1, int(round(self.rate_hz / self.joint_rate_hz)))]
        sensor_stamps = stamps
        if self.receipt_stamps:
            frame_end = (stamps // 1_000_000 + 1) * 1_000_000
            late = np.maximum(frame_end + self.rng.integers(0, 200_000, n), self.last_receipt)
            sensor_stamps = np.maximum.accumulate(late) + 1 + np.arange(n)
            self.last_receipt = int(sensor_stamps[-1])
        self.publish(
            sensor_stamps,
            self.rng.normal(0.0, 0.5, (n, 3)),
            joint_stamps,
            np.tile(self.velocity, (len(joint_stamps), 1)),
            all_joints=True,
        )
        self.next_index += n

    def publish(
        self, stamps, values, joint_stamps, joint_velocity, *, all_joints: bool = False
    ) -> None:
        """Publish recorded arrays at their own pace (stamps relative to the first); velocities
        are of the profile's joints unless `all_joints` (then of `joint_names`)."""
        from egovib_ros.bag.codec import encode_imu_batch, encode_joint_state_batch

        names = self.joint_names
        if not all_joints:
            columns = {name: j for j, name in enumerate(self.profile.joint_names)}
            full = np.tile(self.velocity, (len(joint_stamps), 1))
            for k, name in enumerate(names):
                if name in columns:
                    full[:, k] = joint_velocity[:, columns[name]]
            joint_velocity = full
        t0, start = int(min(stamps[0], joint_stamps[0])), time.monotonic()
        i = k = 0
        while i < len(stamps) or k < len(joint_stamps):
            due = t0 + int((time.monotonic() - start + 0.01) * 1e9)
            i_end, k_end = np.searchsorted(stamps, due), np.searchsorted(joint_stamps, due)
            if k_end > k:
                parts = [slice(None)]
                if self.split_joints:
                    parts = [slice(0, len(names) // 2), slice(len(names) // 2, None)]
                position = self._positions(joint_stamps[k:k_end], joint_velocity[k:k_end])
                # split: both publishers stamp a control tick alike (per-joint drivers)
                messages = [
                    encode_joint_state_batch(
                        joint_stamps[k:k_end] + self.joint_clock_offset_ns,
                        position[:, part],
                        None if self.positions_only else joint_velocity[k:k_end, part],
                        names[part],
                    )
                    for part in parts
                ]
                for row in zip(*messages):  # in stamp order, publisher after publisher
                    for data in row:
                        self._publish(self.joint_pub, data)
            if i_end > i:
                for data in encode_imu_batch(
                    stamps[i:i_end], values[i:i_end], "imu_link", self.profile.sensor_field
                ):
                    self._publish(self.raw_pub, data)
            i, k = i_end, k_end
            self.client.spin_for(0.01)
        self.stamps.append(np.asarray(stamps))
        self.values.append(np.asarray(values))

    def sent(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate(self.stamps), np.concatenate(self.values)

    def write_bag(self, path: Path) -> Path:
        """The messages sent (`keep_messages`), as they were, into a bag (log time = stamp):
        what `egovib` commands read offline."""
        from egovib_ros.bag.codec import IMU_TYPE, JOINT_STATE_TYPE
        from egovib_ros.bag.writer import BagWriter

        types = {self.raw_pub.topic_name: IMU_TYPE, self.joint_pub.topic_name: JOINT_STATE_TYPE}
        with BagWriter(path) as bag:
            for topic, msgtype in types.items():
                bag.add_topic(topic, msgtype)
            for topic, stamp, data in sorted(self.messages, key=lambda m: m[1]):
                bag.write(topic, stamp, data)
        return path


def reports(client, node: str, level: int | None = None, *texts: str) -> bool:
    """Whether `node`'s latest /diagnostics status has `level` (any if None) and every one
    of `texts` in its message."""
    status = client.statuses.get(node)
    return (
        status is not None
        and (level is None or status.level == level)
        and all(text in status.message for text in texts)
    )


def matched(client, node: str, **at_least: int) -> bool:
    """Whether `node`'s latest /diagnostics status reports at least these DDS match counts
    (e.g. output_subscribers=1): the node's side of those matches is done."""
    from egovib_ros.nodes.convert import diagnostic_values

    status = client.statuses.get(node)
    if status is None:
        return False
    values = diagnostic_values(status)
    return all(int(values.get(key, 0)) >= count for key, count in at_least.items())


def wait_for_output(
    client, subscription, node: str, *, subscribers: int = 1, timeout: float = 60.0
) -> bool:
    """Until `subscription` (this process's reader of `node`'s output) and `node` (its
    writer, as its /diagnostics report: `subscribers` readers, this one included) have both
    matched. The output is volatile: what the node publishes before its writer has matched
    a reader never reaches that reader."""
    return client.spin_until(
        lambda: (
            subscription.get_publisher_count() > 0
            and matched(client, node, output_subscribers=subscribers)
        ),
        timeout,
    )


def header_stamp_ns(raw: bytes) -> int:
    """The header stamp of a serialised message that starts with a std_msgs/Header (Imu,
    JointState): little-endian CDR, sec and nanosec right after the encapsulation header."""
    assert raw[1] == 1, "big-endian CDR"
    sec, nanosec = struct.unpack_from("<iI", raw, 4)
    return sec * 1_000_000_000 + nanosec


def wait_for_stream_end(client, *received: list, end_ns: int, timeout: float = 15.0) -> bool:
    """Spin until every `received` list (filled by a reliable subscription) holds a message
    stamped at or after `end_ns`. A reliable link repairs a lost packet at the writer's next
    heartbeat (3 s in Fast DDS) and holds back the samples after it until then: stopping
    the writer before that would lose them."""
    return client.spin_until(
        lambda: all(r and header_stamp_ns(r[-1]) >= end_ns for r in received), timeout
    )


def many_joints(profile) -> list[str]:
    """A JointState's names: the profile's joints among ten others, shuffled (fixed order)."""
    names = list(profile.joint_names) + [f"other_joint_{i}" for i in range(10)]
    order = np.random.default_rng(len(names)).permutation(len(names))
    return [names[i] for i in order]


@pytest.fixture
def feeder(ros_client):
    """Feeder factory bound to the test's ros_client: feeder(profile, **options)."""
    return lambda profile, **options: Feeder(ros_client, profile, **options)


@pytest.fixture(scope="session")
def sim_methods_model_path(tmp_path_factory) -> Path:
    """A free-motion noise model of the simulated hand calibrated for every method (paper,
    cancel, hybrid: `egovib calibrate --methods hybrid`), from 4 s of simulated motion."""
    from egovib_ros.core import calibrate_arrays
    from egovib_ros.core.methods import calibrate_methods
    from egovib_ros.sim import simulate_motion

    rec, _ = simulate_motion(duration_s=4.0, max_speed=0.5, seed=4)
    arrays = (rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity)
    paper, _ = calibrate_arrays(*arrays, sweep="free", source="test motion")
    model, _ = calibrate_methods(paper, *arrays, source="test motion")
    path = tmp_path_factory.mktemp("model") / "methods.npz"
    model.save(path)
    return path


@pytest.fixture(scope="session")
def sim_model_path(tmp_path_factory) -> Path:
    """A noise model calibrated offline from a short simulated superposition sweep."""
    from egovib_ros.core import calibrate_arrays
    from egovib_ros.sim import simulate_sweep

    rec, _ = simulate_sweep(grid="superposition", dwell_s=1.0, settle_s=0.3, seed=11)
    model, _ = calibrate_arrays(
        rec.sensor_stamps_ns,
        rec.sensor,
        rec.joint_stamps_ns,
        rec.joint_velocity,
        sweep="superposition",
        source="test sweep",
    )
    assert np.all(model.counts[model.axis_mask()] > 0)
    path = tmp_path_factory.mktemp("model") / "model.npz"
    model.save(path)
    return path


@pytest.fixture(scope="session")
def sim_bags(tmp_path_factory) -> Path:
    """A directory with a simulated calibration sweep (`sweep`) and a motion bag (`motion`)."""
    import simbags

    return simbags.write_sim_bags(tmp_path_factory.mktemp("sim_bags"))


@pytest.fixture(scope="session")
def sim_bags_model(sim_bags) -> Path:
    """The model `egovib calibrate` makes of sim_bags/sweep."""
    import simbags

    path = sim_bags / "fixture_model.npz"
    result = simbags.egovib("calibrate", sim_bags / "sweep", "--out", path, "--quiet")
    assert result.returncode == 0, result.stderr
    return path
