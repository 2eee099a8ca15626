"""Calibrate a noise model live (colcon install): the calibrator, and optionally the sweep
driver that commands the robot through its velocity grid.

    # a robot you drive yourself (free motion, no contact), Ctrl-C when done:
    ros2 launch egovib_ros calibrate.launch.py robot:=/path/profile.yaml grid:=free \
        output:=model.npz
    # a sweep over the grid (ros2_control forward-command controller on `commands_topic`):
    ros2 launch egovib_ros calibrate.launch.py robot:=quadcopter grid:=superposition sweep:=true \
        commands_topic:=/motor_velocity_controller/commands dwell:=5.0
    # the simulated PR2 hand, end to end:
    ros2 launch egovib_ros calibrate.launch.py sim:=true sweep:=true dwell:=2.0
    # any profile simulated (sim_robot), end to end:
    ros2 launch egovib_ros calibrate.launch.py robot:=example_arm sim:=true sweep:=true dwell:=1.0

`robot` is a profile path or a shipped name (config/robots); empty = the PR2 hand.
`sim:=true` simulates the robot too: sim_hand without `robot` (the PR2 hand), sim_robot
with it (any profile; publishing, as sim_hand here, no ground truth). The calibrator
writes a checkpoint after every cell and the model at Ctrl-C; a restarted calibrator
resumes from the checkpoint. With `sweep:=true` the launch ends when the
sweep has been commanded; stop the calibrator then (Ctrl-C) to write the model.
"""

from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description():
    robot, grid = LaunchConfiguration("robot"), LaunchConfiguration("grid")
    commands = [("hand_velocity_controller/commands", LaunchConfiguration("commands_topic"))]
    sim = LaunchConfiguration("sim")
    simulated = ["'", sim, "'.lower() in ('true', '1') and '", robot, "'"]
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "robot", default_value="", description="robot profile path or shipped name"
            ),
            DeclareLaunchArgument(
                "output",
                default_value="noise_model.npz",
                description="model file written at Ctrl-C",
            ),
            DeclareLaunchArgument(
                "grid", default_value="superposition", description="full | superposition | free"
            ),
            DeclareLaunchArgument(
                "sweep", default_value="false", description="start the sweep driver"
            ),
            DeclareLaunchArgument(
                "dwell", default_value="15.0", description="sweep: seconds per cell"
            ),
            DeclareLaunchArgument(
                "settle", default_value="1.0", description="sweep: seconds to reach each cell"
            ),
            DeclareLaunchArgument(
                "commands_topic",
                default_value="hand_velocity_controller/commands",
                description="the velocity controller's command topic (Float64MultiArray)",
            ),
            DeclareLaunchArgument(
                "sim",
                default_value="false",
                description="simulate the robot too: sim_hand without robot, sim_robot with it",
            ),
            Node(
                package="egovib_ros",
                executable="calibrator",
                name="calibrator",
                output="screen",
                parameters=[
                    {"robot": robot, "grid": grid, "output": LaunchConfiguration("output")}
                ],
            ),
            Node(
                package="egovib_ros",
                executable="sweep_driver",
                name="sweep_driver",
                output="screen",
                condition=IfCondition(LaunchConfiguration("sweep")),
                remappings=commands,
                parameters=[
                    {
                        "robot": robot,
                        "grid": grid,
                        "dwell": LaunchConfiguration("dwell"),
                        "settle": LaunchConfiguration("settle"),
                    }
                ],
            ),
            Node(
                package="egovib_ros",
                executable="sim_hand",
                name="sim_hand",
                output="screen",
                condition=IfCondition(PythonExpression(simulated + [" == ''"])),
                remappings=commands,
                parameters=[{"publish_ground_truth": False}],
            ),
            Node(
                package="egovib_ros",
                executable="sim_robot",
                name="sim_robot",
                output="screen",
                condition=IfCondition(PythonExpression(simulated + [" != ''"])),
                remappings=commands,
                parameters=[{"robot": robot, "publish_ground_truth": False}],
            ),
        ]
    )
