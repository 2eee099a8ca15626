"""`egovib denoise` as a library: the core's denoiser run on a recorded bag.

The bag is streamed (memory does not grow with the recording): input MCAP chunks are
copied verbatim (no topic decoded but the sensor and joint topics) and the profile's
denoised topic is added, one message per valid raw sample: the raw message with the
cleaned field, every other byte kept. The core is the denoiser node's: live and offline
results agree.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Callable

import numpy as np

from egovib_ros.bag.codec import MessageBatch, imu_layout, replace_imu_field
from egovib_ros.bag.mcapfile import MESSAGE_HEADER, message_records, rows
from egovib_ros.bag.reader import BagReader
from egovib_ros.bag.recording import RecordingStream
from egovib_ros.bag.writer import BagWriter, compression_name
from egovib_ros.core import NoiseModel
from egovib_ros.core.held import output_rows
from egovib_ros.core.methods import make_denoiser, resolve_method
from egovib_ros.core.stream import check_stream, has_bad_input
from egovib_ros.errors import BagError
from egovib_ros.outputs import atomic_output

LOG = logging.getLogger("egovib_ros.bag")
#: Above this share of the output without a joint state near it, the run warns (--quiet
#: too): a stream's first sample or block has none; a joint-state topic that stops early
#: (a truncated recording) leaves the rest of the bag not denoised.
NO_JOINT_STATE_WARN = 0.01


class _DenoisedTopic:
    """Writes the profile's denoised topic: for every sample the denoiser outputs, the raw
    message of that header stamp with its field replaced, at the raw message's log time.

    Raw messages are held by stamp, not by their place in the file (a bag may hold them in
    any order; the denoiser gets its samples in stamp order). Output stamps increase
    strictly: each is found by a binary search among the held stamps
    (core.held.output_rows); a held message the output passed without taking it (out of
    order, a bad sample, a stamp repeated) gets no denoised message and is counted.
    Memory: the raw messages not answered yet (a block plus the stream's look-ahead)."""

    def __init__(self, writer: BagWriter, denoised_topic: str, field: str):
        self.writer = writer
        self.denoised_topic, self.field = denoised_topic, field
        self.channel_id = writer.topics[denoised_topic].channel_id
        self._batches: dict[int, tuple[MessageBatch, int | None]] = {}  # id -> (raw, field offset)
        self._next_id = 0
        # the held raw messages, sorted by stamp (ties in the order read), a row each:
        # stamp, batch id, row in the batch
        self._held = np.zeros((0, 3), np.int64)
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
            len(self._held) == 0 or stamps[0] >= self._held[-1, 0]
        )
        added = np.stack([stamps, np.full(len(stamps), ident, np.int64), rows_], axis=1)
        self._held = np.concatenate([self._held, added])
        if not in_order:
            self._held = self._held[np.argsort(self._held[:, 0], kind="stable")]

    def add_output(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """Write the denoised messages of these output samples (stamps strictly increasing)."""
        if len(stamps) == 0:
            return
        values = np.asarray(values, np.float64)
        if values.shape[1] == 1:  # the combined signal goes in x, y = z = 0
            values = np.concatenate([values, np.zeros((len(values), 2))], axis=1)
        at = output_rows(self._held[:, 0], stamps)  # held sorted by stamp, as the denoiser was fed
        batches, rows_ = self._held[at, 1], self._held[at, 2]
        self._write(batches, rows_, values)
        done = int(at[-1]) + 1
        self.dropped += done - len(at)
        self._passed = int(stamps[-1])
        self._held = self._held[done:]
        still = set(np.unique(self._held[:, 1]).tolist())
        for ident in [i for i in self._batches if i not in still]:
            del self._batches[ident]

    def finish(self) -> None:
        """End of the bag: raw messages never answered are counted."""
        self.dropped += len(self._held)
        self._held = self._held[:0]
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
    method: str | None = None,
    compress: bool | str = False,
    replace_denoised: bool = False,
    progress: Callable[[int], None] | None = None,
    save_model: str | os.PathLike | None = None,
    **settings,
) -> dict:
    """Denoise one bag into `out` (written atomically: nothing appears unless complete);
    returns figures (samples, blocks, size ratio, ...). `settings`: the denoiser's
    (core.methods.make_denoiser: channels, output, oversubtraction, floor, joint_lag_s,
    noise_gain_db, adapt: the model goes on learning while no contact is detected).

    A bag that holds the denoised topic already (a recorded live run) is refused (BagError)
    unless `replace_denoised`: then its own is left out of the copy (counted in the
    figures). `save_model`: the model as adapted by the end of the bag is written there
    (atomically, after the bag).

    One function: the reading, the denoising and the writing share one bag's streams, and
    the order of their ends (output closed, then the model saved, then the figures) is the
    atomicity promised above."""
    model = model if isinstance(model, NoiseModel) else NoiseModel.load(model)
    profile = model.robot_profile()
    bag = Path(bag)
    with BagReader(bag) as reader:
        stream = RecordingStream(
            reader, profile, ground_truth=False, denoised=False, commands=False
        )
        raw_topic, denoised_topic = stream.names["raw"], stream.names["denoised"]
        copy_topics = [t for t in reader.topics if t != denoised_topic]
        replaced = reader.topics[denoised_topic].count if denoised_topic in reader.topics else 0
        if denoised_topic in reader.topics and not replace_denoised:
            raise BagError(
                f"{bag}: already holds {denoised_topic} ({replaced} messages: a recorded "
                f"denoiser's output?); not replaced without --replace-denoised"
            )
        method = resolve_method(model, method)
        denoiser = make_denoiser(model, method, source=f"{bag}: {raw_topic}", **settings)
        with (
            atomic_output(out, directory=True, kind="bag") as tmp,
            BagWriter(tmp, compress=compress) as writer,
        ):
            for topic in copy_topics:
                writer.copy_topic(reader, topic)
            writer.copy_topic(reader, raw_topic, as_topic=denoised_topic)
            job = _DenoisedTopic(writer, denoised_topic, profile.sensor_field)
            copied = {"verbatim": 0, "rewritten": 0}  # chunks copied as they were; batches
            joint_rows = [0]  # joint states as the core gets them (split messages joined)

            def push(pieces) -> None:
                for piece in pieces:
                    joint_rows[0] += len(piece.joint_stamps_ns)
                    for chunk in (
                        denoiser.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity),
                        denoiser.push_sensor(piece.sensor_stamps_ns, piece.sensor),
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
                joint_states=joint_rows[0],  # rows, as calibrate, gap, model show
                joints_where=f"{bag}: {stream.names['joint_states']}",
            )
            ratio = writer.size_ratio
            if save_model is not None:  # the bag complete, before it appears: both or neither
                writer.close()  # (closing again on leaving the with is a no-op)
                with atomic_output(save_model) as model_tmp:
                    denoiser.adapted_model().save(model_tmp)
    stats = denoiser.stats
    _warn_without_joint_states(bag, method, stats, job.written)
    adapted = getattr(denoiser, "adaptation_stats", None)
    return {
        "samples_in": job.raw_read,
        "denoised_messages": job.written,
        "raw_without_output": job.dropped,
        "method": method,
        "delay_ms": denoiser.delay_ms,
        # a superposition model fills the cells off its axes by design (Eq. 6): not unmeasured
        "samples_unmeasured": 0
        if model.measured == "superposition"
        else (stats.samples_unmeasured or 0),
        "blocks": stats.blocks or 0,
        "blocks_out_of_grid": stats.blocks_out_of_grid or 0,
        "blocks_no_joint_state": stats.blocks_no_joint_state or 0,
        "blocks_unmeasured": stats.blocks_unmeasured or 0,
        "samples_no_joint_state": stats.samples_no_joint_state or 0,
        "dropped_out_of_order": stats.dropped_out_of_order,
        "channels": denoiser.channels,
        "output": getattr(denoiser, "output", "bandpassed"),
        "chunks_copied_verbatim": copied["verbatim"],
        "batches_rewritten": copied["rewritten"],
        "size_ratio": ratio,
        "compression": compression_name(compress) or "none",
        "input_counts": counts,
        "bad_input": has_bad_input(stats),  # anything counted in input_counts
        "replaced_denoised": replaced,  # messages of the bag's own denoised topic left out
        "adapt": None if adapted is None else adapted.as_dict(),
        "saved_model": None if save_model is None else str(save_model),
    }


def _warn_without_joint_states(bag, method: str, stats, written: int) -> None:
    """A WARNING when more than NO_JOINT_STATE_WARN of the samples had no joint state near
    them (written as read: not denoised). The paper's blocks say it in the core already
    (core.subtraction, at the first such block)."""
    missing = stats.samples_no_joint_state or 0
    if method != "paper" and written and missing > NO_JOINT_STATE_WARN * written:
        LOG.warning(
            "%s: %d of %d samples (%.0f %%) had no joint state near them (the joint states "
            "start later or stop earlier than the sensor, or pause): written without denoising",
            bag,
            missing,
            written,
            100.0 * missing / written,
        )
