"""`egovib calibrate` and `egovib denoise`: the core run on recorded bags.

They call the very same core as the calibrator and denoiser nodes, so live and
offline results agree. Bags are streamed (egovib_ros.bag): memory does not grow with
the recording, topics that are only copied are copied as serialized bytes (whole MCAP
chunks when possible), and several bags or directories of bags run in parallel
(`--jobs`, Dask) with one progress bar and one summary.

Library use (evaluate, gap and scripts call these directly):
    denoise_bag(bag, out, model=..., channels=..., compress=...) -> dict of figures
    calibrate_bags([bag, ...], profile=..., sweep=...) -> (NoiseModel, stats)
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from egovib_ros.bag import (
    BagReader,
    BagWriter,
    MessageBatch,
    RecordingStream,
    compression_name,
    iter_recording,
)
from egovib_ros.bag.codec import imu_layout, replace_imu_field
from egovib_ros.bag.many import BagJob, expand_bags, raise_if_bugs, run_bags, summary_lines
from egovib_ros.bag.mcapfile import MESSAGE_HEADER, message_records, rows
from egovib_ros.bag.reader import bag_fingerprint
from egovib_ros.cliutil import check_stream, int_in, nonneg_float
from egovib_ros.core import CalibrationAccumulator, NoiseModel, StreamingDenoiser
from egovib_ros.core.noise_model import sweep_mask
from egovib_ros.errors import BagError, ConfigError
from egovib_ros.fileutil import atomic_output, prepare_output
from egovib_ros.robot import RobotProfile, load_profile


def register(subparsers: argparse._SubParsersAction) -> None:
    cal = subparsers.add_parser(
        "calibrate",
        help="build a noise model from a calibration sweep or any no-contact recording",
        description="Assign blocks of the bags' sensor signal to joint-velocity cells and write "
        "the per-cell mean/std noise spectra (CONTRACT section 4). Several bags (or directories "
        "of bags) give one model; they are read in parallel with --jobs.",
    )
    cal.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 bag(s) or directories of bags")
    cal.add_argument("--out", required=True, metavar="MODEL.npz", help="noise-model file to write")
    cal.add_argument(
        "--robot",
        metavar="PROFILE",
        default=None,
        help="robot profile (YAML path or shipped name); default the PR2 hand",
    )
    cal.add_argument(
        "--grid",
        choices=("auto", "full", "superposition", "free"),
        default="auto",
        help="what the bags hold: a full or superposition sweep, or free (any no-contact) motion; "
        "auto = decided from the data",
    )
    parallel_options(cal)
    cal.add_argument(
        "--force", action="store_true", help="replace an existing model written by egovib"
    )
    cal.add_argument("--quiet", action="store_true", help="no progress bar")
    cal.set_defaults(func=run_calibrate)

    den = subparsers.add_parser(
        "denoise",
        help="remove ego-vibration from bags",
        description="Spectral subtraction of the model's noise at the recorded joint velocities; "
        "writes a bag with the input topics (copied as they are) plus the model's denoised "
        "topic: one message per raw sample, the input message with the cleaned field, the raw "
        "sample's stamp. Several bags (or directories of bags): --out is a directory, one "
        "output bag per input.",
    )
    den.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 bag(s) or directories of bags")
    den.add_argument("--model", required=True, metavar="MODEL.npz")
    den.add_argument(
        "--out",
        required=True,
        metavar="BAG",
        help="output bag directory (one input bag) or directory of output bags (several)",
    )
    den.add_argument(
        "--channels",
        choices=("per_axis", "combined"),
        default="per_axis",
        help="per_axis: each axis cleaned (default); combined: the paper's 1-D signal in x",
    )
    den.add_argument(
        "--output",
        choices=("dropin", "bandpassed"),
        default=None,
        help="dropin (default with per_axis): the raw field minus the estimated ego-vibration, "
        "gravity and everything outside the band kept; bandpassed: the cleaned band-passed "
        "signal (the paper's; always with --channels combined)",
    )
    den.add_argument(
        "--oversubtraction",
        type=nonneg_float,
        default=1.0,
        help="alpha in max(|Y| - alpha N, beta N)",
    )
    den.add_argument(
        "--floor", type=nonneg_float, default=0.0, help="beta in max(|Y| - alpha N, beta N)"
    )
    den.add_argument(
        "--compress",
        choices=("none", "zstd"),
        default="none",
        help="MCAP chunk compression of the output bag (readable by rosbags and ros2 bag)",
    )
    parallel_options(den)
    den.add_argument(
        "--force", action="store_true", help="replace an existing bag written by egovib"
    )
    den.add_argument("--quiet", action="store_true", help="no progress bar")
    den.set_defaults(func=run_denoise)


def parallel_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--jobs",
        type=int_in(1, 4096),
        default=1,
        metavar="N",
        help="bags processed at once (N > 1: a local Dask cluster of N worker processes)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run on an existing Dask cluster (e.g. tcp://host:8786) instead of a local one",
    )


# --------------------------------------------------------------------------
# denoise
# --------------------------------------------------------------------------
def model_profile(model: NoiseModel) -> RobotProfile:
    """The robot profile the model was calibrated with (topics, field, joints)."""
    if model.profile is None:
        raise ConfigError(
            f"{model.provenance.get('path', 'noise model')}: the model carries no robot profile "
            f"and is not the PR2 grid; recalibrate it with --robot PROFILE"
        )
    return model.profile


class _DenoisedTopic:
    """Writes the profile's denoised topic: for every sample the denoiser outputs, the raw
    message with that header stamp, its field replaced (every other byte kept), at the raw
    message's log time.

    Raw messages are held by stamp, not by their place in the file: a bag may hold its
    messages in any order (topic by topic, chunks overlapping in time, stamps swapped), and
    the recording stream hands the denoiser its samples in stamp order. The denoiser's
    output stamps increase strictly, so each is found by a binary search among the held
    stamps; a held message the output has passed without taking it (out of order, a bad
    sample, a second message with the same stamp) gets no denoised message and is counted.
    Memory: the raw messages the denoiser has not answered yet (a block plus the stream's
    look-ahead)."""

    def __init__(self, writer: BagWriter, denoised_topic: str, field: str):
        self.writer = writer
        self.denoised_topic, self.field = denoised_topic, field
        self.channel_id = writer.topics[denoised_topic].channel_id
        self._batches: dict[int, tuple[MessageBatch, int | None]] = {}  # id -> (raw, field offset)
        self._next_id = 0
        # the held raw messages, sorted by stamp (ties in the order read): stamp, batch id, row
        self._stamp = np.zeros(0, np.int64)
        self._batch = np.zeros(0, np.int64)
        self._row = np.zeros(0, np.int64)
        self._passed: int | None = None  # stamp of the last output sample
        self.raw_read = 0
        self.written = 0
        self.dropped = 0

    def add_raw(self, raw: MessageBatch, stamps: np.ndarray) -> None:
        """Hold raw messages (any order) until the denoiser answers their stamps."""
        if len(raw) == 0:
            return
        self.raw_read += len(raw)
        rows_ = np.arange(len(raw), dtype=np.int64)
        if self._passed is not None:  # stamped before the output's progress: never answered
            late = stamps <= self._passed
            if late.any():
                self.dropped += int(late.sum())
                stamps, rows_ = stamps[~late], rows_[~late]
                if len(stamps) == 0:
                    return
        ident = self._next_id
        self._next_id += 1
        self._batches[ident] = (raw, imu_layout(raw, self.field))
        in_order = np.all(stamps[1:] >= stamps[:-1]) and (
            len(self._stamp) == 0 or stamps[0] >= self._stamp[-1]
        )
        self._stamp = np.concatenate([self._stamp, stamps])
        self._batch = np.concatenate([self._batch, np.full(len(stamps), ident, np.int64)])
        self._row = np.concatenate([self._row, rows_])
        if not in_order:
            order = np.argsort(self._stamp, kind="stable")
            self._stamp, self._batch, self._row = (
                self._stamp[order],
                self._batch[order],
                self._row[order],
            )

    def add_output(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """Write the denoised messages of these output samples (stamps strictly increasing)."""
        if len(stamps) == 0:
            return
        values = np.asarray(values, np.float64)
        if values.shape[1] == 1:  # the combined signal goes in x, y = z = 0
            values = np.concatenate([values, np.zeros((len(values), 2))], axis=1)
        at = np.searchsorted(self._stamp, stamps, side="left")
        found = at < len(self._stamp)
        found[found] = self._stamp[at[found]] == stamps[found]
        if not found.all():  # cannot happen: every output sample is a raw sample held here
            stamp = int(stamps[~found][0])
            raise RuntimeError(f"denoised sample stamped {stamp} has no held raw message")
        batches, rows_ = self._batch[at], self._row[at]
        self._write(batches, rows_, values)
        done = int(at[-1]) + 1
        self.dropped += done - len(at)
        self._passed = int(stamps[-1])
        self._stamp, self._batch, self._row = (
            self._stamp[done:],
            self._batch[done:],
            self._row[done:],
        )
        still = set(np.unique(self._batch).tolist())
        for ident in [i for i in self._batches if i not in still]:
            del self._batches[ident]

    def finish(self) -> None:
        """End of the bag: raw messages never answered are counted."""
        self.dropped += len(self._stamp)
        self._stamp, self._batch, self._row = self._stamp[:0], self._batch[:0], self._row[:0]
        self._batches.clear()

    def _write(self, batches: np.ndarray, rows_: np.ndarray, values: np.ndarray) -> None:
        # runs of consecutive messages from one raw batch, in output order
        cuts = np.flatnonzero(batches[1:] != batches[:-1]) + 1
        runs = [
            (self._batches[int(batches[a])], rows_[a:b])
            for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(batches)])
        ]
        log_times = np.concatenate([raw.log_times[r] for (raw, _), r in runs])
        widths = {raw.uniform_length for (raw, _), _ in runs}
        offsets = {offset for (_, offset), _ in runs}
        if len(widths) != 1 or None in widths or len(offsets) != 1 or None in offsets:
            # unusual messages: the codec's general path
            messages = MessageBatch.concat([raw.take(r) for (raw, _), r in runs])
            self.writer.write_batch(
                self.denoised_topic, log_times, replace_imu_field(messages, values, self.field)
            )
        else:
            width, offset = widths.pop(), offsets.pop()
            records = message_records(self.channel_id, log_times, None, width)
            row = 0
            for (raw, _), r in runs:
                records[row : row + len(r), MESSAGE_HEADER:] = rows(raw.buf, raw.starts[r], width)
                row += len(r)
            at = MESSAGE_HEADER + offset
            records[:, at : at + 24] = (
                np.ascontiguousarray(values, "<f8").view(np.uint8).reshape(-1, 24)
            )
            self.writer.write_message_records(self.denoised_topic, log_times, records)
        self.written += len(batches)


def denoise_bag(
    bag: str | os.PathLike,
    out: str | os.PathLike,
    *,
    model: NoiseModel | str | os.PathLike,
    channels: str = "per_axis",
    output: str | None = None,
    oversubtraction: float = 1.0,
    floor: float = 0.0,
    compress: bool | str = False,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Denoise one bag into `out` (written atomically: nothing appears unless complete).

    Streams the bag: input MCAP chunks are copied verbatim (topics never decoded but
    the sensor and joint topics), the profile's denoised topic is added, one message
    per raw sample. Returns figures (samples, blocks, size ratio, ...)."""
    model = model if isinstance(model, NoiseModel) else NoiseModel.load(model)
    profile = model_profile(model)
    bag = Path(bag)
    with BagReader(bag) as reader:
        stream = RecordingStream(
            reader, profile, ground_truth=False, denoised=False, commands=False
        )
        raw_topic, denoised_topic = stream.names["raw"], stream.names["denoised"]
        copy_topics = [t for t in reader.topics if t != denoised_topic]
        denoiser = StreamingDenoiser(
            model,
            channels=channels,
            output=output,
            oversubtraction=oversubtraction,
            floor=floor,
            source=f"{bag}: {raw_topic}",
        )
        with atomic_output(out, directory=True, kind="bag") as tmp:
            with BagWriter(tmp, compress=compress) as writer:
                for topic in copy_topics:
                    writer.copy_topic(reader, topic)
                writer.copy_topic(reader, raw_topic, as_topic=denoised_topic)
                job = _DenoisedTopic(writer, denoised_topic, profile.sensor_field)
                copied = {"verbatim": 0, "rewritten": 0}  # chunks copied as they were; batches

                def push(pieces) -> None:
                    for piece in pieces:
                        for chunk in (
                            denoiser.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity),
                            denoiser.push_accel(piece.accel_stamps_ns, piece.accel),
                        ):
                            job.add_output(chunk.stamps_ns, chunk.values)

                for batch in reader.batches(copy_topics):
                    verbatim = writer.copy_batch(batch, set(copy_topics))
                    copied["verbatim"] += verbatim
                    copied["rewritten"] += verbatim == 0
                    pieces = stream.add(batch)
                    if "raw" in stream.decoded:
                        job.add_raw(batch.messages[raw_topic], stream.decoded["raw"][0])
                    push(pieces)
                    if progress is not None:
                        progress(batch.bytes_read)
                push(stream.finish())
                final = denoiser.flush()
                job.add_output(final.stamps_ns, final.values)
                job.finish()
                # too many bad samples or unusable joint states: refused (before the bag appears)
                counts = check_stream(
                    denoiser.stats,
                    f"{bag}: {raw_topic}",
                    joint_states=stream.counts["joint_states"],
                )
                ratio = writer.size_ratio
    stats = denoiser.stats
    return {
        "samples_in": job.raw_read,
        "denoised_messages": job.written,
        "raw_without_output": job.dropped,
        "blocks": stats["blocks"],
        "blocks_out_of_grid": stats["blocks_out_of_grid"],
        "blocks_no_joint_state": stats["blocks_no_joint_state"],
        "blocks_unmeasured": stats.get("blocks_unmeasured", 0),
        "dropped_out_of_order": stats["dropped_out_of_order"],
        "channels": channels,
        "output": denoiser.output,
        "chunks_copied_verbatim": copied["verbatim"],
        "batches_rewritten": copied["rewritten"],
        "size_ratio": ratio,
        "compression": compression_name(compress) or "none",
        "input_counts": counts,
    }


