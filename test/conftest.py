"""Shared fixtures for the tests that run real ROS 2 nodes over real DDS.

Every such test gets a private random ROS_DOMAIN_ID with localhost-only discovery,
starts the nodes as separate processes (the venv's console scripts) and stops them
all at the end, also when the test fails.
"""
from __future__ import annotations

import random
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

from egovib_ros.orchestration import NodeGroup, Watcher


class NodeProcesses(NodeGroup):
    """The demo's NodeGroup, addressed by process handle as the tests like it."""

    def __init__(self, domain_id: int, log_dir: Path):
        super().__init__(log_dir, domain_id)

    def start(self, executable: str, params: dict | None = None, *, log_name: str | None = None, **options):
        """Run `executable --ros-args -p name:=value ...`; output goes to a log file.
        `options`: remap, namespace, args (see NodeGroup.start)."""
        return super().start(f"{log_name or executable}.{len(self.procs)}", executable, params, **options)

    def _name(self, proc: subprocess.Popen) -> str:
        return next(name for name, p in self.procs.items() if p is proc)

    def log(self, proc: subprocess.Popen) -> str:
        return super().log(self._name(proc))

    def stop(self, proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Send `sig` (Ctrl-C by default) and wait; kill if it does not end in time."""
        return super().stop(self._name(proc), timeout, sig)

    def cleanup(self) -> None:
        self.close()


@pytest.fixture
def ros_domain(monkeypatch) -> int:
    """A random private ROS domain, localhost discovery, for this test and its nodes."""
    domain_id = random.SystemRandom().randint(1, 200)
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


@pytest.fixture(scope="session")
def sim_model_path(tmp_path_factory) -> Path:
    """A noise model calibrated offline from a short simulated superposition sweep."""
    from egovib_ros.core import calibrate_arrays
    from egovib_ros.sim import simulate_sweep
    rec, _ = simulate_sweep(grid="superposition", dwell_s=1.0, settle_s=0.3, seed=11)
    model, _ = calibrate_arrays(rec.accel_stamps_ns, rec.accel, rec.joint_stamps_ns, rec.joint_velocity,
                                sweep="superposition", source="test sweep")
    assert np.all(model.counts[model.axis_mask()] > 0)
    path = tmp_path_factory.mktemp("model") / "model.npz"
    model.save(path)
    return path
