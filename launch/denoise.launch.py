"""Denoise a robot's Imu stream live with a calibrated noise model (colcon install).

    ros2 launch egovib_ros denoise.launch.py model:=/path/to/model.npz
    ros2 launch egovib_ros denoise.launch.py model:=quad.npz sensor_topic:=/fc/imu/raw \
        joints_topic:=/motors/joint_states denoised_topic:=/fc/imu/clean channels:=combined
    ros2 launch egovib_ros denoise.launch.py model:=hybrid.npz method:=hybrid

The model carries the robot profile it was calibrated with: the Imu field to clean,
the joints and the topic names (relative, so `namespace:=` applies). `sensor_topic`,
`joints_topic` and `denoised_topic` remap those names when your robot publishes
elsewhere; empty keeps the profile's. `reliable:=true` makes the inputs reliable (a
lossless replay of a bag on a loaded machine).
"""

from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def _denoiser(context):
    from egovib_ros.core import NoiseModel  # the installed package

    def arg(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    profile = NoiseModel.load(arg("model")).robot_profile()
    remappings = [
        (source, target)
        for source, target in (
            (profile.node_sensor_topic, arg("sensor_topic")),
            (profile.node_joints_topic, arg("joints_topic")),
            (profile.node_denoised_topic, arg("denoised_topic")),
        )
        if target
    ]
    # output: the method's default (dropin with paper, bandpassed with cancel and hybrid)
    extra = {"output": arg("output")} if arg("output") else {}
    if arg("reliable").lower() == "true":
        for topic in (
            arg("sensor_topic") or profile.sensor_topic,
            arg("joints_topic") or profile.joints_topic,
        ):
            extra[f"qos_overrides./{topic.lstrip('/')}.subscription.reliability"] = "reliable"
    return [
        Node(
            package="egovib_ros",
            executable="denoiser",
            name="denoiser",
            namespace=arg("namespace"),
            output="screen",
            remappings=remappings,
            parameters=[
                {
                    "model": LaunchConfiguration("model"),
                    "channels": LaunchConfiguration("channels"),
                    "method": LaunchConfiguration("method"),
                    "oversubtraction": LaunchConfiguration("oversubtraction"),
                    "floor": LaunchConfiguration("floor"),
                },
                extra,
            ],
        )
    ]


def generate_launch_description():
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "model", description="noise model (.npz) from `egovib calibrate` or the calibrator"
            ),
            DeclareLaunchArgument(
                "channels",
                default_value="per_axis",
                description="per_axis (drop-in replacement) | combined (the paper's 1-D signal)",
            ),
            DeclareLaunchArgument(
                "method",
                default_value="paper",
                description="paper (a block of delay) | cancel | hybrid (4 ms; need a model from "
                "`egovib calibrate --methods hybrid`)",
            ),
            DeclareLaunchArgument(
                "output",
                default_value="",
                description="dropin (raw minus the ego-vibration, gravity kept; paper only) | "
                "bandpassed; empty: dropin with paper, bandpassed with cancel and hybrid",
            ),
            DeclareLaunchArgument(
                "oversubtraction", default_value="1.0", description="alpha (paper); changes live"
            ),
            DeclareLaunchArgument(
                "floor", default_value="0.0", description="beta (paper); changes live"
            ),
            DeclareLaunchArgument(
                "namespace", default_value="", description="namespace of the node and its topics"
            ),
            DeclareLaunchArgument(
                "sensor_topic", default_value="", description="remap the profile's sensor topic"
            ),
            DeclareLaunchArgument(
                "joints_topic",
                default_value="",
                description="remap the profile's joint-state topic",
            ),
            DeclareLaunchArgument(
                "denoised_topic", default_value="", description="remap the profile's denoised topic"
            ),
            DeclareLaunchArgument(
                "reliable", default_value="false", description="reliable input subscriptions"
            ),
            OpaqueFunction(function=_denoiser),
        ]
    )