def _describe_denoise(figures: dict) -> str:
    text = (
        f"{figures['denoised_messages']} samples denoised ({figures['channels']}, "
        f"{figures['output']}); "
        f"blocks {figures['blocks']}, out of grid {figures['blocks_out_of_grid']}, "
        f"no joint state {figures['blocks_no_joint_state']}"
    )
    if figures.get("blocks_unmeasured"):
        text += f", on unmeasured cells {figures['blocks_unmeasured']}"
    if figures["raw_without_output"]:
        text += f", raw samples dropped (out of order / non-finite) {figures['raw_without_output']}"
    if figures["compression"] != "none" and figures["size_ratio"]:
        text += f"; zstd size ratio {figures['size_ratio']:.1f}"
    return text + f"; {figures['input_counts']}"


def _denoise_task(bag: Path, out: Path, progress, **options) -> dict:
    return denoise_bag(bag, out, progress=progress, **options)


def output_jobs(
    specs: Sequence[str], out: str | os.PathLike, *, suffix: str = "", option: str = "--out"
) -> list[BagJob]:
    """One input bag -> `out` is its output; several (or a directory) -> `out` is a
    directory holding one output per input, under the input's relative name + `suffix`."""
    pairs = expand_bags(specs)
    target = Path(out).resolve()
    for spec in specs:  # a later run over the same input would take the outputs for inputs
        if target.is_relative_to(Path(spec).resolve()):
            raise ConfigError(f"{out}: {option} is inside the input {spec}; write it elsewhere")
    single = len(specs) == 1 and len(pairs) == 1 and Path(specs[0]) == pairs[0][0]
    if single:
        return [BagJob(pairs[0][0], Path(out))]
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: with several input bags {option} must be a directory")
    return [BagJob(bag, out / f"{name}{suffix}") for bag, name in pairs]


