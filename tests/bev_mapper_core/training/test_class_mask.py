"""Per-class masks of unknown ground truth (``FrameSet.class_mask``): a class masked in a cell is
neither trained nor scored there, whatever its target says (an imported dataset's class without a
source must not be learned as "absent").
"""

from __future__ import annotations

import numpy as np
import torch

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.methods.bimapper.losses import across_space_loss, bimapper_loss
from bev_mapper_core.methods.focusbev.losses import weighted_bce
from bev_mapper_core.methods.s2g2.losses import s2g2_loss  # noqa: F401 - imported: its signature takes class_mask
from bev_mapper_core.training.class_weights import class_pos_weight
from bev_mapper_core.training.data import FrameSet
from bev_mapper_core.training.evaluate import score_frameset

B, K, H, W = 2, 2, 8, 6


def _batch(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(B, K, H, W, generator=g)
    target = torch.rand(B, K, H, W, generator=g) > 0.5
    mask = torch.ones(B, H, W, dtype=torch.bool)
    mask[:, 0] = False
    class_mask = torch.ones(B, K, H, W, dtype=torch.bool)
    class_mask[:, 1] = False  # class 1 unknown everywhere (no source)
    class_mask[:, 0, :, :2] = False  # class 0 unknown in two columns (boxes below a filter)
    return logits, target, mask, class_mask


def test_a_masked_class_or_cell_does_not_change_the_bce_losses():
    logits, target, mask, cm = _batch()
    flipped = target.clone()
    flipped[:, 1] = ~flipped[:, 1]
    flipped[:, 0, :, :2] = ~flipped[:, 0, :, :2]
    for loss in (lambda t: bimapper_loss({"logits": logits}, {"target": t, "mask": mask, "class_mask": cm}, 0)[0],
                 lambda t: weighted_bce(logits, t.float(), mask, None, cm)):
        assert torch.allclose(loss(target), loss(flipped))
    # without the class mask the flipped targets change the loss: the mask is what keeps them out
    plain = bimapper_loss({"logits": logits}, {"target": target, "mask": mask}, 0)[0]
    assert not torch.allclose(plain, bimapper_loss({"logits": logits}, {"target": flipped, "mask": mask}, 0)[0])
    # a scored cell still counts
    t2 = target.clone()
    t2[:, 0, 3, 4] = ~t2[:, 0, 3, 4]
    assert not torch.allclose(weighted_bce(logits, target.float(), mask, None, cm),
                              weighted_bce(logits, t2.float(), mask, None, cm))


def test_a_masked_class_does_not_change_the_across_space_loss():
    logits, target, mask, cm = _batch(1)
    N, Hp, Wp = 2, 5, 4
    plane_logits = torch.randn(B, N, K, Hp, Wp, generator=torch.Generator().manual_seed(2))
    ys, xs = torch.meshgrid(torch.linspace(-0.9, 0.9, Hp), torch.linspace(-0.9, 0.9, Wp), indexing="ij")
    gt_grid = torch.stack([xs, ys], -1)[None].expand(N, Hp, Wp, 2).contiguous()  # (N, Hp, Wp, 2)
    gt_valid = torch.ones(N, Hp, Wp, dtype=torch.bool)
    flipped = target.clone()
    flipped[:, 1] = ~flipped[:, 1]
    a = across_space_loss(plane_logits, target.float(), gt_grid, gt_valid, mask, None, cm)
    b = across_space_loss(plane_logits, flipped.float(), gt_grid, gt_valid, mask, None, cm)
    assert torch.allclose(a, b)
    # the class mask of all-known cells gives the loss without it
    full = torch.ones_like(cm)
    assert torch.allclose(across_space_loss(plane_logits, target.float(), gt_grid, gt_valid, mask, None, full),
                          across_space_loss(plane_logits, target.float(), gt_grid, gt_valid, mask))


def test_frameset_batches_weights_and_scores_honour_the_class_mask():
    grid = BevGrid(x_min=0.0, x_max=3.0, y_min=-2.0, y_max=2.0, resolution=0.5)  # 8 rows x 6 columns
    assert grid.shape == (H, W)
    _, target, mask, cm = _batch(3)
    target, mask, cm = target.numpy(), mask.numpy(), cm.numpy()
    fs = FrameSet(np.zeros((B, 1, 4, 4), np.uint8), target, mask, class_mask=cm)
    assert torch.equal(fs.batch(np.arange(B))["class_mask"], torch.from_numpy(cm))
    # positive weights count each class's known cells only: class 1 has none, weight 1 (clipped)
    w = class_pos_weight(fs)
    known0 = mask[:, None] & cm
    pos0, tot0 = np.count_nonzero(target[:, 0] & known0[:, 0]), np.count_nonzero(known0[:, 0])
    assert w[0] == round(float(np.clip(np.sqrt((tot0 - pos0) / pos0), 1, 10)), 3) and w[1] == 1.0

    def predict(batch):  # the ground truth itself, where known; the opposite where unknown
        t = batch["target"].numpy().astype(bool)
        probs = np.where(batch["class_mask"].numpy(), t, ~t).astype(np.float32)
        return probs, np.ones((len(t), H, W), bool)

    res = score_frameset(predict, fs, grid, ("drivable", "vehicle"))
    assert res["classes"]["drivable"]["iou"] == 1.0  # the wrong cells are all unknown: not scored
    assert res["classes"]["vehicle"]["iou"] is None  # never known: no score (not 0)
    assert all(row["drivable"] in (1.0, None) and row["vehicle"] is None for row in res["iou_by_range"].values())
