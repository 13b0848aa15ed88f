"""Issue #38: cameras recorded compressed (``sensor_msgs/CompressedImage``, JPEG and PNG), on
image_transport's ``<image topic>/compressed`` (found without flags) and on the image topic
itself; ``bev-bag synth --compressed`` writes such bags. Damaged compressed images (a JPEG that
does not decode, a truncated message, a wrong ``format``) are counted and said, the rest mapped.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from bag_helpers import replay_ipm, replay_scores, rewrite_bag, synth_small
from rosbags.typesys import Stores, get_typestore

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import JPEG_QUALITY
from bags.replay import METRICS_FILE

pytest.importorskip("bev_mapper_core.synth")

FRAMES, SEED = 3, 7
TS = get_typestore(Stores.ROS2_JAZZY)
CAMERAS = ("front", "front_right", "back_right", "back", "back_left", "front_left")
NO_OUTPUTS = ("--no-pictures", "--no-report")


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """The same drive with raw images and with compressed ones (JPEG RGB, PNG labels)."""
    root = tmp_path_factory.mktemp("compressed")
    return (synth_small(root / "raw", frames=FRAMES, seed=SEED),
            synth_small(root / "compressed", frames=FRAMES, seed=SEED, compressed=True))



def test_synth_compressed_writes_jpeg_rgb_and_png_labels_on_the_compressed_topics(drives):
    _, bag = drives
    with BagReader(bag) as r:
        for c in CAMERAS:
            for kind, fmt in (("rgb", "jpeg"), ("labels", "png")):
                topic = T.compressed_topic(T.image_topic(c, kind))
                assert r.topics[topic].msgtype == T.COMPRESSED_IMAGE_TYPE and r.topics[topic].count == FRAMES
                assert T.image_topic(c, kind) not in r.topics
                assert r.image_topic(c, kind) == topic  # found without flags
                m = next(iter(r.messages([topic])))
                assert m.msg.format == fmt and bytes(m.msg.data[:2]) == {"jpeg": b"\xff\xd8", "png": b"\x89P"}[fmt]


def test_png_label_images_replay_exactly_as_raw_ones(drives, tmp_path):
    raw, bag = drives
    assert replay_ipm(raw, tmp_path / "raw", *NO_OUTPUTS) == 0
    assert replay_ipm(bag, tmp_path / "compressed", *NO_OUTPUTS) == 0
    got = replay_scores(tmp_path / "compressed")
    assert got["frames_scored"] == FRAMES and got["decode_errors"] == 0 and got["complete"]
    assert got == replay_scores(tmp_path / "raw")


def _jpeg_roundtrip(rgb: np.ndarray) -> np.ndarray:
    """What OpenCV's JPEG (the synth's quality) makes of an RGB image, decoded to RGB."""
    data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1]
    return cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def test_jpeg_rgb_frames_are_the_raw_ones_through_jpeg(drives):
    raw, bag = drives
    with BagReader(raw) as r, BagReader(bag) as c:
        pairs = list(zip(r.frames(labels=False, gt=False), c.frames(labels=False, gt=False), strict=True))
        assert not c.issues
    assert len(pairs) == FRAMES
    for a, b in pairs:
        assert all(b.valid.values()) and b.rgb.keys() == a.rgb.keys()
        for cam, img in a.rgb.items():
            np.testing.assert_array_equal(b.rgb[cam], _jpeg_roundtrip(img))


def test_info_says_which_images_are_compressed(drives, capsys):
    _, bag = drives
    assert main(["info", str(bag)]) == 0
    assert "images: rgb (compressed), labels (compressed)" in capsys.readouterr().out
    assert main(["info", str(bag), "--json"]) == 0
    cams = json.loads(capsys.readouterr().out)["cameras"]
    assert [c["compressed"] for c in cams] == [["rgb", "labels"]] * len(CAMERAS)


def _params_file(path, **params):
    body = "".join(f"    {k}: {json.dumps(v)}\n" for k, v in params.items())
    path.write_text(f"/**:\n  ros__parameters:\n    rig: surround6\n{body}")
    return path


def test_compressed_images_on_the_image_topic_itself_and_named_by_the_params_file(drives, tmp_path, capsys):
    """CompressedImage on ``/cameras/<cam>/labels`` (once refused as the wrong type), and the
    ``.../compressed`` topics named by ``--params-file`` (once: ``image: has no field 'encoding'``),
    either as the topic or with ``compressed: true``: the same maps as the raw images.
    """
    raw, bag = drives
    assert replay_ipm(raw, tmp_path / "raw", *NO_OUTPUTS) == 0
    want = replay_scores(tmp_path / "raw")
    plain = rewrite_bag(bag, tmp_path / "plain", lambda t, m, d: (t.removesuffix(T.COMPRESSED_SUFFIX), m, d))
    with BagReader(plain) as r:
        assert r.topics["/cameras/front/labels"].msgtype == T.COMPRESSED_IMAGE_TYPE and not r.type_problems
    runs = {"on the topic": (plain, ()),
            "topic named": (bag, ("--params-file", str(_params_file(
                tmp_path / "named.yaml", image_topic="/cameras/{camera}/labels/compressed")))),
            "compressed: true": (bag, ("--params-file", str(_params_file(tmp_path / "flag.yaml", compressed=True))))}
    for name, (src, extra) in runs.items():
        out = tmp_path / name.replace(" ", "_").replace(":", "")
        assert replay_ipm(src, out, *NO_OUTPUTS, *extra) == 0, (name, capsys.readouterr().err)
        got = replay_scores(out)
        assert got["frames_scored"] == FRAMES and got["decode_errors"] == 0, name
        assert {k: v for k, v in got.items() if k != "rig"} == {k: v for k, v in want.items() if k != "rig"}, name


def _edit_compressed(data: bytes, change) -> bytes:
    msg = TS.deserialize_cdr(data, T.COMPRESSED_IMAGE_TYPE)
    change(msg)
    return bytes(TS.serialize_cdr(msg, T.COMPRESSED_IMAGE_TYPE))


def _undecodable(msg) -> None:
    """A JPEG whose header is fine but whose Huffman table is garbage: the decoder fails."""
    data = bytearray(msg.data.tobytes())
    dht = data.find(b"\xff\xc4")
    data[dht + 4:dht + 24] = b"\xff" * 20
    msg.data = np.frombuffer(bytes(data), np.uint8)


def _wrong_format(msg) -> None:
    msg.format = "theora"


def _jpeg_labels(msg) -> None:
    """A label image sent as JPEG (which changes label ids)."""
    ids = cv2.imdecode(msg.data, cv2.IMREAD_UNCHANGED)
    msg.format, msg.data = "jpeg", cv2.imencode(".jpg", ids)[1].reshape(-1)


#: (topic, frame index) -> what is wrong with that message
DAMAGE = {
    ("/cameras/front/image_raw/compressed", 0): lambda d: _edit_compressed(d, _undecodable),
    ("/cameras/front_right/image_raw/compressed", 1): lambda d: d[:len(d) // 2],  # a truncated message
    ("/cameras/back/image_raw/compressed", 2): lambda d: _edit_compressed(d, _wrong_format),
    ("/cameras/back_left/labels/compressed", 1): lambda d: _edit_compressed(d, _jpeg_labels),
}


@pytest.fixture(scope="module")
def damaged(drives, tmp_path_factory):
    """The compressed drive with the four bad images of :data:`DAMAGE`."""
    _, bag = drives
    seen: dict[str, int] = {}

    def edit(topic, msgtype, data):
        index = seen[topic] = seen.get(topic, -1) + 1
        change = DAMAGE.get((topic, index))
        return topic, msgtype, (data if change is None else change(data))

    return rewrite_bag(bag, tmp_path_factory.mktemp("damaged") / "bag", edit)


def test_damaged_compressed_images_are_counted_and_the_rest_mapped(damaged):
    with BagReader(damaged) as r:
        frames = list(r.frames(gt=False))
        problems = r.issues.to_metrics()["input_problems"]
    assert len(frames) == FRAMES
    assert [sorted(c for c, ok in f.valid.items() if not ok) for f in frames] == [
        ["front"], ["back_left", "front_right"], ["back"]]
    assert {t: p["decode_errors"] for t, p in problems.items()} == {t: 1 for t, _ in DAMAGE}
    first = {t: p["first"] for t, p in problems.items()}
    assert "corrupt or truncated data" in first["/cameras/front/image_raw/compressed"]
    assert "does not deserialize" in first["/cameras/front_right/image_raw/compressed"]
    assert "format 'theora' names no codec" in first["/cameras/back/image_raw/compressed"]
    assert "must be PNG" in first["/cameras/back_left/labels/compressed"]


def test_replay_of_damaged_compressed_images_says_so_without_a_traceback(damaged, tmp_path, capsys):
    capsys.readouterr()
    assert replay_ipm(damaged, tmp_path / "out", *NO_OUTPUTS, "--input", "labels") == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error: " in err and "/cameras/back_left/labels/compressed: 1" in err
    m = json.loads((tmp_path / "out" / METRICS_FILE).read_text())
    assert m["frames"] == FRAMES and m["frames_scored"] == FRAMES and not m["complete"]
    assert m["decode_errors"] == 1 and "must be PNG" in m["damage"]