def run_denoise(args: argparse.Namespace) -> int:
    model = NoiseModel.load(args.model)  # a bad model fails once, before any bag is touched
    model_profile(model)
    # Bad options fail here too; this also builds the model's look-up table once, which
    # the workers then receive with the model instead of each building (and logging) it.
    StreamingDenoiser(
        model,
        channels=args.channels,
        output=args.output,
        oversubtraction=args.oversubtraction,
        floor=args.floor,
    )
    jobs = output_jobs(args.bags, args.out)
    for job in jobs:  # before any work: every output may be written (or replaced with --force)
        prepare_output(job.out, force=args.force, inputs=[job.bag, args.model], kind="bag")
    task = functools.partial(
        _denoise_task,
        model=model,
        channels=args.channels,
        output=args.output,
        oversubtraction=args.oversubtraction,
        floor=args.floor,
        compress=args.compress,
    )
    results = run_bags(
        task, jobs, jobs=args.jobs, scheduler=args.scheduler, desc="denoise", quiet=args.quiet
    )
    return report_results(results, _describe_denoise, single=len(jobs) == 1)


def report_results(results, describe, *, single: bool) -> int:
    """Single bag: its line, or its one-line error (exit 2). Several: the summary."""
    if single:
        r = results[0]
        if not r.ok:
            raise BagError(r.error.splitlines()[0]) if r.error else BagError(f"{r.bag}: failed")
        print(describe(r.value), file=sys.stderr)
        print(f"wrote {r.out}", file=sys.stderr)
        return 0
    for line in summary_lines(results, describe):
        print(line, file=sys.stderr)
    raise_if_bugs(results)  # a bag failed on a bug: an internal error (exit 1), not bad input
    return 0 if all(r.ok for r in results) else 2


