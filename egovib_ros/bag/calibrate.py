"""`egovib calibrate` as a library: noise models from recorded bags.

calibrate_bag(bag, profile=..., sweep=...) -> CalibrationAccumulator (one bag, streamed)
calibrate_bags([bag, ...], profile=..., sweep=..., jobs=...) -> (NoiseModel, stats, results)
"""

from __future__ import annotations

import functools
import os
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

from egovib_ros.bag.many import BagJob, expand_bags, run_bags
from egovib_ros.bag.reader import bag_fingerprint
from egovib_ros.bag.recording import iter_recording, read_recording
from egovib_ros.core import CalibrationAccumulator
from egovib_ros.core.methods import calibrate_detection, calibrate_methods
from egovib_ros.core.stream import check_stream
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.robot import RobotProfile, load_profile


def calibrate_bag(
    bag: str | os.PathLike,
    *,
    profile: RobotProfile,
    sweep: str = "auto",
    joint_lag_s: float = 0.0,
    progress: Callable[[int], None] | None = None,
) -> CalibrationAccumulator:
    """Stream one bag into a CalibrationAccumulator (flushed). Memory: one slice. The
    accumulator's `input_counts` is the line of bad-input counts to print. `joint_lag_s`:
    the joint states lag the sensor by this much (their stamps are moved later)."""
    where = f"{bag}: {profile.sensor_topic}"
    acc = CalibrationAccumulator(
        profile=profile, sweep=sweep, source=where, joint_lag_s=joint_lag_s
    )
    joint_states = 0
    for piece in iter_recording(
        bag, profile=profile, ground_truth=False, denoised=False, commands=False, progress=progress
    ):
        acc.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
        acc.push_sensor(piece.sensor_stamps_ns, piece.sensor)
        joint_states += len(piece.joint_stamps_ns)
    acc.flush()
    # too many bad samples or unusable joint states: refused; else counted
    acc.input_counts = check_stream(
        acc.stats, where, joint_states=joint_states, joints_where=f"{bag}: {profile.joints_topic}"
    )
    return acc


def _calibrate_task(bag: Path, out, progress, **options) -> CalibrationAccumulator:
    return calibrate_bag(bag, progress=progress, **options)


def calibrate_bags(
    bags: Sequence[str | os.PathLike],
    *,
    profile: RobotProfile | None = None,
    sweep: str = "auto",
    joint_lag_s: float = 0.0,
    jobs: int = 1,
    scheduler: str | None = None,
    quiet: bool = True,
):
    """One noise model from one or more bags (bags read in parallel with `jobs` > 1 or a
    Dask `scheduler`). Returns (model, stats, per-bag results); model is None if a bag
    failed (the results say which and why)."""
    profile = profile or load_profile(None)
    pairs = expand_bags(bags, outputs_per_bag=False)  # one model from all of them
    task = functools.partial(_calibrate_task, profile=profile, sweep=sweep, joint_lag_s=joint_lag_s)
    results = run_bags(
        task,
        [BagJob(bag) for bag, _ in pairs],
        jobs=jobs,
        scheduler=scheduler,
        desc="calibrate",
        quiet=quiet,
    )
    accumulators = [r.value for r in results if r.ok]
    for r in results:  # what the summary shows per bag (before pooling)
        if r.ok:
            r.value = dict(r.value.stats.as_dict(), input_counts=r.value.input_counts)
    if not all(r.ok for r in results):
        return None, None, results
    # Bags are separate streams, each framed and flushed on its own: only the statistics
    # (sweep and free-motion tally: "auto" decides on the pooled data) are pooled, in the
    # order given, so the result does not depend on which bag finished first.
    acc = accumulators[0]
    for other in accumulators[1:]:
        acc.merge(other)
    # absolute paths: `evaluate` finds the calibration bag from any directory, and its
    # fingerprint tells whether it is still the bag the model was made from
    names = [str(Path(b).resolve()) for b, _ in pairs]
    source = (
        names[0]
        if len(names) == 1
        else f"{len(names)} bags: " + ", ".join(names[:20]) + (", ..." if len(names) > 20 else "")
    )
    model = acc.to_model(source=source)
    if len(names) == 1:
        model.provenance["source_bag"] = names[0]
        # the bag as given: a warning its reader gives (a truncated file) then reads as the
        # calibration's own, said once
        model.provenance["source_fingerprint"] = bag_fingerprint(pairs[0][0])
    return model, acc.stats, results


def calibrate_bag_methods(
    bag: str | os.PathLike, model, *, joint_lag_s: float = 0.0, methods: str = "all"
):
    """What the other methods need on top of the paper's table, fitted on the calibration
    bag `bag` of `model`: with methods "all", what `cancel` and `hybrid` need
    (core.methods.calibrate_methods); always the contact detector's thresholds of each method
    the model can run (core.methods.calibrate_detection). Returns (the model with them,
    {"methods": what was fitted or None, "thresholds": ..., "seconds": the recording's
    length, "recording": it, joint states as calibrated}). The fit takes the recording
    whole: memory grows with the bag."""
    profile = model.robot_profile()
    rec = read_recording(bag, profile=profile, ground_truth=False, denoised=False)
    rec = replace(rec, joint_stamps_ns=rec.joint_stamps_ns + int(round(joint_lag_s * NS_PER_S)))
    arrays = (rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity)
    source = f"{bag}: {profile.sensor_topic}"
    fitted = None
    if methods == "all":
        model, fitted = calibrate_methods(model, *arrays, source=source)
    model, thresholds = calibrate_detection(model, *arrays, source=source)
    seconds = len(rec.sensor_stamps_ns) / profile.rate_hz
    return model, {
        "methods": fitted,
        "thresholds": thresholds,
        "seconds": seconds,
        "recording": rec,
    }
