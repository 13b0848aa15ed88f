"""Damaged bags (issue #10): ``bev-bag info`` and ``replay`` end cleanly on every one.

A seeded generator (:mod:`bag_damage`) derives a few dozen damaged bags from one small
synthetic drive: byte flips in MCAP chunks and anywhere, truncation at random offsets,
``metadata.yaml`` mutations, wrong message types, invalid stamps, GT grids that do not fit,
wrong-size and undecodable label images, a NaN odometry quaternion, a camera without
CameraInfo, sqlite3 rows with unknown topic ids. For each, in-process through
``bags.cli.main.main``: no exception escapes, a non-zero status comes with an ``error:`` line, a
damaged bag is never replayed as ``complete: true``, and the outputs of the readable frames
are kept. Then one test per defect of the issue's bag-tool part (#4, #5, #6; #8, SIGTERM, is
in ``test_bag_signals.py``).
"""

from __future__ import annotations

import contextlib
import io
import json
import random
from dataclasses import dataclass
from pathlib import Path

import bag_damage as D
import pytest

from bags.cli.main import main
from bags.errors import BagCorruptError
from bags.io import topics as T
from bags.io.metadata import MAX_METADATA_NODES, MetadataError, parse_yaml
from bags.io.reader import BagReader
from bags.replay import BAG_DIR, IMAGE_TOPIC, METRICS_FILE
from bev_mapper_core.geometry.grid import MAX_GRID_CELLS

pytestmark = [pytest.mark.slow]

pytest.importorskip("bev_mapper_core.synth")

VARIANTS = {v.name: v for v in D.variants()}


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> D.Base:
    return D.make_base(tmp_path_factory.mktemp("fuzz"))


def build(base: D.Base, name: str, tmp_path: Path) -> Path:
    return VARIANTS[name].build(base, tmp_path, random.Random(f"{D.SEED}:{name}"))


