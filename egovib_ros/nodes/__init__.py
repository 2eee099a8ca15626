"""The ROS 2 executables: egovib_ros/nodes/<name>.py with main(), one per node."""

#: The one list of the executables: setup.py makes an entry point of each (it reads this
#: assignment from the source, so it stays a literal tuple of names).
NODES = (
    "sim_hand",
    "sim_robot",
    "sweep_driver",
    "calibrator",
    "denoiser",
    "contact_detector",
    "bag_recorder",
    "bag_player",
)
