"""Issue #28: the data section CRC of a written MCAP file, computed from the chunks' own CRCs
(``crc32_combine``) instead of a second pass over their bytes, is the CRC of the data section."""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np
import pytest
from mcap.reader import make_reader

from bags.io import topics as T
from bags.io.integrity import check_mcap, data_crc_verified
from bags.io.mcap_storage import crc32_combine
from bags.io.writer import BagWriter
from msg_adapters import make_image


@pytest.mark.parametrize("len1,len2", [(0, 0), (0, 1), (5, 0), (3, 7), (100, 4096), (17, 1 << 20), (1, 1234567)])
def test_crc32_combine_is_the_crc_of_the_concatenation(len1, len2):
    a, b = os.urandom(len1), os.urandom(len2)
    assert crc32_combine(zlib.crc32(a), zlib.crc32(b), len2) == zlib.crc32(a + b)
    assert crc32_combine(zlib.crc32(a, 0xDEADBEEF), zlib.crc32(b), len2) == zlib.crc32(a + b, 0xDEADBEEF)


def _data_end_crc(data: bytes) -> tuple[int, int]:
    """The DataEnd record's CRC and where the data section ends (before DataEnd)."""
    summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
    at = summary_start - 13
    assert data[at] == 0x0F and struct.unpack_from("<Q", data, at + 1)[0] == 4
    return struct.unpack_from("<I", data, at + 9)[0], at


@pytest.mark.parametrize("chunk_size,messages", [(4096, 40), (1 << 20, 40), (1 << 20, 0), (64, 3)])
def test_the_data_section_crc_is_that_of_its_bytes(tmp_path, chunk_size, messages):
    rng = np.random.default_rng(chunk_size + messages)
    with BagWriter(tmp_path / "bag", chunk_size=chunk_size) as w:
        w.add_topic("/cameras/a/labels", T.IMAGE_TYPE)
        for i in range(messages):
            img = rng.integers(0, 255, (int(rng.integers(1, 60)), 41)).astype(np.uint8)
            w.write("/cameras/a/labels", make_image(w.factory, img, "mono8", 1_000 + i, "a"), 1_000 + i)
    file = tmp_path / "bag" / "bag.mcap"
    data = file.read_bytes()
    crc, at = _data_end_crc(data)
    assert crc == zlib.crc32(data[:at]) and crc != 0
    assert check_mcap(file) is None and data_crc_verified(file)
    with file.open("rb") as f:
        summary = make_reader(f).get_summary()
    chunks = len(summary.chunk_indexes)
    assert chunks == 0 if messages == 0 else chunks > 1 if chunk_size < 8192 else chunks == 1
