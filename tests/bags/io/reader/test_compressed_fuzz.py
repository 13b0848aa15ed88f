"""Issue #41: the compressed camera images of :mod:`compressed_cases` in a bag.

One small compressed drive (front1 rig) is re-written with the front camera's RGB image of frame
``i`` replaced by the ``i``-th RGB case and its label image by the ``i``-th label case. Expected:
the reader marks the camera invalid exactly in the frames of the refused cases (counted as decode
errors, with the refusal's words) and valid in the others (a CMYK JPEG converted); ``bev-bag
info`` reads the bag; ``bev-bag replay`` maps the other frames (the rig has one camera), exits 1 with an ``error:`` line that
counts the refused images, and never prints a traceback. (``bev-bag play`` republishes the bytes
as recorded, decoding nothing: tests/bags/cli/test_bags_play_compressed.py; ``evaluate`` runs
the same reader in its Ray tasks.)
"""

from __future__ import annotations

import contextlib
import io
import json
import re

import compressed_cases as C
import cv2
import numpy as np
import pytest
from bag_helpers import rewrite_bag
from rosbags.typesys import Stores, get_typestore

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.replay import METRICS_FILE

pytest.importorskip("bev_mapper_core.synth")

TS = get_typestore(Stores.ROS2_JAZZY)
CAM = "front"
RGB_CASES, LABEL_CASES = C.cases("rgb"), C.cases("labels")
FRAMES = max(len(RGB_CASES), len(LABEL_CASES))
TOPIC = {"rgb": T.compressed_topic(T.image_topic(CAM, "rgb")),
         "labels": T.compressed_topic(T.image_topic(CAM, "labels"))}
GRID = ["--grid-x-min", "-10", "--grid-x-max", "10", "--grid-y-min", "-5", "--grid-y-max", "5",
        "--grid-res", "0.5"]


def cli(*argv: str) -> tuple[int, str]:
    """``bev-bag ARGV`` in-process: ``(status, stderr)``; an escaping exception fails the test."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(argv))
    text = out.getvalue() + err.getvalue()
    assert "Traceback" not in text
    return rc, err.getvalue()


def _case_data(kind: str, case: C.Case, data: bytes) -> bytes:
    """The recorded message ``data`` (CDR) with its image replaced by ``case`` of its content."""
    msg = TS.deserialize_cdr(data, T.COMPRESSED_IMAGE_TYPE)
    good = cv2.imdecode(msg.data, cv2.IMREAD_UNCHANGED)
    if kind == "rgb":
        good = good[..., ::-1]  # BGR -> RGB
    payload, msg.format = case.make(np.ascontiguousarray(good))
    msg.data = np.frombuffer(payload, np.uint8)
    return bytes(TS.serialize_cdr(msg, T.COMPRESSED_IMAGE_TYPE))


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("compressed_fuzz")
    assert main(["synth", str(root / "good"), "--rig", "front1", "--scale", "0.25", "--frames", str(FRAMES),
                 "--seed", "41", "--compressed", *GRID]) == 0
    seen: dict[str, int] = {}

    def edit(topic, msgtype, data):
        i = seen[topic] = seen.get(topic, -1) + 1
        for kind, table in (("rgb", RGB_CASES), ("labels", LABEL_CASES)):
            if topic == TOPIC[kind] and i < len(table):
                data = _case_data(kind, table[i], data)
        return topic, msgtype, data

    return rewrite_bag(root / "good", root / "bag", edit)


@pytest.mark.parametrize("kind", ["rgb", "labels"])
def test_each_case_is_refused_or_decoded_in_its_frame(bag, kind):
    table = RGB_CASES if kind == "rgb" else LABEL_CASES
    with BagReader(bag) as r:
        frames = list(r.frames(rgb=kind == "rgb", labels=kind == "labels", gt=False))
        problems = r.issues.to_metrics()["input_problems"]
    assert len(frames) == FRAMES
    got = {c.name: frames[i].valid[CAM] for i, c in enumerate(table)}
    assert got == {c.name: c.refused is None for c in table}
    refused = [c for c in table if c.refused]
    assert problems[TOPIC[kind]]["decode_errors"] == len(refused)
    assert re.search(refused[0].refused, problems[TOPIC[kind]]["first"])
    for i, c in enumerate(table):
        if c.refused is None and kind == "rgb":
            img = frames[i].rgb[CAM]
            assert img.dtype == np.uint8 and img.shape[2] == 3 and img.mean() > 20  # a picture, not black


def test_info_and_replay_say_so_and_map_the_rest(bag, tmp_path):
    rc, err = cli("info", str(bag))
    assert rc == 0, err
    rc, err = cli("replay", str(bag), "--out", str(tmp_path / "out"), "--quiet", "--method", "ipm",
                  "--no-pictures", "--no-report", "--input", "labels")
    refused = sum(c.refused is not None for c in LABEL_CASES)
    assert rc == 1 and f"{TOPIC['labels']}: {refused}" in err and "error: " in err
    m = json.loads((tmp_path / "out" / METRICS_FILE).read_text())
    # front1 has one camera: a frame whose image is refused has nothing to map and is skipped
    assert m["decode_errors"] == m["frames_skipped"] == refused and not m["complete"]
    assert m["frames"] == m["frames_scored"] == FRAMES - refused
