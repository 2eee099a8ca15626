"""Foreign bags: the same messages in the file layouts other writers produce.

Users' bags come from `ros2 bag record`, from converters that write one topic after the
other, from the `mcap` library, with compressed or tiny or huge chunks, from sqlite3
storage, with log times that are receive times (latency) or another clock altogether.
`write_layout(source, out, layout)` rewrites a bag's messages (the same serialized bytes,
topics, types and definitions) in one such layout, so that every command can be checked
to give the same answer whatever the file looks like.

Writers used: rosbags' `Writer` (MCAP and sqlite3), the `mcap` library's `Writer`, and the
project's own `BagWriter`; no layout is produced by hand-made records.
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np
import yaml
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

_NS = 1_000_000_000


@dataclasses.dataclass(frozen=True)
class Layout:
    """How the messages are laid out in the file."""

    name: str
    writer: str = "rosbags"  # rosbags | mcap (the mcap library) | project
    order: str = "time"  # time | topic | rtopic | windows (0.5 s of each topic in turn)
    storage: str = "mcap"  # mcap | sqlite3 (rosbags only)
    compression: str = ""  # "" | zstd | lz4 (chunk compression)
    chunk_bytes: int = 1 << 20
    chunked: bool = True  # mcap library: False writes loose messages
    # stamp | latency (receive times, 0-30 ms late) | offset (+1 h) | writer (a converter's
    # own clock as it writes the file: one topic after the other in log time too) | same
    # (every message at one log time)
    log: str = "stamp"
    swap: float = 0.0  # share of neighbouring sensor samples whose header stamps swap
    velocity: bool = True  # False: JointStates carry positions only (many real drivers)
    files: str = "one"  # one | topic (sensor topics in one file, the others in another)
    joints: str = "one"  # one | per_joint (a JointState per joint, all with one stamp)
    # bytes after every message: rclpy's serialize_message leaves 8 stray ones after some
    # JointStates (positions only), and bags written with it (rosbag2_py) keep them
    trailing: int = 0
    # sample: header stamps mark sample times | receipt: a USB driver's, stamped as each
    # message is read (1 ms frames, 0-0.2 ms host latency)
    stamps: str = "sample"


LAYOUTS = (
    Layout("rosbags_time", compression="zstd"),
    Layout("rosbags_topic", order="topic"),
    Layout("rosbags_rtopic", order="rtopic", compression="zstd"),
    Layout("mcap_time_zstd", writer="mcap", compression="zstd"),
    Layout("mcap_topic_lz4", writer="mcap", order="topic", compression="lz4"),
    Layout("mcap_windows", writer="mcap", order="windows", chunk_bytes=64 << 10),
    Layout("mcap_tiny_chunks", writer="mcap", chunk_bytes=8192),
    Layout("mcap_one_huge_chunk", writer="mcap", order="topic", chunk_bytes=1 << 30),
    Layout("mcap_unchunked", writer="mcap", chunked=False),
    Layout("sqlite3_time", storage="sqlite3"),
    Layout("sqlite3_topic", storage="sqlite3", order="topic"),
    Layout("receive_time_logs", log="latency"),
    Layout("wall_clock_logs", log="offset", order="topic"),
    Layout("swapped_stamps", swap=0.01),
    Layout("project_topic_zstd", writer="project", order="topic", compression="zstd"),
    Layout("joint_state_per_joint", joints="per_joint", compression="zstd"),
    Layout("converter_clock_logs", order="topic", log="writer"),
    Layout("converter_clock_logs_reversed", order="rtopic", log="writer"),
    Layout("topics_in_two_files", files="topic"),
    Layout("sqlite3_topics_in_two_files", storage="sqlite3", files="topic", order="rtopic"),
    Layout("trailing_bytes", trailing=8),
)


@dataclasses.dataclass
class Connection:
    topic: str
    msgtype: str
    msgdef: str
    msgdef_format: str
    rihs01: str
    qos: list


def read_messages(bag: Path) -> tuple[list[Connection], list[tuple[str, int, bytes]]]:
    """The bag's connections and every message as (topic, log time, bytes), in log-time order."""
    with Reader(bag) as reader:
        conns, seen = [], set()
        for c in reader.connections:
            if c.topic in seen:
                continue
            seen.add(c.topic)
            conns.append(
                Connection(
                    c.topic,
                    c.msgtype,
                    c.msgdef.data,
                    "ros2idl" if c.msgdef.format.name == "IDL" else "ros2msg",
                    c.digest,
                    list(getattr(c.ext, "offered_qos_profiles", []) or []),
                )
            )
        messages = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]
    return conns, messages


