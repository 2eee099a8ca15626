"""`egovib calibrate` and `egovib denoise`: the core run on recorded bags.

They call the very same core as the calibrator and denoiser nodes, so live and
offline results agree.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np
from tqdm import tqdm

from egovib_ros.bagio import read_recording, write_recording
from egovib_ros.cliutil import check_stream, nonneg_float
from egovib_ros.core import NoiseModel, calibrate_arrays, denoise_batch
from egovib_ros.core.noise_model import sweep_mask
from egovib_ros.errors import BagError
from egovib_ros.fileutil import atomic_output, prepare_output


def register(subparsers: argparse._SubParsersAction) -> None:
    cal = subparsers.add_parser(
        "calibrate", help="build a noise model from a calibration-sweep bag",
        description="Assign 64-sample blocks of a sweep bag to joint-velocity cells and write the "
                    "per-cell mean/std noise spectra (CONTRACT section 4).")
    cal.add_argument("bag", help="rosbag2 directory with /joint_states and /accelerometer/raw")
    cal.add_argument("--out", required=True, metavar="MODEL.npz", help="noise-model file to write")
    cal.add_argument("--grid", choices=("auto", "full", "superposition", "free"), default="auto",
                     help="what the bag holds: a sweep (full or superposition) or free motion; auto decides "
                          "from how many blocks sit on grid velocities")
    cal.add_argument("--force", action="store_true",
                     help="replace an existing model written by egovib")
    cal.add_argument("--quiet", action="store_true", help="no progress bar")
    cal.set_defaults(func=run_calibrate)

    den = subparsers.add_parser(
        "denoise", help="remove ego-vibration from a bag",
        description="Spectral subtraction of the model's noise at the recorded joint velocities; writes a "
                    "bag with the input topics plus /accelerometer/denoised (one message per raw sample, "
                    "with the raw sample's stamp).")
    den.add_argument("bag", help="rosbag2 directory with /joint_states and /accelerometer/raw")
    den.add_argument("--model", required=True, metavar="MODEL.npz")
    den.add_argument("--out", required=True, metavar="BAG", help="output bag directory")
    den.add_argument("--channels", choices=("per_axis", "combined"), default="per_axis",
                     help="per_axis: each axis cleaned (default); combined: the paper's 1-D signal in x")
    den.add_argument("--oversubtraction", type=nonneg_float, default=1.0,
                     help="alpha in max(|Y| - alpha N, beta N)")
    den.add_argument("--floor", type=nonneg_float, default=0.0,
                     help="beta in max(|Y| - alpha N, beta N)")
    den.add_argument("--force", action="store_true",
                     help="replace an existing bag written by egovib")
    den.add_argument("--quiet", action="store_true", help="no progress bar")
    den.set_defaults(func=run_denoise)


def run_calibrate(args: argparse.Namespace) -> int:
    prepare_output(args.out, force=args.force, inputs=[args.bag], kind="model")  # before any work
    rec = read_recording(args.bag, ground_truth=False, denoised=False)
    with tqdm(total=len(rec.accel_stamps_ns), unit="sample", unit_scale=True, desc="calibrate",
              disable=args.quiet or None, file=sys.stderr) as bar:
        model, stats = calibrate_arrays(rec.accel_stamps_ns, rec.accel, rec.joint_stamps_ns,
                                        rec.joint_velocity, source=str(args.bag), progress=bar.update,
                                        sweep=args.grid)
    # too many bad samples or unusable joint states: refused; else counted
    counts = check_stream(stats, str(args.bag), joint_states=len(rec.joint_stamps_ns))
    if model.coverage()["blocks"] == 0:
        raise BagError(f"{args.bag}: no steady block near any grid velocity "
                       f"(rejected: {stats['rejected']}); is this a calibration sweep or free motion?")
    with atomic_output(args.out) as tmp:
        model.save(tmp)
    print(model.summary(), file=sys.stderr)
    if model.measured != "free" and model.dense_ok:
        missing = int(np.sum(model.counts[sweep_mask(model.grid, model.measured)] == 0))
        if missing:
            print(f"warning: {missing} cells of the {model.measured} grid have no block; "
                  f"they are filled at load time (see NoiseModel)", file=sys.stderr)
    print(f"rejected blocks: {stats['rejected']}", file=sys.stderr)
    print(counts, file=sys.stderr)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def run_denoise(args: argparse.Namespace) -> int:
    # before any work
    prepare_output(args.out, force=args.force, inputs=[args.bag, args.model], kind="bag")
    model = NoiseModel.load(args.model)
    rec = read_recording(args.bag, joint_names=model.joint_names)      # the joints the model knows
    stamps, values, stats = denoise_batch(rec.accel_stamps_ns, rec.accel, rec.joint_stamps_ns,
                                          rec.joint_velocity, model, channels=args.channels,
                                          oversubtraction=args.oversubtraction, floor=args.floor,
                                          joint_names=rec.joint_names, source=str(args.bag))
    # too many bad samples or unusable joint states: refused; else counted
    counts = check_stream(stats, str(args.bag), joint_states=len(rec.joint_stamps_ns))
    if values.shape[1] == 1:   # CONTRACT: combined signal in x, y = z = 0
        values = np.concatenate([values, np.zeros((len(values), 2))], axis=1)
    out = dataclasses.replace(rec, denoised_stamps_ns=stamps, denoised=values)
    total = len(rec.accel_stamps_ns) * (3 if rec.contact is not None else 1) * 2 + len(rec.joint_stamps_ns)
    with atomic_output(args.out, directory=True, kind="bag") as tmp, \
            tqdm(total=total, unit="msg", unit_scale=True, desc="write", disable=args.quiet or None,
                 file=sys.stderr) as bar:
        write_recording(tmp, out, progress=bar.update)
    print(f"denoised {len(stamps)} samples ({args.channels}); blocks: {stats['blocks']}, "
          f"out of grid: {stats['blocks_out_of_grid']}, no joint state: {stats['blocks_no_joint_state']}, "
          f"dropped out-of-order: {stats['dropped_out_of_order']}", file=sys.stderr)
    print(counts, file=sys.stderr)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0

