"""Running the package's ROS 2 nodes as processes, without `launch` (not on PyPI).

`NodeGroup` starts node executables (the console scripts beside this Python) in one
private ROS domain with localhost-only discovery, so nothing else on the network sees
or disturbs them, logs each to a file, and stops them all at the end. No rclpy here: the
in-process rclpy side (`Watcher`: /diagnostics, joint commands) is
`egovib_research.tools.watcher`. Used by `egovib demo`, `egovib live-bench` and the node tests.

On a colcon install the launch files in `launch/` do the same job.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Mapping

BIN = Path(sys.executable).parent


def param_text(value) -> str:
    """A parameter value as `--ros-args -p name:=VALUE` text (YAML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        items = (json.dumps(v) if isinstance(v, str) else param_text(v) for v in value)
        return "[" + ",".join(items) + "]"
    return str(value)


#: Queue of a lossless input: 10 s at 3 kHz. Reliable is not enough: a reliable reader whose
#: keep-last queue is full drops its oldest samples, so a node starved for longer than its
#: queue (1 s by default) would lose input; with 10 s it catches up instead.
RELIABLE_INPUT_DEPTH = 30_000


def reliable_input(*topics: str, depth: int = RELIABLE_INPUT_DEPTH) -> dict[str, object]:
    """QoS override parameters that make a node's sensor subscriptions reliable and `depth`
    deep (lossless replay or calibration on a loaded machine). `topics` as the node
    resolves them (absolute names, e.g. '/accelerometer/raw')."""
    params: dict[str, object] = {}
    for topic in topics:
        prefix = f"qos_overrides./{topic.lstrip('/')}.subscription"
        params[f"{prefix}.reliability"] = "reliable"
        params[f"{prefix}.depth"] = depth
    return params


def deep_output(*topics: str, depth: int = RELIABLE_INPUT_DEPTH) -> dict[str, object]:
    """QoS override parameters that give a node's stream publishers `depth` samples of
    history, so that a reliable subscriber on a loaded machine still gets a lost sample
    resent (nodes.common.stream_publisher says why). `topics` as the node resolves them."""
    return {f"qos_overrides./{topic.lstrip('/')}.publisher.depth": depth for topic in topics}


class NodeGroup:
    """Node processes sharing one private ROS domain; `close()` stops them all."""

    def __init__(self, log_dir: str | os.PathLike, domain_id: int | None = None):
        self.domain_id = (
            domain_id if domain_id is not None else random.SystemRandom().randint(1, 200)
        )
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(
            os.environ,
            ROS_DOMAIN_ID=str(self.domain_id),
            ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
            PYTHONUNBUFFERED="1",
            RCUTILS_COLORIZED_OUTPUT="0",
        )
        self.procs: dict[str, subprocess.Popen] = {}

    def use_domain_here(self) -> None:
        """Put this process in the group's domain (before rclpy.init)."""
        os.environ["ROS_DOMAIN_ID"] = str(self.domain_id)
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

    def start(
        self,
        name: str,
        executable: str,
        params: Mapping | None = None,
        *,
        remap: Mapping[str, str] | None = None,
        namespace: str = "",
        env: Mapping[str, str] | None = None,
    ) -> subprocess.Popen:
        """Start `executable --ros-args -p k:=v ... -r from:=to ...` as process `name`
        (`env`: variables added to the group's environment for this process)."""
        cmd = [str(BIN / executable), "--ros-args"]
        for key, value in (params or {}).items():
            cmd += ["-p", f"{key}:={param_text(value)}"]
        for source, target in (remap or {}).items():
            cmd += ["-r", f"{source}:={target}"]
        if namespace:
            cmd += ["-r", f"__ns:={namespace}"]
        with open(self.log_path(name), "w") as log:
            proc = subprocess.Popen(
                cmd,
                stdout=log,
                stderr=subprocess.STDOUT,
                env={**self.env, **(env or {})},
                start_new_session=True,
            )
        self.procs[name] = proc
        return proc

    def log_path(self, name: str) -> Path:
        return self.log_dir / f"{name}.log"

    def log(self, name: str) -> str:
        return self.log_path(name).read_text()

    def check_alive(self, *names: str) -> None:
        for name in names:
            code = self.procs[name].poll()
            if code is not None:
                raise RuntimeError(
                    f"{name} exited with status {code}; its log:\n{self.log(name)[-3000:]}"
                )

    def wait_for_log(self, name: str, text: str, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.log(name):
            self.check_alive(name)
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"{name}: no '{text}' after {timeout:g} s; log:\n{self.log(name)[-3000:]}"
                )
            time.sleep(0.1)

    def stop(self, name: str, timeout: float = 30.0, sig: int = signal.SIGINT) -> int:
        """Ctrl-C the node (or send `sig`) and wait for it (kill after `timeout`)."""
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10
        for proc in self.procs.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


__all__ = [
    "NodeGroup",
    "param_text",
    "reliable_input",
    "deep_output",
    "RELIABLE_INPUT_DEPTH",
    "BIN",
]