# --------------------------------------------------------------------------
# calibrate
# --------------------------------------------------------------------------
def calibrate_bag(
    bag: str | os.PathLike,
    *,
    profile: RobotProfile,
    sweep: str = "auto",
    progress: Callable[[int], None] | None = None,
) -> CalibrationAccumulator:
    """Stream one bag into a CalibrationAccumulator (flushed). Memory: one slice. The
    accumulator's `input_counts` is the line of bad-input counts to print."""
    where = f"{bag}: {profile.sensor_topic}"
    acc = CalibrationAccumulator(profile=profile, sweep=sweep, source=where)
    joint_states = 0
    for piece in iter_recording(
        bag, profile=profile, ground_truth=False, denoised=False, commands=False, progress=progress
    ):
        acc.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
        acc.push_accel(piece.accel_stamps_ns, piece.accel)
        joint_states += len(piece.joint_stamps_ns)
    acc.flush()
    # too many bad samples or unusable joint states: refused; else counted
    acc.input_counts = check_stream(acc.stats, where, joint_states=joint_states)
    return acc


def merge_accumulators(accumulators: Sequence[CalibrationAccumulator]) -> CalibrationAccumulator:
    """Pool the per-cell sums of several bags' accumulators into the first (in the order
    given, so the result does not depend on which bag finished first). Bags are separate
    streams: each was framed and flushed on its own; only the statistics are pooled.

    Both the sweep and the free-motion tally are pooled, so "auto" decides on the pooled data."""
    first = accumulators[0]
    for other in accumulators[1:]:
        first.merge(other)
    return first


