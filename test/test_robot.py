"""egovib_ros.robot: profiles load, validate every field with a one-line error, round-trip."""

import dataclasses

import numpy as np
import pytest
import yaml

from egovib_ros.errors import ConfigError
from egovib_ros.robot import RobotProfile, load_profile, profile_names


def test_default_is_the_pr2_hand_of_the_contract():
    p = load_profile()
    assert p.name == "pr2_right_hand" and p.joint_names == ("r_wrist_roll_joint", "r_gripper_joint")
    assert (
        p.grid_shape == (21, 21) and p.rate_hz == 3000 and p.sensor_field == "linear_acceleration"
    )
    assert np.allclose(p.grid()[0], np.arange(-10, 11) * 0.3)
    assert p.node_sensor_topic == "accelerometer/raw"
    assert "pr2_right_hand" in profile_names()


def test_round_trip_and_one_directional_grid():
    p = RobotProfile(
        name="drone",
        sensor_topic="/imu",
        sensor_field="angular_velocity",
        rate_hz=1000,
        denoised_topic="/imu/denoised",
        joints_topic="/motors",
        joint_names=("m1", "m2"),
        max_speed=1.0,
        bidirectional=False,
        steps=5,
        band_hz=(50, 450),
    )
    assert p.grid_shape == (6, 6) and np.allclose(p.grid()[1], [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    assert RobotProfile.loads(p.dumps()) == p
    # sensor.stamps: written only when not the default (auto), read back
    assert "stamps" not in p.to_dict()["sensor"]
    usb = dataclasses.replace(p, sensor_stamps="receipt")
    assert usb.to_dict()["sensor"]["stamps"] == "receipt" and RobotProfile.loads(usb.dumps()) == usb


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["sensor"].update(field="magnetic_field"), "sensor field"),
        (lambda d: d["sensor"].update(rate_hz=float("nan")), "rate_hz"),
        (lambda d: d["joints"].update(names=[]), "between 1 and 8 joints"),
        (
            lambda d: d["joints"].update(
                names=[f"j{i}" for i in range(9)], max_speed=[1] * 9, bidirectional=[True] * 9
            ),
            "between 1 and 8 joints",
        ),
        (lambda d: d["joints"].update(max_speed=[3.0]), "max_speed has 1 entries"),
        (lambda d: d["joints"].update(max_speed=[3.0, -1]), "max_speed"),
        (lambda d: d["joints"].update(steps=0), "steps"),
        (lambda d: d["processing"].update(band_hz=[150, 1600]), "Nyquist"),
        (lambda d: d["processing"].update(hop=48), "hop must divide"),
        (lambda d: d["joints"].update(colour="red"), "unknown key"),
        (lambda d: d["sensor"].update(stamps="arrival"), "sensor.stamps must be one of"),
        (lambda d: d.update(schema="egovib.robot/9"), "schema"),
    ],
)
def test_bad_profiles_are_one_line_errors(edit, message, tmp_path):
    data = load_profile().to_dict()
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=message) as info:
        load_profile(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_missing_profile_names_the_shipped_ones():
    with pytest.raises(ConfigError, match="pr2_right_hand"):
        load_profile("no_such_robot")


def test_a_yaml_syntax_error_names_its_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(
        "schema: egovib.robot/1\nname: mine\nprocessing:\n  band_hz: [150, 750\n  hop: 32\n"
    )
    with pytest.raises(ConfigError) as info:
        load_profile(path)
    assert str(info.value) == (
        f"{path}: not valid YAML (line 5, column 6: expected ',' or ']', but got ':')"
    )
