"""Messages read through an MCAP file's indexes are rosbags' messages, in rosbags' order, with
the chunk CRCs checked wherever the data section's CRC was not."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2.storage_mcap import ReaderError

from bags.io import topics as T
from bags.io.integrity import check_mcap, data_crc_verified
from bags.io.raw import IndexedMcap
from bags.io.reader import BagReader
from bags.io.writer import BagWriter
from msg_adapters import make_image

TOPICS = ["/cameras/a/labels", "/cameras/b/labels", "/cameras/a/image_raw"]


def _bag(path, chunk_size=4096):
    """Messages of three topics in chunks of ``chunk_size`` bytes, log times out of order and tied."""
    rng = np.random.default_rng(3)
    with BagWriter(path, chunk_size=chunk_size) as w:
        for t in TOPICS:
            w.add_topic(t, T.IMAGE_TYPE)
        for i in range(60):
            topic = TOPICS[int(rng.integers(3))]
            log = 1_000 + int(rng.integers(0, 25)) * 10  # many ties, no order
            img = rng.integers(0, 255, (int(rng.integers(1, 40)), 33)).astype(np.uint8)
            w.write(topic, make_image(w.factory, img, "mono8", log, f"f{i}"), log)
    return path


def _rosbags(path, topics):
    with AnyReader([path]) as r:
        conns = [c for c in r.connections if c.topic in topics]
        return [(c.topic, t, bytes(raw)) for c, t, raw in r.messages(connections=conns)]


@pytest.mark.parametrize("verified", [True, False])
def test_messages_are_rosbags_messages_in_rosbags_order(tmp_path, verified):
    bag = _bag(tmp_path / "bag")
    file = next(bag.glob("*.mcap"))
    assert check_mcap(file) is None and data_crc_verified(file)
    ix = IndexedMcap.open(file, verified)
    try:
        for topics in (set(TOPICS), {TOPICS[0]}, {TOPICS[1], TOPICS[2]}):
            got = list(ix.messages(topics))
            assert got == _rosbags(bag, topics)
            assert len(got) > 10
        assert list(ix.messages({"/nothing"})) == []
    finally:
        ix.close()


def test_a_damaged_chunk_is_refused_when_its_crc_is_checked(tmp_path):
    bag = _bag(tmp_path / "bag")
    file = next(bag.glob("*.mcap"))
    data = bytearray(file.read_bytes())
    at = data.index(b"f30\x00")  # a frame id inside some chunk's records
    data[at + 1] ^= 0x01
    file.write_bytes(bytes(data))
    assert check_mcap(file) is not None and not data_crc_verified(file)  # BagReader streams it then
    ix = IndexedMcap.open(file, verified=False)
    try:
        with pytest.raises(ReaderError, match="checksum"):
            list(ix.messages(set(TOPICS)))
    finally:
        ix.close()


def test_the_reader_reads_through_the_indexes_or_leaves_the_file_to_rosbags(tmp_path):
    bag = _bag(tmp_path / "bag")
    with BagReader(bag) as r:
        assert r._src._indexed is not None
        got = [(m.topic, m.log_ns, m.msg) for m in r.messages(raw=True)]
    assert got == _rosbags(bag, set(TOPICS))
    assert IndexedMcap.open(bag / "metadata.yaml", verified=True) is None  # not an MCAP file


@pytest.mark.parametrize("verified", [True, False])
def test_views_are_the_same_bytes_and_outlive_the_reader(tmp_path, verified):
    bag = _bag(tmp_path / "bag")
    file = next(bag.glob("*.mcap"))
    ix = IndexedMcap.open(file, verified)
    try:
        got = list(ix.messages(set(TOPICS), views=True))
        assert all(isinstance(raw, memoryview) and raw.readonly for _, _, raw in got)
        assert [(t, ns, bytes(raw)) for t, ns, raw in got] == _rosbags(bag, set(TOPICS))
    finally:
        ix.close()  # views still alive: the map is released with them, not under them
    assert [(t, ns, bytes(raw)) for t, ns, raw in got] == _rosbags(bag, set(TOPICS))


def test_fast_frames_read_views_and_the_same_messages(tmp_path):
    bag = _bag(tmp_path / "bag")
    with BagReader(bag) as r:
        fast = [(m.topic, m.log_ns, m.msg) for m in r.messages(fast=True)]
        slow = [(m.topic, m.log_ns, m.msg) for m in r.messages()]
    assert len(fast) == len(slow) > 10
    for (ft, fl, f), (st, sl, s) in zip(fast, slow):
        assert (ft, fl, f.header.frame_id, f.encoding, f.height, f.width, f.step) == (
            st, sl, s.header.frame_id, s.encoding, s.height, s.width, s.step)
        assert np.array_equal(f.data, s.data) and not f.data.flags.writeable