def _calibrate_task(bag: Path, out, progress, **options) -> CalibrationAccumulator:
    return calibrate_bag(bag, progress=progress, **options)


def calibrate_bags(
    bags: Sequence[str | os.PathLike],
    *,
    profile: RobotProfile | None = None,
    sweep: str = "auto",
    jobs: int = 1,
    scheduler: str | None = None,
    quiet: bool = True,
):
    """One noise model from one or more bags (bags read in parallel with `jobs` > 1 or a
    Dask `scheduler`). Returns (model, stats, per-bag results); model is None if a bag
    failed (the results say which and why)."""
    profile = profile or load_profile(None)
    pairs = expand_bags(bags)
    task = functools.partial(_calibrate_task, profile=profile, sweep=sweep)
    results = run_bags(
        task,
        [BagJob(bag) for bag, _ in pairs],
        jobs=jobs,
        scheduler=scheduler,
        desc="calibrate",
        quiet=quiet,
    )
    if not all(r.ok for r in results):
        return None, None, results
    per_bag = [
        dict(r.value.stats, input_counts=r.value.input_counts) for r in results
    ]  # before pooling
    acc = merge_accumulators([r.value for r in results])
    for r, stats in zip(results, per_bag):  # what the summary shows per bag
        r.value = stats
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
        model.provenance["source_fingerprint"] = bag_fingerprint(names[0])
    return model, acc.stats, results