def header_stamp(data: bytes) -> int | None:
    """The std_msgs/Header stamp of a CDR message that starts with one (Imu, JointState)."""
    if len(data) < 12:
        return None
    sec, nsec = struct.unpack_from("<iI", data, 4)
    return sec * _NS + nsec


def _with_stamp(data: bytes, stamp: int) -> bytes:
    sec, nsec = divmod(stamp, _NS)
    return data[:4] + struct.pack("<iI", sec, nsec) + data[12:]


def _without_velocity(data: bytes) -> bytes:
    from egovib_ros.bag.codec import JOINT_STATE_TYPE, typestore

    msg = typestore().deserialize_cdr(data, JOINT_STATE_TYPE)
    msg.velocity = np.zeros(0, np.float64)
    return bytes(typestore().serialize_cdr(msg, JOINT_STATE_TYPE))


def _per_joint(data: bytes) -> list[bytes]:
    """One JointState per joint, each with the message's stamp (per-joint drivers)."""
    from egovib_ros.bag.codec import JOINT_STATE_TYPE, typestore

    store = typestore()
    msg = store.deserialize_cdr(data, JOINT_STATE_TYPE)
    out = []
    for k, name in enumerate(msg.name):
        part = dataclasses.replace(
            msg,
            name=[name],
            position=msg.position[k : k + 1],
            velocity=msg.velocity[k : k + 1] if len(msg.velocity) else msg.velocity,
            effort=msg.effort[k : k + 1] if len(msg.effort) else msg.effort,
        )
        out.append(bytes(store.serialize_cdr(part, JOINT_STATE_TYPE)))
    return out