def cli(*argv: str) -> tuple[int, str, str]:
    """``bev-bag ARGV`` in-process; an exception escaping main fails the test (a traceback)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(argv))
    out, err = out.getvalue(), err.getvalue()
    assert "Traceback" not in out + err
    if rc != 0:
        assert any(line.startswith("error: ") for line in err.splitlines()), err
    return rc, out, err


def replay(bag: Path, out: Path, *extra: str) -> tuple[int, str, str]:
    return cli("replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm",
               "--no-pictures", *extra)


def metrics(out: Path) -> dict | None:
    f = out / METRICS_FILE
    return json.loads(f.read_text()) if f.exists() else None


@dataclass
class Outcome:
    """``bev-bag info`` and ``replay`` of one damaged variant."""

    bag: Path
    info: tuple[int, str, str]
    replay: tuple[int, str, str]
    out: Path
    metrics: dict | None


@pytest.fixture(scope="module")
def fuzz(base, tmp_path_factory):
    """``fuzz(name) -> Outcome``, run once per variant and shared by the tests."""
    done: dict[str, Outcome] = {}

    def run(name: str) -> Outcome:
        if name not in done:
            root = tmp_path_factory.mktemp(name)
            bag = build(base, name, root)
            info = cli("info", str(bag))
            rep = replay(bag, root / "out")
            done[name] = Outcome(bag, info, rep, root / "out", metrics(root / "out"))
        return done[name]
    return run


def frames_before_damage(bag: Path) -> int:
    """Frames a reader yields (label images) before the damage stops it."""
    n = 0
    try:
        with BagReader(bag) as r:
            for _ in r.frames(rgb=False):
                n += 1
    except BagCorruptError:
        pass
    return n


def check_outputs(out: Path, m: dict) -> None:
    """metrics.json agrees with the output bag, and nothing temporary is left."""
    with BagReader(out / BAG_DIR) as r:
        assert r.topics[IMAGE_TOPIC].count == m["frames"]
    assert not [p for p in out.rglob("*partial*")]


# ---------------------------------------------------------------------------- the fuzz
def test_generator_is_seeded(base, tmp_path):
    """Same seed, same damaged bytes; a few dozen variants."""
    assert len(VARIANTS) >= 40
    a = build(base, "flip_any_0", tmp_path / "a")
    b = build(base, "flip_any_0", tmp_path / "b")
    assert (a / "bag.mcap").read_bytes() == (b / "bag.mcap").read_bytes()
    assert (a / "bag.mcap").read_bytes() != base.mcap_file.read_bytes()


@pytest.mark.parametrize("name", list(VARIANTS))
def test_damaged_bag(fuzz, name):
    v, o = VARIANTS[name], fuzz(name)
    assert len(o.info[1]) < 100_000  # an alias bomb is not printed
    if v.kind in ("storage", "metadata", "sqlite"):
        assert o.info[0] == 1
    assert o.replay[0] == 1, "a damaged bag replayed as intact"
    m = o.metrics
    if m is None:  # refused before anything was written
        assert not o.out.exists() or not any(o.out.iterdir())
        return
    assert m["complete"] is False and m["damage"]
    check_outputs(o.out, m)
    if v.kind == "storage":
        assert m["frames"] + m["frames_skipped"] == frames_before_damage(o.bag)
    if v.from_frame is not None:
        assert m["frames"] >= v.from_frame  # the frames before the damage were kept


def test_intact_base_replays_complete(base, tmp_path):
    assert cli("info", str(base.mcap))[0] == 0
    rc, _, _ = replay(base.mcap, tmp_path / "out")
    m = metrics(tmp_path / "out")
    assert rc == 0 and m["complete"] is True and m["damage"] is None
    assert m["frames"] == m["frames_scored"] == D.FRAMES
    assert m["decode_errors"] == m["bad_stamps"] == 0 and m["input_problems"] == {}
    assert m["cameras_without_calibration"] == []


# ------------------------------------------------------------ #4: tracebacks -> error:
@pytest.mark.parametrize("name, topic", [
    ("wrong_type_camera_info", D.INFO), ("wrong_type_tf_static", T.TF_STATIC),
    ("wrong_type_odom", T.ODOM), ("wrong_type_labels", D.LABELS), ("wrong_type_gt", D.GT0)])
def test_wrong_message_type_is_an_error_naming_the_topic(fuzz, name, topic):
    o = fuzz(name)
    for rc, _, err in (o.info, o.replay):
        assert rc == 1 and f"topic {topic} carries" in err
    assert o.metrics is None


def test_metadata_yaml_is_read_safely():
    with pytest.raises(MetadataError, match="not UTF-8"):
        parse_yaml(b"\xff\xfe binary")
    with pytest.raises(MetadataError, match="alias"):
        parse_yaml(D.alias_bomb().encode())
    with pytest.raises(MetadataError, match="recursive"):
        parse_yaml(b"a: &x [1, *x]\n")
    assert parse_yaml(b"a: &x [1, 2]\nb: *x\n") == {"a": [1, 2], "b": [1, 2]}  # plain aliases
    assert 9 ** 6 > MAX_METADATA_NODES > 9 ** 5


@pytest.mark.parametrize("name", ["meta_binary", "meta_list", "meta_alias_bomb_in_custom",
                                  "meta_custom_int", "meta_topic_name_int"])
def test_bad_metadata_yaml_is_reported_and_the_data_kept(fuzz, name):
    o = fuzz(name)
    rc, out, err = o.info
    assert rc == 1 and "metadata.yaml" in err and len(out) < 100_000
    assert o.replay[0] == 1 and "metadata.yaml" in o.metrics["damage"]
    assert o.metrics["frames"] == D.FRAMES


def test_small_alias_bomb_is_not_expanded_by_info(base, tmp_path):
    """9**6 strings: today's info prints ~3.7 MB of them."""
    bag = D._copy(base, tmp_path)
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text().replace(
        "  custom_data:\n", D.alias_bomb(6).split("\n", 1)[1].split("  version")[0]
        + "  custom_data:\n    bomb: *a5\n", 1))
    rc, out, err = cli("info", str(bag))
    assert rc == 1 and len(out) < 100_000 and "alias" in err


