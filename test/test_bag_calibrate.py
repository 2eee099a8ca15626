"""egovib_ros.bag.calibrate (`egovib calibrate` as a library): a bag streamed into the core's
accumulator gives the whole-array model; several bags pool their cells; a failed bag is named."""

from __future__ import annotations

import shutil

import numpy as np

from egovib_ros.bag import read_recording
from egovib_ros.bag.calibrate import calibrate_bag, calibrate_bags
from egovib_ros.core import calibrate_arrays
from egovib_ros.robot import load_profile

CELL_FIELDS = ("cells", "cell_counts", "cell_mean", "cell_std")


def test_a_streamed_bag_gives_the_whole_array_model(sim_bags):
    profile = load_profile(None)
    acc = calibrate_bag(sim_bags / "sweep", profile=profile, sweep="superposition")
    rec = read_recording(sim_bags / "sweep")
    expected, _ = calibrate_arrays(
        rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity,
        profile=profile, sweep="superposition",
    )  # fmt: skip
    model = acc.to_model()
    for name in CELL_FIELDS:
        np.testing.assert_allclose(getattr(model, name), getattr(expected, name), rtol=1e-12)
    assert acc.input_counts.startswith("bad input treated as missing: 0 sensor samples")
    assert acc.input_counts.endswith(f"0 of {len(rec.joint_stamps_ns)} joint states dropped")


def test_bags_pooled_and_a_broken_one_named(sim_bags, tmp_path):
    for name in ("a", "b"):
        shutil.copytree(sim_bags / "sweep", tmp_path / "two" / name)
    one, _, _ = calibrate_bags([sim_bags / "sweep"])
    both, stats, results = calibrate_bags([tmp_path / "two"])
    assert [r.ok for r in results] == [True, True]
    np.testing.assert_array_equal(both.cell_counts, 2 * one.cell_counts)  # the same bag twice
    np.testing.assert_allclose(both.cell_mean, one.cell_mean, rtol=1e-12)
    assert both.provenance["source"].startswith("2 bags: ")
    assert one.provenance["source_bag"] == str((sim_bags / "sweep").resolve())
    mcap = next((tmp_path / "two" / "b").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:5000])
    model, stats, results = calibrate_bags([tmp_path / "two"])
    assert model is None and stats is None
    failed = [r for r in results if not r.ok]
    assert len(failed) == 1 and str(failed[0].bag).endswith("two/b") and failed[0].error
    assert not failed[0].internal  # a damaged bag is bad input, not a bug