def arrange(  # noqa: C901 (one branch per layout option)
    conns: list[Connection], messages: list, layout: Layout, *, seed: int = 5
) -> list[tuple[str, int, bytes]]:
    """The messages with the layout's log times, stamps and file order."""
    rng = np.random.default_rng(seed)
    joint_topics = {c.topic for c in conns if c.msgtype == "sensor_msgs/msg/JointState"}
    stamped = {
        c.topic for c in conns if c.msgtype in ("sensor_msgs/msg/Imu", "sensor_msgs/msg/JointState")
    }
    out = list(messages)
    if not layout.velocity:
        out = [
            (t, log, _without_velocity(d)) if t in joint_topics else (t, log, d)
            for t, log, d in out
        ]
    if layout.joints == "per_joint":
        out = [
            (t, log, part)
            for t, log, d in out
            for part in (_per_joint(d) if t in joint_topics else [d])
        ]
    if layout.stamps == "receipt":
        imu = {c.topic for c in conns if c.msgtype == "sensor_msgs/msg/Imu"}
        # the raw stream and its ground truth share stamps: restamp them alike
        sample = np.unique([header_stamp(d) for t, _, d in out if t in imu])
        frame_end = (sample // 1_000_000 + 1) * 1_000_000
        late = frame_end + rng.integers(0, 200_000, len(sample))
        receipt = dict(
            zip(sample.tolist(), (np.maximum.accumulate(late) + np.arange(len(sample))).tolist())
        )
        out = [
            (t, log, _with_stamp(d, receipt[header_stamp(d)]) if t in imu else d)
            for t, log, d in out
        ]
    if layout.swap:
        # Swap the header stamps of the same neighbouring samples on every Imu topic (the
        # raw stream and its ground truth share stamps).
        imu = [c.topic for c in conns if c.msgtype == "sensor_msgs/msg/Imu"]
        positions = {t: [i for i, m in enumerate(out) if m[0] == t] for t in imu}
        n = min(len(p) for p in positions.values())
        pick = rng.choice(n - 1, max(1, int(layout.swap * n)), replace=False)
        for topic in imu:
            pos = positions[topic]
            for k in pick:
                i, j = pos[k], pos[k + 1]
                si, sj = header_stamp(out[i][2]), header_stamp(out[j][2])
                out[i] = (out[i][0], out[i][1], _with_stamp(out[i][2], sj))
                out[j] = (out[j][0], out[j][1], _with_stamp(out[j][2], si))
    if layout.log not in ("stamp", "writer", "same"):
        relogged = []
        for topic, log_time, data in out:
            stamp = header_stamp(data) if topic in stamped else None
            base = stamp if stamp is not None else log_time
            if layout.log == "latency":
                base += int(rng.uniform(0.0, 0.03) * _NS)
            else:
                base += 3600 * _NS
            relogged.append((topic, base, data))
        out = relogged
    rank = {c.topic: k for k, c in enumerate(conns)}
    if layout.order == "time":
        out.sort(key=lambda m: m[1])
    elif layout.order in ("topic", "rtopic"):
        sign = 1 if layout.order == "topic" else -1
        out.sort(key=lambda m: (sign * rank[m[0]], m[1]))
    elif layout.order == "windows":
        out.sort(key=lambda m: (m[1] // (_NS // 2), rank[m[0]], m[1]))
    else:
        raise ValueError(layout.order)
    if layout.log == "same":  # every message at one log time (a converter's constant)
        out = [(t, 1_800_000_000 * _NS, d) for t, _, d in out]
    if layout.log == "writer":  # 10 us per message written, on the day of the conversion
        out = [(t, 1_800_000_000 * _NS + 10_000 * k, d) for k, (t, _, d) in enumerate(out)]
    if layout.trailing:
        stray = bytes([0x97, 0x7F, 0, 0, 0x70, 0x5B, 0x60, 0x0D] * layout.trailing)[
            : layout.trailing
        ]
        out = [(t, log, d + stray) for t, log, d in out]
    return out


def write_layout(source: Path, out: Path, layout: Layout, *, read=None) -> Path:
    """Rewrite the bag `source` into the bag directory `out` in `layout` (`read`: what
    read_messages(source) returned, when several layouts are written from one source)."""
    conns, messages = read if read is not None else read_messages(source)
    messages = arrange(conns, messages, layout)
    if layout.files == "topic":
        _write_rosbags_per_topic(out, conns, messages, layout)
    elif layout.writer == "rosbags":
        _write_rosbags(out, conns, messages, layout)
    elif layout.writer == "mcap":
        _write_mcap_library(out, conns, messages, layout)
    elif layout.writer == "project":
        _write_project(out, conns, messages, layout)
    else:
        raise ValueError(layout.writer)
    return out


def _write_rosbags(out: Path, conns, messages, layout: Layout) -> None:
    plugin = StoragePlugin.MCAP if layout.storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(out, version=9, storage_plugin=plugin)
    if layout.compression == "zstd" and layout.storage == "mcap":
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        ids = {
            c.topic: writer.add_connection(
                c.topic, c.msgtype, msgdef=c.msgdef, rihs01=c.rihs01, offered_qos_profiles=c.qos
            )
            for c in conns
        }
        for topic, log_time, data in messages:
            writer.write(ids[topic], log_time, data)


def _write_rosbags_per_topic(out: Path, conns, messages, layout: Layout) -> None:
    """Two storage files in one bag: the Imu topics in the first, the others in the second
    (a recorder per topic group, merged into one bag directory), each spanning the whole
    recording; metadata.yaml lists both."""
    groups = [
        [c for c in conns if c.msgtype == "sensor_msgs/msg/Imu"],
        [c for c in conns if c.msgtype != "sensor_msgs/msg/Imu"],
    ]
    out.mkdir(parents=True)
    infos, names = [], []
    for k, group in enumerate(groups):
        topics = {c.topic for c in group}
        part = out.parent / f".{out.name}_part{k}"
        _write_rosbags(part, group, [m for m in messages if m[0] in topics], layout)
        info = yaml.safe_load((part / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        (name,) = info["relative_file_paths"]
        names.append(f"{out.name}_{k}{Path(name).suffix}")
        (part / name).rename(out / names[-1])
        infos.append(info)
        for leftover in part.iterdir():
            leftover.unlink()
        part.rmdir()
    start = min(i["starting_time"]["nanoseconds_since_epoch"] for i in infos)
    end = max(
        i["starting_time"]["nanoseconds_since_epoch"] + i["duration"]["nanoseconds"] for i in infos
    )
    info = dict(infos[0])
    info.update(
        relative_file_paths=names,
        files=[dict(i["files"][0], path=n) for i, n in zip(infos, names)],
        topics_with_message_count=[e for i in infos for e in i["topics_with_message_count"]],
        message_count=sum(i["message_count"] for i in infos),
        starting_time={"nanoseconds_since_epoch": start},
        duration={"nanoseconds": end - start},
    )
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
    (out / "metadata.yaml").write_text(text)


def _write_mcap_library(out: Path, conns, messages, layout: Layout) -> None:
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    out.mkdir(parents=True)
    name = f"{out.name}.mcap"
    compression = {
        "": CompressionType.NONE,
        "zstd": CompressionType.ZSTD,
        "lz4": CompressionType.LZ4,
    }[layout.compression]
    counts = {c.topic: 0 for c in conns}
    with open(out / name, "wb") as fh:
        writer = McapWriter(
            fh,
            chunk_size=layout.chunk_bytes,
            compression=compression,
            use_chunking=layout.chunked,
        )
        writer.start(profile="ros2", library="mcap (egovib conformance corpus)")
        channel = {}
        for c in conns:
            schema = writer.register_schema(c.msgtype, c.msgdef_format, c.msgdef.encode())
            channel[c.topic] = writer.register_channel(
                c.topic, "cdr", schema, {"offered_qos_profiles": yaml.safe_dump(c.qos).strip()}
            )
        for sequence, (topic, log_time, data) in enumerate(messages):
            writer.add_message(channel[topic], log_time, data, log_time, sequence)
            counts[topic] += 1
        writer.finish()
    times = [m[1] for m in messages]
    start, duration = min(times), max(times) - min(times)
    info = {
        "version": 9,
        "storage_identifier": "mcap",
        "relative_file_paths": [name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": len(messages),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": c.topic,
                    "type": c.msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": c.qos,
                    "type_description_hash": c.rihs01,
                },
                "message_count": counts[c.topic],
            }
            for c in conns
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [
            {
                "path": name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": len(messages),
            }
        ],
        "custom_data": None,
        "ros_distro": "jazzy",
    }
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
    (out / "metadata.yaml").write_text(text)


def _write_project(out: Path, conns, messages, layout: Layout) -> None:
    from egovib_ros.bag import BagWriter

    with BagWriter(out, compress=layout.compression or False, chunk_bytes=layout.chunk_bytes) as w:
        for c in conns:
            w.add_topic(
                c.topic,
                c.msgtype,
                msgdef=c.msgdef,
                msgdef_format=c.msgdef_format,
                type_hash=c.rihs01 or None,
                offered_qos_profiles=c.qos,
            )
        run: list = []  # consecutive messages of one topic, written together
        for message in [*messages, None]:
            if run and (message is None or message[0] != run[0][0]):
                w.write_batch(run[0][0], [m[1] for m in run], [m[2] for m in run])
                run = []
            if message is not None:
                run.append(message)
