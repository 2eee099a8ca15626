"""egovib_ros.nodes.common over real DDS: a raw subscription drained per callback takes
every message once, in order, a burst at a time."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import Imu

from egovib_ros.bag.codec import decode_imu, encode_imu_batch
from egovib_ros.nodes.common import drain, sensor_subscription, stream_publisher


def test_drain_takes_each_message_once_in_order_a_burst_per_callback(ros_client):
    node = ros_client.node
    publisher = stream_publisher(node, Imu, "drain_test")
    batches: list[list[bytes]] = []
    sub = sensor_subscription(
        node, Imu, "drain_test", lambda data: batches.append(drain(sub, Imu, data))
    )
    assert ros_client.spin_until(lambda: publisher.get_subscription_count() > 0, 20.0)
    n_bursts, burst = 60, 30
    raws = encode_imu_batch(np.arange(n_bursts * burst), np.zeros((n_bursts * burst, 3)))
    for k in range(n_bursts):
        for raw in raws[k * burst : (k + 1) * burst]:
            publisher.publish(raw)
        ros_client.spin_for(0.01)
    assert ros_client.spin_until(lambda: sum(map(len, batches)) >= len(raws), 20.0)
    ros_client.spin_for(0.2)  # the executor's events of drained messages find nothing
    stamps, _ = decode_imu([raw for batch in batches for raw in batch])
    np.testing.assert_array_equal(stamps, np.arange(len(raws)))
    assert len(batches) < len(raws) / 2  # bursts taken whole, not a callback per message
