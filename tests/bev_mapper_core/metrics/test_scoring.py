"""One scorer: per-class scope masks in the accumulator, and every scoring path agreeing on them.

``bev-bag replay``, ``bev-train eval`` and validation during training all score through
:class:`~bev_mapper_core.metrics.MetricAccumulator` with its default range bands and the masks
of :func:`~bev_mapper_core.metrics.scope_masks`; these tests pin that down.
"""

from __future__ import annotations

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError, InputError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, resolve_classes
from bev_mapper_core.metrics import MetricAccumulator, default_range_bands, scope_masks
from bev_mapper_core.training.data import FrameSet
from bev_mapper_core.training.evaluate import score_frameset

GRID = BevGrid(-4.0, 4.0, -2.0, 2.0, 0.5)  # 16 x 8 cells


def _random_frame(rng, C):
    probs = rng.random((C, *GRID.shape)).astype(np.float32)
    gt = rng.random((C, *GRID.shape)) > 0.6
    return probs, gt


def test_per_class_masks_equal_one_accumulator_per_class():
    """A (C, H, W) visibility scores each class exactly as a separate accumulator with its mask."""
    rng = np.random.default_rng(3)
    names = ("drivable", "vehicle", "pedestrian")
    joint = MetricAccumulator(GRID, names)
    single = [MetricAccumulator(GRID, (n,)) for n in names]
    for _ in range(4):
        probs, gt = _random_frame(rng, len(names))
        masks = rng.random((len(names), *GRID.shape)) > 0.3
        known = rng.random(GRID.shape) > 0.1
        joint.update(probs, gt, masks, known)
        for c, acc in enumerate(single):
            acc.update(probs[c:c + 1], gt[c:c + 1], masks[c], known)
    res = joint.result()
    for c, n in enumerate(names):
        ref = single[c].result()["classes"][n]
        assert res["classes"][n] == pytest.approx(ref)
        for band, row in single[c].result()["iou_by_range"].items():
            assert res["iou_by_range"][band][n] == pytest.approx(row[n]) if row[n] is not None \
                else res["iou_by_range"][band][n] is None


def test_per_class_mask_shape_is_checked():
    acc = MetricAccumulator(GRID, ("drivable", "vehicle"))
    probs, gt = _random_frame(np.random.default_rng(0), 2)
    with pytest.raises(InputError, match="per-class visibility"):
        acc.update(probs, gt, np.ones((3, *GRID.shape), bool))


def test_scope_masks_restrict_only_flat_classes_to_the_seen_ground():
    visible = np.zeros(GRID.shape, bool)
    visible[:, :10] = True
    ground = np.zeros(GRID.shape, bool)
    ground[:, :4] = True
    names = BEV_CLASS_NAMES
    m = scope_masks(names, visible, ground, "ground")
    assert m.shape == (len(names), *GRID.shape)
    for c, cls in enumerate(resolve_classes(names)):
        assert np.array_equal(m[c], (visible & ground) if cls.flat else visible), cls.name
    assert np.array_equal(scope_masks(names, visible, ground, "visible"),
                          np.repeat(visible[None], len(names), 0))
    # no ground layer: the ground scope falls back to the visible cells
    assert np.array_equal(scope_masks(names, visible, None, "ground"), np.repeat(visible[None], len(names), 0))
    with pytest.raises(ConfigError, match="scope"):
        scope_masks(names, visible, ground, "everything")


def test_default_range_bands_cover_the_grid_in_10m_steps():
    assert default_range_bands(BevGrid()) == ((0, 10), (10, 20), (20, 30), (30, 40))
    assert default_range_bands(GRID) == ((0, 10),)
    assert MetricAccumulator(BevGrid(), ("drivable",)).range_bands == default_range_bands(BevGrid())


def test_score_frameset_equals_a_hand_loop_and_batches_do_not_matter():
    """The FrameSet scoring loop (eval, validation) is the accumulator over each frame's masks."""
    rng = np.random.default_rng(7)
    names = ("drivable", "lane_divider", "vehicle")
    M, N = 5, 2
    labels = rng.integers(0, 5, (M, N, 3, 4), dtype=np.uint8)
    labels[:, 0, 0, 0] = np.arange(M)  # the frame's index, for predict below
    target = rng.random((M, len(names), *GRID.shape)) > 0.5
    mask = rng.random((M, *GRID.shape)) > 0.2
    ground = mask & (rng.random((M, *GRID.shape)) > 0.3)
    fs = FrameSet(labels, target, mask, ground, ("a", "b"))
    probs = rng.random((M, len(names), *GRID.shape)).astype(np.float32)
    known = rng.random((M, *GRID.shape)) > 0.1

    def predict(batch):  # images (B, N, h, w) -> (B, C, H, W), (B, H, W)
        idx = [int(x[0, 0, 0]) for x in batch["images"].numpy()]
        return probs[idx], known[idx]

    for scope in ("visible", "ground"):
        ref = MetricAccumulator(GRID, names)
        for i in range(M):
            ref.update(probs[i], target[i], scope_masks(names, mask[i], ground[i], scope), known[i])
        want = ref.result()
        for batch in (1, 2, 5):
            got = score_frameset(predict, fs, GRID, names, batch=batch, scope=scope)
            got.pop("ms_per_frame")
            assert got == want, (scope, batch)
    limited = score_frameset(predict, fs, GRID, names, batch=2, limit=3)
    assert limited["frames"] == 3


@pytest.mark.slow
def test_replay_and_eval_score_the_same_drive_identically(tmp_path):
    """``bev-bag replay`` of a synthetic bag and ``bev-train eval``'s loop over the same drive
    rendered for training give the same metrics document (one scorer, one set of bands)."""
    import json

    from bags.cli.main import main as bev_bag
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import MapperConfig, create_mapper
    from bev_mapper_core.training.data import synth_frameset
    from bev_mapper_core.training.evaluate import evaluate_mapper

    seed, frames = 950000008, 4
    bag, out = tmp_path / "bag", tmp_path / "out"
    assert bev_bag(["synth", str(bag), "--rig", "front1", "--frames", str(frames), "--seed", str(seed)]) == 0
    assert bev_bag(["replay", str(bag), "--out", str(out), "--method", "ipm", "--no-pictures"]) == 0
    replayed = json.loads((out / "metrics.json").read_text())

    rig, grid = preset_rig("front1"), BevGrid()
    fs = synth_frameset(rig, grid, BEV_CLASS_NAMES, [seed], frames, 1, None)
    evaluated = evaluate_mapper(create_mapper(rig, grid, MapperConfig(method="ipm")), fs, grid)
    assert replayed["frames_scored"] == evaluated["frames"] == frames
    assert replayed["classes"] == evaluated["classes"]
    assert replayed["iou_by_range"] == evaluated["iou_by_range"]
    assert replayed["miou"] == evaluated["miou"]
