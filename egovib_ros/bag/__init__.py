"""rosbag2 bags <-> numpy, streamed in bounded memory; no rclpy.

    read_recording(path, profile=...) -> Recording             whole bag (small bags, tests)
    iter_recording(path, profile=...) -> Iterator[Recording]    aligned time slices (any size)
    write_recording(path, rec), write_recordings(path, slices)
    BagReader(path).batches(topics) -> ReadBatch               packed messages per MCAP chunk
    BagWriter(path, compress="zstd")                           chunked MCAP (+ metadata.yaml)

Streaming a bag through the core (what `egovib calibrate` does; evaluate and gap alike)
gives the whole-array result in memory that does not grow with the bag:

    for piece in iter_recording(bag, profile=model.profile):   # topics, field, joints
        consumer.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
        out = consumer.push_sensor(piece.sensor_stamps_ns, piece.sensor)
    consumer.flush()

Layers: `mcapfile` (MCAP records, chunk by chunk), `codec` (the CDR codec of Imu,
JointState and commands), `reader`/`writer` (rosbag2 directories), `recording`
(profile-keyed arrays), `many` (several bags in parallel, Dask).
"""

from egovib_ros.bag.codec import (
    decode_imu,
    decode_joint_states,
    encode_imu_batch,
    encode_joint_state_batch,
)
from egovib_ros.bag.reader import BagReader, bag_topics
from egovib_ros.bag.recording import (
    Recording,
    concat_recordings,
    iter_recording,
    read_recording,
    write_recording,
    write_recordings,
)
from egovib_ros.bag.writer import BagWriter

__all__ = [
    "decode_imu",
    "decode_joint_states",
    "encode_imu_batch",
    "encode_joint_state_batch",
    "BagReader",
    "bag_topics",
    "Recording",
    "concat_recordings",
    "iter_recording",
    "read_recording",
    "write_recording",
    "write_recordings",
    "BagWriter",
]
