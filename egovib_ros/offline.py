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
from egovib_ros.bag.many import BagJob, expand_bags, raise_if_bugs, run_bags, summary_lines
from egovib_ros.bag.mcapfile import MESSAGE_HEADER, message_records, rows
from egovib_ros.bag.messages import decode_imu, imu_layout, replace_imu_field
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
    """Pairs denoiser output with the raw messages it replaces and releases the output
    bag's content in input order: each input unit (an MCAP chunk copied verbatim, or a
    batch of messages per topic) followed by the denoised messages of its raw samples,
    once every one of those samples is final.

    A denoised message is its raw message with the field replaced, built straight into
    MCAP message records: one copy of the raw bytes out of the input chunk, then the 24
    bytes of the field. Raw samples the denoiser drops (out of order, bad) have no
    denoised message; they are counted."""

    def __init__(
        self,
        writer: BagWriter,
        raw_topic: str,
        denoised_topic: str,
        field: str,
        copy_topics: set[str],
    ):
        self.writer = writer
        self.raw_topic, self.denoised_topic, self.field = raw_topic, denoised_topic, field
        self.channel_id = writer.topics[denoised_topic].channel_id
        self.copy_topics = copy_topics
        self.units: list[
            tuple[object, int]
        ] = []  # (ReadBatch, global index past its last raw message)
        self.raw_read = 0  # raw messages read so far
        self.resolved = 0  # raw messages before this are matched or dropped
        self.pending: list[
            tuple[MessageBatch, int, int | None]
        ] = []  # (raw batch, global start, field offset)
        self.pending_stamps = np.zeros(0, np.int64)  # stamps of raw messages from `resolved` on
        self.out: list[
            tuple[np.ndarray, np.ndarray, object]
        ] = []  # (global index, log times, records|batch)
        self.written = 0
        self.dropped = 0
        self.verbatim_chunks = 0
        self.copied_chunks = 0

    def add_input(self, batch, raw_stamps: np.ndarray | None) -> None:
        raw = batch.messages.get(self.raw_topic)
        if raw is not None and len(raw):
            stamps = raw_stamps if raw_stamps is not None else decode_imu(raw, self.field)[0]
            self.pending.append((raw, self.raw_read, imu_layout(raw, self.field)))
            self.pending_stamps = np.concatenate([self.pending_stamps, stamps])
            self.raw_read += len(raw)
        self.units.append((batch, self.raw_read))

    def add_output(self, stamps: np.ndarray, values: np.ndarray) -> None:
        if len(stamps) == 0:
            return
        if values.shape[1] == 1:  # CONTRACT: combined signal in x, y = z = 0
            values = np.concatenate([values, np.zeros((len(values), 2))], axis=1)
        index = self.resolved + self._match(stamps)
        self.out.append((index,) + self._denoised(index, values))
        done = int(index[-1]) + 1
        self.dropped += done - self.resolved - len(index)
        self.pending_stamps = self.pending_stamps[done - self.resolved :]
        self.resolved = done
        self.pending = [p for p in self.pending if p[1] + len(p[0]) > done]
        self._emit()

    def finish(self) -> None:
        self.dropped += self.raw_read - self.resolved
        self.resolved = self.raw_read
        self.pending, self.pending_stamps = [], np.zeros(0, np.int64)
        self._emit()

    def _denoised(self, index: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, object]:
        """(log times, MCAP records or a MessageBatch) of the raw messages at global `index`
        with the field set to `values`."""
        parts = []
        for raw, first, offset in self.pending:
            lo, hi = np.searchsorted(index, [first, first + len(raw)])
            if hi > lo:
                parts.append((raw, index[lo:hi] - first, offset))
        widths = {raw.uniform_length for raw, _, _ in parts}
        offsets = {offset for _, _, offset in parts}
        log_times = np.concatenate([raw.log_times[local] for raw, local, _ in parts])
        if len(widths) != 1 or None in widths or len(offsets) != 1 or None in offsets:
            # unusual messages: the codec's general path
            messages = MessageBatch.concat([raw.take(local) for raw, local, _ in parts])
            return log_times, replace_imu_field(messages, values, self.field)
        width, offset = widths.pop(), offsets.pop()
        records = message_records(self.channel_id, log_times, None, width)
        row = 0
        for raw, local, _ in parts:
            records[row : row + len(local), MESSAGE_HEADER:] = rows(
                raw.buf, raw.starts[local], width
            )
            row += len(local)
        at = MESSAGE_HEADER + offset
        records[:, at : at + 24] = values.astype("<f8").view(np.uint8).reshape(-1, 24)
        return log_times, records

    def _match(self, stamps: np.ndarray) -> np.ndarray:
        """Positions (from `resolved`) of the raw messages of these output stamps (in order)."""
        n, known = len(stamps), self.pending_stamps
        if n <= len(known) and np.array_equal(known[:n], stamps):
            return np.arange(n)
        index = np.empty(n, np.int64)  # some raw samples were dropped: walk (rare)
        j = 0
        for k, stamp in enumerate(stamps.tolist()):
            while j < len(known) and known[j] != stamp:
                j += 1
            if j == len(known):
                raise RuntimeError(f"denoised sample stamped {stamp} has no raw message")
            index[k] = j
            j += 1
        return index

    def _emit(self) -> None:
        while self.units and self.units[0][1] <= self.resolved:
            batch, raw_end = self.units.pop(0)
            self._copy(batch)
            while self.out and self.out[0][0][0] < raw_end:
                index, log_times, data = self.out[0]
                k = int(np.searchsorted(index, raw_end))
                if isinstance(data, MessageBatch):
                    self.writer.write_batch(
                        self.denoised_topic, log_times[:k], data.take(np.arange(k))
                    )
                    rest = data.take(np.arange(k, len(index)))
                else:
                    self.writer.write_message_records(self.denoised_topic, log_times[:k], data[:k])
                    rest = data[k:]
                self.written += k
                if k < len(index):
                    self.out[0] = (index[k:], log_times[k:], rest)
                else:
                    self.out.pop(0)

    def _copy(self, batch) -> None:
        chunk = batch.chunk
        if chunk is not None:
            other = {c for c, t in batch.topic_of_channel.items() if t not in self.copy_topics}
            if other:
                chunk = chunk.without(other)
            if self.writer.write_chunk(chunk, batch.scanner.schemas, batch.scanner.channels):
                self.verbatim_chunks += 1
                return
        self.copied_chunks += 1
        for topic, messages in batch.messages.items():
            if topic in self.copy_topics and len(messages):
                self.writer.write_batch(topic, messages.log_times, messages)


