"""bag_player: play a rosbag2 (MCAP or sqlite3) at its recorded timing, then exit.

Messages (read batch by batch by egovib_ros.bag.BagReader) are published as stored at
their bag receive times, scaled by `rate`; topic names drop their leading '/' so that
namespaces and remappings apply. With `clock: true`, /clock carries the bag time, so nodes
started with use_sim_time run on the recording's time base.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Iterator

import numpy as np
import rclpy
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from egovib_ros.bag import BagReader
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import BagError
from egovib_ros.nodes.bag_recorder import message_class
from egovib_ros.nodes.common import (
    Param,
    SubscriberGate,
    declare_parameters,
    run_node,
    stream_publisher,
    wait_for_delivery,
)
from egovib_ros.nodes.convert import ns_to_stamp

TICK_S = 0.002  # publishing granularity: messages due within a tick go out together
CLOCK_PERIOD_NS = 1_000_000  # /clock at up to 1 kHz of bag time
PARAMETERS = (
    Param("bag", "", "rosbag2 directory to play"),
    Param("rate", 1.0, "playback speed factor (2.0 = twice as fast)", range=(0.001, 1000.0)),
    Param("clock", False, "publish /clock with the bag time"),
    Param(
        "topics",
        [""],
        "topics to play (bag names, with or without the leading '/', as bag_recorder takes "
        "them); empty = all",
    ),
    Param(
        "wait_for_subscribers",
        0,
        "wait until every played topic has at least this many subscribers (and /clock one, "
        "when published) before starting",
        range=(0, 100),
    ),
    Param(
        "wait_timeout",
        10.0,
        "seconds to wait for subscribers before giving up",
        range=(0.0, 3600.0),
    ),
    Param("start_delay", 0.0, "seconds to wait before playing", range=(0.0, 3600.0)),
    Param(
        "linger",
        0.5,
        "seconds to stay up after the last message was acknowledged (or not within 5 s)",
        range=(0.0, 3600.0),
    ),
)


def bag_topic_key(name: str) -> str:
    """A topic name as bags and the `topics` parameter are compared: bags store absolute
    names ('/joint_states'), users write them either way ('joint_states')."""
    return "/" + name.strip().lstrip("/")


class BagPlayer(Node):
    """Plays the bag `bag`; `run()` returns when every message was published."""

    def __init__(self):
        super().__init__("bag_player")
        params = declare_parameters(self, PARAMETERS)
        self.bag = Path(params["bag"])
        self.rate = params["rate"]
        self.wait_for_subscribers = params["wait_for_subscribers"]
        self.wait_timeout = params["wait_timeout"]
        self.start_delay = params["start_delay"]
        self.linger = params["linger"]
        if not (self.bag / "metadata.yaml").is_file():
            raise BagError(f"{self.bag}: not a rosbag2 directory (no metadata.yaml)")
        self.reader = BagReader(self.bag)  # the bag layer: BagError on an unreadable bag
        wanted = {bag_topic_key(t) for t in params["topics"] or [] if t.strip()}
        missing = sorted(wanted - {bag_topic_key(t) for t in self.reader.topics})
        if missing and len(missing) == len(wanted):
            raise BagError(f"{self.bag}: none of the topics {missing} is in the bag")
        if missing:
            self.get_logger().warning(f"{self.bag}: topics {missing} are not in the bag")
        self.topic_publishers = {}
        for topic, info in self.reader.topics.items():
            if wanted and bag_topic_key(topic) not in wanted:
                continue
            try:
                msg_class = message_class(info.msgtype)
            except (ImportError, AttributeError):
                self.get_logger().warning(f"{topic}: type {info.msgtype} not available, skipped")
                continue
            self.topic_publishers[topic] = stream_publisher(self, msg_class, topic.lstrip("/"))
        self.clock_publisher = (
            self.create_publisher(Clock, "/clock", 10) if params["clock"] else None
        )
        self.published = 0

    def _wait_for_subscribers(self) -> None:
        gates = [
            SubscriberGate(
                list(self.topic_publishers.values()), self.wait_for_subscribers, self.wait_timeout
            )
        ]
        if self.clock_publisher is not None:
            # the nodes on sim time: a /clock they miss at the start shifts their start
            gates.append(SubscriberGate([self.clock_publisher], 1, self.wait_timeout))
        while rclpy.ok() and not all([gate.is_open() for gate in gates]):  # poll every gate
            time.sleep(0.05)
        if any(gate.timed_out for gate in gates):
            self.get_logger().warning("not every topic has its subscribers; playing anyway")

    def run(self) -> int:
        """Publish every message at its recorded time (scaled by rate); 0 when all are out."""
        if self.wait_for_subscribers > 0:
            self._wait_for_subscribers()
        time.sleep(self.start_delay)
        topics = list(self.topic_publishers)
        count = sum(self.reader.topics[t].count for t in topics)
        self.get_logger().info(f"playing {self.bag} ({count} messages) at rate {self.rate}")
        start_wall, start_bag_ns = time.monotonic(), None
        clock_msg = Clock()
        last_clock_ns = None
        for bag_ns, topic, data in self._in_time_order(topics):
            if start_bag_ns is None:
                start_bag_ns = bag_ns
            due = start_wall + (bag_ns - start_bag_ns) / NS_PER_S / self.rate
            wait = due - time.monotonic()
            if wait > TICK_S:
                time.sleep(wait)
            if not rclpy.ok():
                self.get_logger().info(f"interrupted after {self.published} messages")
                return 0
            # /clock at most every CLOCK_PERIOD_NS of bag time, always before the message it covers.
            if self.clock_publisher is not None and (
                last_clock_ns is None or bag_ns - last_clock_ns >= CLOCK_PERIOD_NS
            ):
                clock_msg.clock = ns_to_stamp(bag_ns)
                self.clock_publisher.publish(clock_msg)
                last_clock_ns = bag_ns
            self.topic_publishers[topic].publish(data)
            self.published += 1
        played_s = time.monotonic() - start_wall  # the pacing, as no subscriber's lag shows it
        wait_for_delivery(self, list(self.topic_publishers.values()), "the last messages")
        time.sleep(self.linger)
        self.get_logger().info(
            f"done: {self.published} messages played in {played_s:.3f} s at rate {self.rate}"
        )
        return 0

    def _in_time_order(self, topics: list[str]) -> Iterator[tuple[int, str, bytes]]:
        """(log time, topic, message) of `topics` in log-time order, read batch by batch by
        the bag layer; messages later than a batch's frontier wait for the next batches."""
        held_t, held_topic, held_data = np.zeros(0, np.int64), [], []
        for batch in self.reader.batches(topics):
            for topic, messages in batch.messages.items():
                held_t = np.concatenate([held_t, messages.log_times])
                held_topic += [topic] * len(messages)
                held_data += messages.to_list()
            order = np.argsort(held_t, kind="stable")
            ready = (
                len(order)
                if batch.frontier_ns is None
                else int(np.searchsorted(held_t[order], batch.frontier_ns, side="right"))
            )
            for i in order[:ready]:
                yield int(held_t[i]), held_topic[i], held_data[i]
            rest = order[ready:]
            held_t = held_t[rest]
            held_topic = [held_topic[i] for i in rest]
            held_data = [held_data[i] for i in rest]
        for i in np.argsort(held_t, kind="stable"):
            yield int(held_t[i]), held_topic[i], held_data[i]

    def close(self) -> None:
        self.reader.close()


def main(args: list[str] | None = None) -> int:
    return run_node(BagPlayer, args)


if __name__ == "__main__":
    raise SystemExit(main())
