"""Issue #28: a replay's ``/bev/<class>`` grids and ``/bev/image`` picture are the bytes rosbags
writes for them, frame after frame, also where later frames take the first frame's headers with
their own stamp written in (``frame_messages._Heads``)."""

from __future__ import annotations

import numpy as np
import pytest

from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import BagWriter
from bags.replay.frame_messages import _HEADS, write_frame_messages
from bags.replay.options import IMAGE_TOPIC, OUT_PREFIX
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import BEV_CLASSES, bev_picture
from bev_mapper_core.mapper import BevPrediction
from msg_adapters import make_image, make_occupancy_grid


class _Mapper:
    classes = BEV_CLASSES
    class_names = tuple(c.name for c in BEV_CLASSES)


#: stamps with seconds and nanoseconds of every width (0, a second's last ns, int32's last second)
STAMPS = [1_700_000_000_123_456_789, 1_700_000_000_223_456_789, 5, 999_999_999, 10**9,
          (2**31 - 1) * 10**9 + 999_999_999, 1_700_000_001_000_000_000]


def _preds(grid, n, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        probs = rng.random((len(BEV_CLASSES),) + grid.shape, dtype=np.float32)
        known = rng.random(grid.shape) > 0.3
        probs[:, ~known] = np.nan  # as IPM leaves unknown cells
        out.append(BevPrediction(classes=_Mapper.class_names, probs=probs, known=known))
    return out


def _write(path, grid, preds, ego, fast):
    with BagWriter(path) as bw:
        for c in _Mapper.class_names:
            bw.add_topic(OUT_PREFIX + c, T.GRID_TYPE)
        bw.add_topic(IMAGE_TOPIC, T.IMAGE_TYPE)
        for stamp, pred in zip(STAMPS, preds):
            if fast:
                write_frame_messages(bw, grid, _Mapper, pred, stamp, ego)
                continue
            for ci, c in enumerate(_Mapper.class_names):  # every message built and serialized by rosbags
                bw.write(OUT_PREFIX + c, make_occupancy_grid(bw.factory, grid, pred.probs[ci], pred.known,
                                                             stamp, ego), stamp)
            picture = bev_picture(grid, pred.probs, _Mapper.classes, pred.known)
            bw.write(IMAGE_TOPIC, make_image(bw.factory, picture, "rgb8", stamp, ego), stamp)
        heads = _HEADS.get(bw)
        verified = None if heads is None else dict(heads._verified)
    with BagReader(path) as r:
        return [(m.topic, m.log_ns, m.msg) for m in r.messages(raw=True)], verified


_NAN_CAST = "ignore:invalid value encountered in cast"  # rosbags' path: NaN in unknown cells, overwritten


@pytest.mark.filterwarnings(_NAN_CAST)
def test_every_frame_is_what_rosbags_writes(tmp_path):
    for i, (grid, ego) in enumerate([(BevGrid(), "base_link"), (BevGrid(x_min=-7.5, x_max=22.5, y_min=-9.0,
                                                                         y_max=9.0, resolution=0.3), "ego/odd_")]):
        preds = _preds(grid, len(STAMPS), seed=i)
        fast, verified = _write(tmp_path / f"fast{i}", grid, preds, ego, fast=True)
        ref, _ = _write(tmp_path / f"ref{i}", grid, preds, ego, fast=False)
        assert len(fast) == len(STAMPS) * (len(BEV_CLASSES) + 1)
        assert fast == ref
        # the later frames took the templates (both kinds verified on the first frame)
        assert sorted(k[0] for k, ok in verified.items() if ok) == ["grid", "image"]


@pytest.mark.filterwarnings(_NAN_CAST)
def test_the_output_bags_are_the_same_files(tmp_path):
    grid = BevGrid()
    preds = _preds(grid, len(STAMPS), seed=5)
    _write(tmp_path / "fast" / "bag", grid, preds, "base_link", fast=True)
    _write(tmp_path / "ref" / "bag", grid, preds, "base_link", fast=False)
    files = sorted(p.name for p in (tmp_path / "fast" / "bag").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "ref" / "bag").iterdir()) and "bag.mcap" in files
    for name in files:
        assert (tmp_path / "fast" / "bag" / name).read_bytes() == (tmp_path / "ref" / "bag" / name).read_bytes()
