"""rosbag2 bags <-> numpy, streamed in bounded memory; no rclpy.

    read_recording(path, profile=...) -> Recording             whole bag (small bags, tests)
    iter_recording(path, profile=...) -> Iterator[Recording]    aligned time slices (any size)
    write_recording(path, rec), write_recordings(path, slices)
    BagReader(path).batches(topics) -> ReadBatch               packed messages per MCAP chunk
    BagWriter(path, compress="zstd")                           chunked MCAP (+ metadata.yaml)
    many.run_bags(task, jobs, jobs=N, scheduler=ADDRESS)       many bags in parallel (Dask)

Streaming a bag through the core (what `egovib calibrate` does; evaluate and gap alike):

    for piece in iter_recording(bag, profile=model.profile):   # topics, field, joints
        consumer.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
        out = consumer.push_sensor(piece.sensor_stamps_ns, piece.sensor)
        # piece.contact / piece.ego: ground truth of the same samples (sim bags)
    consumer.flush()

gives the whole-array result (`feed` on read_recording's arrays) in memory that does not
grow with the bag.

Layers: `mcapfile` (MCAP records, chunk by chunk, numpy), `codec` (packed
messages, the one CDR codec of Imu/JointState/commands), `reader`/`writer` (rosbag2 directories),
`recording` (profile-keyed arrays), `many` (several bags).
"""

from egovib_ros.bag.codec import (
    COMMANDS_TYPE,
    IMU_TYPE,
    JOINT_STATE_TYPE,
    MessageBatch,
    decode_commands,
    decode_imu,
    decode_joint_states,
    encode_commands,
    encode_imu_batch,
    encode_joint_state_batch,
    replace_imu_field,
    rosbags_imu,
    rosbags_joint_state,
    typestore,
)
from egovib_ros.bag.reader import BagReader, ReadBatch, TopicInfo, bag_topics
from egovib_ros.bag.recording import (
    Recording,
    RecordingStream,
    bag_topic_names,
    concat_recordings,
    iter_recording,
    read_recording,
    write_recording,
    write_recordings,
)
from egovib_ros.bag.writer import COMPRESSIONS, BagWriter, compression_name

__all__ = [
    "COMMANDS_TYPE",
    "IMU_TYPE",
    "JOINT_STATE_TYPE",
    "MessageBatch",
    "decode_commands",
    "decode_imu",
    "decode_joint_states",
    "encode_commands",
    "encode_imu_batch",
    "encode_joint_state_batch",
    "replace_imu_field",
    "rosbags_imu",
    "rosbags_joint_state",
    "typestore",
    "BagReader",
    "ReadBatch",
    "TopicInfo",
    "bag_topics",
    "Recording",
    "RecordingStream",
    "bag_topic_names",
    "concat_recordings",
    "iter_recording",
    "read_recording",
    "write_recording",
    "write_recordings",
    "COMPRESSIONS",
    "BagWriter",
    "compression_name",
]
