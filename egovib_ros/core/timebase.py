"""Time in the package: stamps are int64 nanoseconds (ROS 2 header stamps, rosbag2 log times),
durations and rates in settings are float seconds and hertz."""

#: Nanoseconds per second: converts between the two.
NS_PER_S = 1_000_000_000
