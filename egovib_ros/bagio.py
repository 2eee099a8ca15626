"""Compatibility shim: the bag layer lives in `egovib_ros.bag` (streaming reader and
writer, profile-keyed recordings, many bags), the CDR codec in `egovib_ros.cdr`.
Existing imports from `egovib_ros.bagio` keep working."""

from egovib_ros.bag import (  # noqa: F401
    COMPRESSIONS,
    BagReader,
    BagWriter,
    MessageBatch,
    ReadBatch,
    Recording,
    RecordingStream,
    bag_topic_names,
    bag_topics,
    compression_name,
    concat_recordings,
    iter_recording,
    read_recording,
    write_recording,
    write_recordings,
)
from egovib_ros.cdr import (  # noqa: F401
    COMMANDS_TYPE,
    IMU_TYPE,
    JOINT_STATE_TYPE,
    decode_commands,
    decode_imu,
    decode_imu_batch,
    decode_joint_state_batch,
    encode_commands,
    encode_imu_batch,
    encode_joint_state_batch,
    imu_message,
    joint_state_message,
    replace_imu_field,
    typestore,
)
