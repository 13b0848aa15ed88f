"""bags: write synthetic drives (mcap, sqlite3), read them back, damage handling, the CLI."""

from __future__ import annotations

import itertools
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bags.cli.main import main
from bags.errors import BagCorruptError, BagError, BagExistsError
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import write_drive
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import surround6
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, BEV_CLASSES

try:
    from bev_mapper_core.synth import CameraFrame, SynthConfig, SynthFrame, generate_drive
except ImportError:  # generator not in the tree yet: hand-made frames only
    generate_drive = None

MS = 1_000_000
T0 = 1_700_000_000 * 1_000_000_000
GRID = BevGrid(-12.0, 12.0, -6.0, 6.0, 0.5)  # 48 x 24 cells
GRID_ARGS = ["--grid-x-min", "-12", "--grid-x-max", "12", "--grid-y-min", "-6", "--grid-y-max",
             "6", "--grid-res", "0.5"]
needs_generator = pytest.mark.skipif(generate_drive is None, reason="synth generator absent")


def _frame(**kw):
    if generate_drive is not None:
        kw["cameras"] = {k: CameraFrame(**vars(v)) for k, v in kw["cameras"].items()}
        return SynthFrame(**kw)
    return SimpleNamespace(**kw)


def hand_frames(rig, grid, n, *, jitter_ns=0, drop=None, seed=0):
    """Random frames with the SynthFrame layout; ``drop`` = (frame index, camera) to omit."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        stamp = T0 + i * 100 * MS
        cams = {}
        for c in rig.cameras:
            if drop == (i, c.name):
                continue
            w, h = c.model.image_size
            j = int(rng.integers(-jitter_ns, jitter_ns + 1)) if jitter_ns else 0
            cams[c.name] = SimpleNamespace(
                rgb=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                labels=rng.integers(0, 11, (h, w), dtype=np.uint8),
                stamp_ns=stamp + j,
            )
        pose = np.eye(4)
        pose[:2, 3] = (2.0 * i, 0.1 * i)
        out.append(_frame(
            index=i, stamp_ns=stamp, world_from_ego=pose,
            linear_velocity=np.array([20.0, 0.0, 0.0]), angular_velocity=np.array([0, 0, 0.05]),
            cameras=cams, gt=rng.random((len(BEV_CLASSES),) + grid.shape) > 0.6,
            visibility=rng.random(grid.shape) > 0.25,
        ))
    return out


def assert_frames_match(bag_frames, ref_frames, rig, grid):
    assert len(bag_frames) == len(ref_frames)
    for f, g in zip(bag_frames, ref_frames):
        assert f.stamp_ns == g.stamp_ns
        assert f.valid == {c: c in g.cameras for c in rig.names}
        for name, cf in g.cameras.items():
            np.testing.assert_array_equal(f.rgb[name], cf.rgb)
            np.testing.assert_array_equal(f.labels[name], cf.labels)
            assert f.camera_stamps[name] == cf.stamp_ns
        assert f.gt_classes == BEV_CLASS_NAMES
        assert f.gt.shape == (len(BEV_CLASSES),) + grid.shape
        vis = np.asarray(g.visibility, bool)
        np.testing.assert_array_equal(f.gt_known, np.broadcast_to(vis, f.gt_known.shape))
        np.testing.assert_array_equal(f.gt == 1.0, np.asarray(g.gt, bool) & vis)
        np.testing.assert_array_equal(f.gt == 0.0, ~np.asarray(g.gt, bool) | ~vis)
        np.testing.assert_allclose(f.odom.world_from_ego, g.world_from_ego, atol=1e-9)
        np.testing.assert_allclose(f.odom.linear_velocity, g.linear_velocity)
        np.testing.assert_allclose(f.odom.angular_velocity, g.angular_velocity)
        ground = getattr(g, "ground_visibility", None)
        if ground is None:
            assert f.ground_visibility is None
        else:
            np.testing.assert_array_equal(f.ground_visibility, ground)
        # the full truth: every cell, seen or not; and the visibility it is masked with in gt
        np.testing.assert_array_equal(f.visibility, vis)
        np.testing.assert_array_equal(f.truth, np.asarray(g.gt, np.float32))


def assert_rig_matches(read_rig, rig):
    assert read_rig.names == rig.names
    for a, b in zip(read_rig.cameras, rig.cameras):
        assert a.model == b.model and a.frame_id == b.frame_id
        np.testing.assert_allclose(a.ego_from_cam_array, b.ego_from_cam_array, atol=1e-9)


def assert_layout(reader, rig, n, ground=False):
    topics = reader.topics
    expect = {T.TF_STATIC: (T.TF_TYPE, 1), T.ODOM: (T.ODOM_TYPE, n), T.TF: (T.TF_TYPE, n)}
    if ground:
        expect[T.GROUND_VISIBILITY] = (T.GRID_TYPE, n)
    for c in rig.names:
        expect[T.image_topic(c, "rgb")] = (T.IMAGE_TYPE, n)
        expect[T.image_topic(c, "labels")] = (T.IMAGE_TYPE, n)
        expect[T.camera_info_topic(c)] = (T.CAMERA_INFO_TYPE, n)
    for c in BEV_CLASS_NAMES:
        expect[T.gt_topic(c)] = (T.GRID_TYPE, n)
        expect[T.truth_topic(c)] = (T.GRID_TYPE, n)
    expect[T.ANY_VISIBILITY] = (T.GRID_TYPE, n)
    assert {k: (v.msgtype, v.count) for k, v in topics.items()} == expect
    assert reader.truth_classes == BEV_CLASS_NAMES
    encodings = {}
    for m in reader.messages([T.image_topic(rig.names[0], "rgb"), T.image_topic(rig.names[0],
                                                                                "labels")]):
        encodings[m.topic] = m.msg.encoding
        if m.topic.endswith("image_raw"):
            assert m.msg.header.frame_id == rig.cameras[0].frame_id
    assert set(encodings.values()) == {"rgb8", "mono8"}
    for m in reader.messages([T.gt_topic("drivable")]):
        assert m.msg.header.frame_id == "base_link"
        assert set(np.unique(m.msg.data)) <= {-1, 0, 100}
    for m in reader.messages([T.truth_topic("drivable"), T.ANY_VISIBILITY]):
        assert m.msg.header.frame_id == "base_link"
        assert set(np.unique(m.msg.data)) <= {0, 100}  # never unknown


def _tf_static_qos(path):
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability

    with AnyReader([Path(path)]) as r:
        (conn,) = [c for c in r.connections if c.topic == T.TF_STATIC]
        return [q.durability for q in conn.ext.offered_qos_profiles], QosDurability


# --------------------------------------------------------------- hand-made frames
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_write_read_roundtrip(tmp_path, storage):
    rig = surround6().scaled(0.25)
    frames = hand_frames(rig, GRID, 3)
    out = tmp_path / "bag"
    summary = write_drive(out, rig, GRID, frames, storage=storage)
    assert summary.frames == 3 and (out / "metadata.yaml").exists()
    suffix = ".mcap" if storage == "mcap" else ".db3"
    assert [p.name for p in out.iterdir() if p.suffix == suffix] == ["bag" + suffix]
    assert not list(tmp_path.glob(".*partial*"))
    durabilities, D = _tf_static_qos(out)
    assert durabilities == [D.TRANSIENT_LOCAL]
    with BagReader(out) as r:
        assert r.damage is None
        assert r.latched_topics == {"/tf_static"}  # what `bev-bag play` publishes transient-local
        assert_layout(r, rig, 3)
        assert_rig_matches(r.rig(), rig)
        assert r.grid() == GRID
        got = list(r.frames())
    assert_frames_match(got, frames, rig, GRID)
    for f in got:  # no jitter: equal header stamps across the cameras of a frame
        assert set(f.camera_stamps.values()) == {f.stamp_ns}


def test_plain_mcap_file_and_labels_only(tmp_path):
    rig = surround6().scaled(0.25)
    frames = hand_frames(rig, GRID, 2)
    write_drive(tmp_path / "bag", rig, GRID, frames)
    with BagReader(tmp_path / "bag" / "bag.mcap") as r:
        got = list(r.frames(rgb=False, gt=False, odom=False))
    assert len(got) == 2 and got[0].rgb == {} and got[0].gt is None and got[0].odom is None
    np.testing.assert_array_equal(got[1].labels["back"], frames[1].cameras["back"].labels)


def test_jitter_stamps_and_sync(tmp_path):
    rig = surround6().scaled(0.25)
    frames = hand_frames(rig, GRID, 3, jitter_ns=8 * MS)
    write_drive(tmp_path / "bag", rig, GRID, frames)
    with BagReader(tmp_path / "bag") as r:
        got = list(r.frames())
    assert_frames_match(got, frames, rig, GRID)
    offsets = [s - f.stamp_ns for f in got for s in f.camera_stamps.values()]
    assert max(abs(o) for o in offsets) <= 8 * MS and any(o != 0 for o in offsets)


def test_missing_camera_gives_partial_frame(tmp_path):
    rig = surround6().scaled(0.25)
    frames = hand_frames(rig, GRID, 4, drop=(1, "back_left"))
    write_drive(tmp_path / "bag", rig, GRID, frames)
    with BagReader(tmp_path / "bag") as r:
        got = list(r.frames())
    assert_frames_match(got, frames, rig, GRID)
    assert not got[1].valid["back_left"] and "back_left" not in got[1].rgb
    assert got[1].valid_mask.sum() == 5 and got[1].camera_stamps["back_left"] is None


def test_refuse_overwrite_and_force(tmp_path, capsys):
    rig = surround6().scaled(0.25)
    out = tmp_path / "bag"
    write_drive(out, rig, GRID, hand_frames(rig, GRID, 1))
    with pytest.raises(BagExistsError, match="--force"):
        write_drive(out, rig, GRID, hand_frames(rig, GRID, 2))
    write_drive(out, rig, GRID, hand_frames(rig, GRID, 2), force=True)
    with BagReader(out) as r:
        assert r.topics[T.ODOM].count == 2
    (tmp_path / "notabag").mkdir()
    (tmp_path / "notabag" / "precious.txt").write_text("keep me")
    with pytest.raises(BagExistsError, match="does not look like a bag"):
        write_drive(tmp_path / "notabag", rig, GRID, hand_frames(rig, GRID, 1), force=True)
    assert (tmp_path / "notabag" / "precious.txt").exists()
    # the CLI refuses before generating anything, with a one-line error
    assert main(["synth", str(out), "--frames", "1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "exists" in err and "Traceback" not in err


def test_failed_write_leaves_nothing(tmp_path):
    rig = surround6().scaled(0.25)

    def frames():
        yield from hand_frames(rig, GRID, 1)
        raise RuntimeError("generator crashed")

    with pytest.raises(RuntimeError):
        write_drive(tmp_path / "bag", rig, GRID, frames())
    assert list(tmp_path.iterdir()) == []


def _truncate(src: Path, dst: Path, keep: float) -> int:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * keep)])
    return len(data)


@pytest.mark.parametrize("as_dir", [False, True], ids=["file", "dir"])
def test_truncated_mcap(tmp_path, as_dir):
    rig = surround6().scaled(0.5)  # ~0.5 MB per frame: several 1 MiB mcap chunks
    frames = hand_frames(rig, GRID, 6)
    write_drive(tmp_path / "bag", rig, GRID, frames)
    src = tmp_path / "bag" / "bag.mcap"
    if as_dir:
        damaged = tmp_path / "damaged"
        shutil.copytree(tmp_path / "bag", damaged)
        _truncate(src, damaged / "bag.mcap", 0.7)
    else:
        damaged = tmp_path / "damaged.mcap"
        _truncate(src, damaged, 0.7)
    got = []
    with pytest.raises(BagCorruptError, match="damaged") as info:
        with BagReader(damaged) as r:
            assert r.damage is not None
            assert_rig_matches(r.rig(), rig)
            for f in r.frames():
                got.append(f)
    assert 1 <= len(got) < len(frames)
    assert f"{len(got)} frame(s) were read" in str(info.value)
    assert_frames_match(got, frames[: len(got)], rig, GRID)
    # cutting only the summary off still reads every frame before failing
    _truncate(src, tmp_path / "tail.mcap", 0.999)
    with pytest.raises(BagCorruptError):
        n = 0
        with BagReader(tmp_path / "tail.mcap") as r:
            for _ in r.frames():
                n += 1
    assert n == len(frames)


def test_unreadable_inputs(tmp_path):
    with pytest.raises(BagError, match="no such"):
        BagReader(tmp_path / "missing")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(BagError, match="not a bag"):
        BagReader(tmp_path / "x.txt")
    (tmp_path / "junk.mcap").write_bytes(b"\x00" * 100)
    with pytest.raises(BagError):
        BagReader(tmp_path / "junk.mcap")


# --------------------------------------------------------------- with the generator
def _cli_synth(out, storage, *extra):
    argv = ["synth", str(out), "--frames", "3", "--seed", "3", "--scale", "0.25",
            "--storage", storage, *GRID_ARGS, *extra]
    assert main(argv) == 0


@needs_generator
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_cli_synth_roundtrip(tmp_path, storage, capsys):
    out = tmp_path / "drive"
    _cli_synth(out, storage)
    assert "wrote 3 frames" in capsys.readouterr().out
    rig = surround6().scaled(0.25)
    ref = list(generate_drive(rig, GRID, SynthConfig(frames=3, seed=3)))
    assert all(f.ground_visibility is not None for f in ref)
    with BagReader(out) as r:
        assert_layout(r, rig, 3, ground=True)
        assert_rig_matches(r.rig(), rig)
        assert r.grid() == GRID
        assert r.custom_data.get("bev_mapper.rig") == "surround6"
        got = list(r.frames())
    assert_frames_match(got, ref, rig, GRID)


@needs_generator
def test_cli_synth_jitter(tmp_path):
    _cli_synth(tmp_path / "drive", "mcap", "--jitter-ms", "6")
    with BagReader(tmp_path / "drive") as r:
        got = list(r.frames(rgb=False))
    assert len(got) == 3 and all(all(f.valid.values()) for f in got)
    offsets = [s - f.stamp_ns for f in got for s in f.camera_stamps.values()]
    assert max(abs(o) for o in offsets) <= 6 * MS and any(o != 0 for o in offsets)


def test_cli_usage_errors(tmp_path, capsys):
    assert main(["synth", str(tmp_path / "b"), "--grid-res", "0.7"]) == 1
    assert "whole number" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "b"), "--jitter-ms", "80"]) == 1
    assert main(["synth", str(tmp_path / "b"), "--scale", "0"]) == 1
    assert main(["nope"]) == 2
    assert not (tmp_path / "b").exists()


@needs_generator
@pytest.mark.slow  # full-size images
def test_cli_synth_truncated(tmp_path):
    """Full-size images (several 1 MiB mcap chunks): a cut file yields the intact frames."""
    out = tmp_path / "drive"
    assert main(["synth", str(out), "--frames", "3", *GRID_ARGS]) == 0
    rig = surround6()
    _truncate(out / "drive.mcap", tmp_path / "cut.mcap", 0.6)
    got = []
    with pytest.raises(BagCorruptError):
        with BagReader(tmp_path / "cut.mcap") as r:
            got.extend(r.frames())
    assert 1 <= len(got) < 3
    ref = list(itertools.islice(generate_drive(rig, GRID, SynthConfig(frames=3)), len(got)))  # render only those
    assert_frames_match(got, ref, rig, GRID)
