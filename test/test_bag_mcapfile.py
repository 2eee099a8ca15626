"""egovib_ros.bag.mcapfile: MCAP chunks scanned and edited with numpy."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import random_recording

from egovib_ros.bag import BagReader, encode_imu_batch, read_recording, write_recording
from egovib_ros.errors import BagError
from egovib_ros.sim.pr2 import BAG_TOPICS


def test_chunk_without_channels(tmp_path):
    rec = random_recording(seconds=0.5)
    write_recording(tmp_path / "bag", rec)
    with BagReader(tmp_path / "bag") as reader:
        batch = next(iter(reader.batches()))
        drop = {c for c, t in batch.topic_of_channel.items() if t == BAG_TOPICS["contact"]}
        chunk = batch.chunks[0]
        kept = chunk.without(drop)
    assert set(kept.index) == set(chunk.index) - drop
    for channel, (times, offsets) in kept.index.items():
        np.testing.assert_array_equal(times, chunk.index[channel][0])
        old_times, old_starts, lengths = chunk.data_span(channel)
        _, new_starts, new_lengths = kept.data_span(channel)
        np.testing.assert_array_equal(lengths, new_lengths)
        for a, b, n in zip(old_starts[:5], new_starts[:5], lengths[:5]):
            assert chunk.records[a : a + n] == kept.records[b : b + n]


@pytest.mark.parametrize("crc", [True, False])
def test_damaged_records_are_detected(tmp_path, crc):
    """A flipped byte inside a chunk: refused by the chunk CRC; without CRCs, a message record
    whose opcode was damaged is missing from the count the bag's index gives."""
    rec = random_recording(seconds=2.0)
    write_recording(tmp_path / "bag", rec, crc=crc)
    mcap = next((tmp_path / "bag").glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    at = data.find(encode_imu_batch(rec.sensor_stamps_ns[4000:4001], rec.sensor[4000:4001])[0])
    assert at > 31 and data[at - 31] == 0x05
    data[at - 31] = 0xFA  # no longer a message record
    mcap.write_bytes(bytes(data))
    expected = "CRC mismatch" if crc else "lost to damaged records|do not match|index lists"
    with pytest.raises(BagError, match=f"bag.*({expected})") as info:
        read_recording(tmp_path / "bag")
    assert "\n" not in str(info.value)