def test_negative_stamps_are_counted_not_a_crash(fuzz):
    m = fuzz("negative_stamp_labels").metrics
    assert m["bad_stamps"] == D.FRAMES - D.FROM and m["frames"] == D.FROM
    assert "sec = -1700000000 is outside" in m["input_problems"][D.LABELS]["first"]


def test_huge_gt_grid_is_refused_before_allocation(fuzz):
    o = fuzz("gt_huge_dims")
    assert o.replay[0] == 1 and o.metrics is None
    assert "60000x60000" in o.replay[2] and str(MAX_GRID_CELLS) in o.replay[2]


# ------------------------------------------------ #5: damage mid-bag keeps the outputs
@pytest.mark.parametrize("name, topic", [
    ("odom_nan_quaternion_mid", T.ODOM), ("gt_rotated_mid", D.GT0),
    ("gt_truncated_mid", D.GT0), ("label_wrong_size_mid", D.LABELS)])
def test_damage_mid_bag_keeps_the_outputs(fuzz, name, topic):
    o = fuzz(name)
    m = o.metrics
    assert o.replay[0] == 1 and m is not None and m["complete"] is False and topic in m["damage"]
    assert m["frames"] >= D.FROM and m["decode_errors"] == D.FRAMES - D.FROM
    assert m["input_problems"][topic]["decode_errors"] == D.FRAMES - D.FROM
    check_outputs(o.out, m)


# ----------------------------------------------- #6: damaged bags not replayed as intact
def test_written_mcap_carries_crcs(base, tmp_path):
    """Chunk, data section and summary CRCs, by synth (``BagWriter``) and by replay."""
    chunks, data_crc, summary_crc = D.mcap_crcs(base.mcap_file.read_bytes())
    assert len(chunks) >= 4 and all(chunks) and data_crc and summary_crc
    assert replay(base.mcap, tmp_path / "o")[0] == 0
    chunks, data_crc, summary_crc = D.mcap_crcs(D._mcap(tmp_path / "o" / BAG_DIR).read_bytes())
    assert chunks and all(chunks) and data_crc and summary_crc


def test_byte_flip_in_a_chunk_is_detected(base, tmp_path):
    bag = D._copy(base, tmp_path)
    f = D._mcap(bag)
    data = bytearray(f.read_bytes())
    a, b = D.chunk_data_ranges(bytes(data))[-2]  # a late chunk: earlier frames stay readable
    data[(a + b) // 2] ^= 0x10
    f.write_bytes(bytes(data))
    rc, _, _ = replay(bag, tmp_path / "o")
    m = metrics(tmp_path / "o")
    assert rc == 1 and m["complete"] is False and "checksum" in m["damage"]
    assert 0 < m["frames"] < D.FRAMES


def test_decode_errors_are_counted_in_metrics(fuzz):
    m = fuzz("label_bad_encoding_mid").metrics
    assert m["decode_errors"] == D.FRAMES - D.FROM and m["frames"] == D.FROM
    assert "no-such-encoding" in m["input_problems"][D.LABELS]["first"]


def test_camera_without_camera_info_is_noted(fuzz):
    o = fuzz("camera_without_camera_info")
    assert "side" in o.info[1] and "no camera_info topic" in o.info[1]
    m = o.metrics
    assert o.replay[0] == 1 and m["cameras_without_calibration"] == ["side"]
    assert "side" in m["damage"] and m["frames"] == D.FRAMES and m["complete"] is False


def test_label_nanosec_overflow_counts_bad_stamps(fuzz):
    m = fuzz("nanosec_overflow_labels").metrics
    assert m["bad_stamps"] == D.FRAMES - D.FROM and m["frames"] == D.FROM
    assert "nanosec = 1500000000 is outside" in m["input_problems"][D.LABELS]["first"]


@pytest.mark.parametrize("name", ["sqlite_dangling_gt_ids", "sqlite_dangling_labels_row"])
def test_sqlite_dangling_topic_ids_are_damage(fuzz, name):
    o = fuzz(name)
    assert o.info[0] == 1 and "missing from the topics table" in o.info[2]
    assert o.replay[0] == 1 and o.metrics["complete"] is False
    assert "topic id" in o.metrics["damage"]
