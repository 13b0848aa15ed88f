"""MCAP checksums (bags/mcap_checksums.py): started early in the background by ``bev-bag``, found
once, the same verdict as a check in the foreground, a damaged file still found."""

from __future__ import annotations

import shutil
import threading

from bag_helpers import synth_small

import bags.mcap_checksums as mc
from bags.cli.main import main


def _fresh() -> None:
    mc._mcap_cache.clear()


def test_a_file_is_checked_once_however_many_ask_at_once(tmp_path, monkeypatch):
    bag = synth_small(tmp_path / "drive", frames=2, seed=51)
    (mcap,) = bag.glob("*.mcap")
    _fresh()
    calls = []
    slow = threading.Event()
    real = mc._check_mcap

    def counted(*a):
        calls.append(1)
        slow.wait(0.3)  # the others ask meanwhile
        return real(*a)

    monkeypatch.setattr(mc, "_check_mcap", counted)
    results = []
    threads = [threading.Thread(target=lambda: results.append((mc.check_mcap(mcap), mc.data_crc_verified(mcap))))
               for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and results == [(None, True)] * 4


def test_the_background_check_finds_what_the_foreground_one_finds(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=2, seed=52)
    (mcap,) = bag.glob("*.mcap")
    bad = tmp_path / "bad"
    shutil.copytree(bag, bad)
    (bad_mcap,) = bad.glob("*.mcap")
    data = bytearray(bad_mcap.read_bytes())
    data[len(data) // 3] ^= 0xFF  # one byte in the data section
    bad_mcap.write_bytes(bytes(data))
    _fresh()
    assert mc.check_in_background([tmp_path / "no-such-bag", tmp_path, "--out", str(tmp_path / "x.txt")]) is None
    thread = mc.check_in_background([str(bag), bad_mcap])
    thread.join()
    found = (mc.check_mcap(mcap), mc.check_mcap(bad_mcap))
    _fresh()
    assert (mc.check_mcap(mcap), mc.check_mcap(bad_mcap)) == found
    assert found[0] is None and "data section checksum mismatch" in found[1]
    assert mc.data_crc_verified(mcap) and not mc.data_crc_verified(bad_mcap)


def test_bev_bag_reports_a_damaged_bag_checked_while_it_loads(tmp_path, capsys):
    bag = synth_small(tmp_path / "drive", frames=2, seed=53)
    (mcap,) = bag.glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    data[len(data) // 3] ^= 0xFF
    mcap.write_bytes(bytes(data))
    capsys.readouterr()
    _fresh()
    main(["info", str(bag)])
    out = capsys.readouterr()
    assert "data section checksum mismatch" in out.out + out.err