def denoise_bag(
    bag: str | os.PathLike,
    out: str | os.PathLike,
    *,
    model: NoiseModel | str | os.PathLike,
    channels: str = "per_axis",
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
            oversubtraction=oversubtraction,
            floor=floor,
            source=f"{bag}: {raw_topic}",
        )
        with atomic_output(out, directory=True, kind="bag") as tmp:
            with BagWriter(tmp, compress=compress) as writer:
                for topic in copy_topics:
                    writer.copy_topic(reader, topic)
                writer.copy_topic(reader, raw_topic, as_topic=denoised_topic)
                job = _DenoisedTopic(
                    writer, raw_topic, denoised_topic, profile.sensor_field, set(copy_topics)
                )

                def push(pieces) -> None:
                    for piece in pieces:
                        for chunk in (
                            denoiser.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity),
                            denoiser.push_accel(piece.accel_stamps_ns, piece.accel),
                        ):
                            job.add_output(chunk.stamps_ns, chunk.values)

                for batch in reader.batches(copy_topics):
                    pieces = stream.add(batch)
                    job.add_input(batch, stream.decoded.get("raw", (None,))[0])
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
        "chunks_copied_verbatim": job.verbatim_chunks,
        "chunks_rewritten": job.copied_chunks,
        "size_ratio": ratio,
        "compression": compression_name(compress) or "none",
        "input_counts": counts,
    }


def _describe_denoise(figures: dict) -> str:
    text = (
        f"{figures['denoised_messages']} samples denoised ({figures['channels']}); "
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
        model, channels=args.channels, oversubtraction=args.oversubtraction, floor=args.floor
    )
    jobs = output_jobs(args.bags, args.out)
    for job in jobs:  # before any work: every output may be written (or replaced with --force)
        prepare_output(job.out, force=args.force, inputs=[job.bag, args.model], kind="bag")
    task = functools.partial(
        _denoise_task,
        model=model,
        channels=args.channels,
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
    names = [str(b) for b, _ in pairs]
    source = (
        names[0]
        if len(names) == 1
        else f"{len(names)} bags: " + ", ".join(names[:20]) + (", ..." if len(names) > 20 else "")
    )
    return acc.to_model(source=source), acc.stats, results


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