def _describe_calibrate(stats: dict) -> str:
    return (
        f"{stats['samples_in']} samples, {stats['blocks']} blocks, {stats['blocks_used']} used "
        f"({stats['mode']}); {stats['input_counts']}"
    )


def coverage_lines(model: NoiseModel) -> list[str]:
    """What `egovib calibrate` prints about the model's coverage."""
    c = model.coverage()
    lines = [
        model.summary(),
        f"coverage: {c['cells_measured']} of {c['cells_total']} cells measured "
        f"({100 * c['fraction_measured']:.1f} %), {c['blocks']} blocks; blocks per measured cell: "
        f"min {c['min_blocks']}, median {c['median_blocks']:g}"
        + (
            f"; {c['cells_under_min_blocks']} cells have too few blocks for a std"
            if c.get("cells_under_min_blocks")
            else ""
        ),
    ]
    if model.measured != "free" and model.dense_ok:
        missing = int(np.sum(model.counts[sweep_mask(model.grid, model.measured)] == 0))
        if missing:
            lines.append(
                f"warning: {missing} cells of the {model.measured} grid have no block; "
                f"they are filled at load time (see NoiseModel)"
            )
    return lines


def run_calibrate(args: argparse.Namespace) -> int:
    prepare_output(args.out, force=args.force, inputs=args.bags, kind="model")  # before any work
    profile = load_profile(args.robot)
    model, stats, results = calibrate_bags(
        args.bags,
        profile=profile,
        sweep=args.grid,
        jobs=args.jobs,
        scheduler=args.scheduler,
        quiet=args.quiet,
    )
    if len(results) > 1 or model is None:
        if len(results) == 1:
            raise BagError(results[0].error)
        for line in summary_lines(results, _describe_calibrate):
            print(line, file=sys.stderr)
        raise_if_bugs(results)
        if model is None:
            print(
                f"egovib: error: no model written: {sum(not r.ok for r in results)} bag(s) failed",
                file=sys.stderr,
            )
            return 2
    where = args.bags[0] if len(args.bags) == 1 else f"{len(results)} bags"
    if model.coverage()["blocks"] == 0:
        raise BagError(
            f"{where}: no steady block near any grid velocity "
            f"(rejected: {stats['rejected']}); is this a calibration sweep or free motion?"
        )
    with atomic_output(args.out) as tmp:
        model.save(tmp)
    for line in coverage_lines(model):
        print(line, file=sys.stderr)
    print(f"rejected blocks: {stats['rejected']}", file=sys.stderr)
    if len(results) == 1:
        print(results[0].value["input_counts"], file=sys.stderr)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0
