"""Real labelled images: the CamVid and folder readers, the partial-label loss, augmentation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from torch.nn import functional as F

from bev_mapper_core.datasets import CamVid, DatasetError, FolderDataset, open_dataset
from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.labels.classes import NUM_LABELS, Label
from bev_mapper_core.labels.spaces import CAMVID, FINE, IGNORE
from bev_mapper_core.nn.augment import Augment, AugmentConfig
from bev_mapper_core.nn.label_space import coarse_predict, confusion, iou_from_confusion, joint_cover, marginal_nll

H, W = 12, 16


def _frame(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A tiny RGB frame and CamVid ids: sky on top, buildings, road below, a car box."""
    rng = np.random.default_rng(seed)
    lab = np.full((H, W), 0, np.uint8)
    lab[3:6] = 1
    lab[6:] = 3
    lab[8:10, 4:8] = 8
    lab[0, 0] = 11  # Unlabelled
    palette = np.array([[120, 160, 220], [90, 80, 70], [0, 0, 0], [110, 110, 110], [0, 0, 0], [0, 0, 0], [0, 0, 0],
                        [0, 0, 0], [200, 20, 20], [0, 0, 0], [0, 0, 0], [0, 0, 0]], np.uint8)
    img = np.clip(palette[lab].astype(int) + rng.integers(-8, 9, (H, W, 3)), 0, 255).astype(np.uint8)
    return img, lab


def _write(path, array) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = array[..., ::-1] if array.ndim == 3 else array  # RGB -> BGR for OpenCV
    assert cv2.imwrite(str(path), arr)


@pytest.fixture
def camvid(tmp_path):
    for split in ("train", "val"):
        for i in range(3):
            img, lab = _frame(i)
            _write(tmp_path / split / f"f{i}.png", img)
            _write(tmp_path / f"{split}annot" / f"f{i}.png", lab)
    return tmp_path


def test_camvid_reads_ids_and_ignores_unlabelled(camvid):
    ds = CamVid(camvid, "train")
    assert len(ds) == 3 and ds.space is CAMVID
    s = ds.read(0)
    assert s.image.shape == (H, W, 3) and s.image.dtype == np.uint8 and s.labels.shape == (H, W)
    assert s.labels[0, 0] == IGNORE and s.labels[9, 5] == 8 and s.labels[11, 0] == 3
    assert isinstance(open_dataset(f"camvid:{camvid}", "val"), CamVid)


def _bad_cases(root):
    """(name, damage function, file the message must name)."""
    def missing():
        (root / "trainannot" / "f1.png").unlink()
        return root / "trainannot" / "f1.png"

    def size():
        _write(root / "trainannot" / "f1.png", np.zeros((H + 1, W), np.uint8))
        return root / "trainannot" / "f1.png"

    def outside():
        lab = _frame(1)[1]
        lab[2, 2] = 12
        _write(root / "trainannot" / "f1.png", lab)
        return root / "trainannot" / "f1.png"

    def unreadable():
        (root / "train" / "f1.png").write_bytes(b"not a png")
        return root / "train" / "f1.png"

    return {"missing": missing, "size": size, "outside": outside, "unreadable": unreadable}


@pytest.mark.parametrize("case", ["missing", "size", "outside", "unreadable"])
def test_camvid_bad_files_raise_naming_the_file_or_are_skipped(camvid, case):
    bad = _bad_cases(camvid)[case]()
    with pytest.raises(DatasetError) as e:
        list(CamVid(camvid, "train"))
    assert isinstance(e.value, BevMapperError) and str(bad) in str(e.value)
    ds = CamVid(camvid, "train", skip_bad=True)
    samples, skipped = ds.load_all()
    assert len(samples) == 2 and len(skipped) == 1 and str(bad) in skipped[0][0] + skipped[0][1]


@pytest.fixture
def folder(tmp_path):
    for i in range(2):
        img, lab = _frame(i)
        _write(tmp_path / "images" / f"a{i}.jpg", img)
        up = np.select([lab == 0, lab == 1, lab == 3, lab == 8], [23, 11, 7, 26], 0).astype(np.uint8)  # Cityscapes ids
        _write(tmp_path / "labels" / f"a{i}.png", up)
    (tmp_path / "label_map.yaml").write_text(
        "encoding: mono8\nlabels:\n  7: road\n  11: building\n  23: unlabeled\n  26: vehicle\nignore: [0]\n")
    return tmp_path


def test_folder_layout_maps_ids_and_covers_missing_parts(folder):
    ds = FolderDataset(folder)
    s = ds.read(0)
    assert s.labels[0, 0] == IGNORE and s.labels[11, 0] == Label.ROAD and s.labels[9, 5] == Label.VEHICLE
    assert s.labels[4, 3] == Label.BUILDING and s.labels[1, 1] == Label.UNLABELED
    road = ds.space.covers[Label.ROAD]
    assert road == {Label.ROAD, Label.LANE_DIVIDER, Label.PED_CROSSING}  # the map never produces markings
    assert ds.space.covers[Label.VEHICLE] == {Label.VEHICLE}
    assert isinstance(open_dataset(f"folder:{folder}"), FolderDataset)
    # a preset instead of the YAML: Cityscapes ids 0..3 are ignored, 7 is road
    s2 = FolderDataset(folder, "cityscapes_ids").read(0)
    assert s2.labels[0, 0] == IGNORE and s2.labels[11, 0] == Label.ROAD


def test_folder_rgb8_palette(tmp_path):
    img, lab = _frame(0)
    colors = {0: (70, 130, 180), 1: (70, 70, 70), 3: (128, 64, 128), 8: (0, 0, 142), 11: (0, 0, 0)}
    rgb = np.zeros((H, W, 3), np.uint8)
    for k, c in colors.items():
        rgb[lab == k] = c
    _write(tmp_path / "images" / "x.png", img)
    _write(tmp_path / "labels" / "x.png", rgb)
    ds = FolderDataset(tmp_path, "cam2bev")
    s = ds.read(0)
    assert s.labels[11, 0] == Label.ROAD and s.labels[9, 5] == Label.VEHICLE and s.labels[0, 0] == Label.OBSTACLE
    rgb[0, 1] = (1, 2, 3)
    _write(tmp_path / "labels" / "x.png", rgb)
    with pytest.raises(DatasetError, match="colour"):
        FolderDataset(tmp_path, "cam2bev").read(0)


@pytest.mark.parametrize("case", ["missing", "size", "outside", "unreadable"])
def test_folder_bad_files(folder, case):
    lab_path, img_path = folder / "labels" / "a1.png", folder / "images" / "a1.jpg"
    if case == "missing":
        lab_path.unlink()
        bad = lab_path
    elif case == "size":
        _write(lab_path, np.full((H, W + 2), 7, np.uint8))
        bad = lab_path
    elif case == "outside":
        _write(lab_path, np.full((H, W), 99, np.uint8))
        bad = lab_path
    else:
        img_path.write_bytes(b"\xff\xd8 broken")
        bad = img_path
    with pytest.raises(DatasetError) as e:
        list(FolderDataset(folder))
    assert str(bad) in str(e.value)
    ds = FolderDataset(folder, skip_bad=True)
    samples, skipped = ds.load_all()
    assert len(samples) == 1 and len(skipped) == 1


def test_folder_bad_label_map(folder):
    (folder / "label_map.yaml").write_text("labels:\n  7: tarmac\n")
    with pytest.raises(ConfigError, match="tarmac"):
        FolderDataset(folder)


def test_marginal_loss_is_cross_entropy_on_fine_labels():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, NUM_LABELS, 5, 7, generator=g)
    target = torch.randint(0, NUM_LABELS, (2, 5, 7), generator=g)
    target[0, 0, 0] = IGNORE
    cover, _ = joint_cover([FINE])
    ref = F.cross_entropy(logits, target, ignore_index=IGNORE)
    assert torch.allclose(marginal_nll(logits, target, cover), ref, atol=1e-5)


def test_coarse_label_never_pushes_down_a_covered_fine_class():
    g = torch.Generator().manual_seed(1)
    cover, (_, off) = joint_cover([FINE, CAMVID])
    road = off + CAMVID.classes.index("Road")
    bicyclist = off + CAMVID.classes.index("Bicyclist")
    for code in (road, bicyclist):
        logits = torch.randn(4, NUM_LABELS, 3, 3, generator=g, requires_grad=True)
        target = torch.full((4, 3, 3), code)
        marginal_nll(logits, target, cover).backward()
        covered = cover[code]
        assert (logits.grad[:, covered] <= 1e-9).all()  # descent raises (or keeps) every covered logit
        assert (logits.grad[:, ~covered] >= -1e-9).all()
        with torch.no_grad():  # and a descent step raises the covered probability sum
            before = logits.softmax(1)[:, covered].sum(1)
            after = (logits - 0.5 * logits.grad).softmax(1)[:, covered].sum(1)
        assert (after >= before - 1e-7).all()
    # a marking under "Road" keeps its logit's gradient non-positive even when it is the likeliest
    logits = torch.zeros(1, NUM_LABELS, 1, 1)
    logits[0, Label.LANE_DIVIDER] = 5.0
    logits.requires_grad_(True)
    marginal_nll(logits, torch.full((1, 1, 1), road), cover).backward()
    assert logits.grad[0, Label.LANE_DIVIDER].item() <= 0


def test_coarse_predict_and_iou():
    logits = torch.zeros(1, NUM_LABELS, 1, 4)
    for i, lab in enumerate((Label.LANE_DIVIDER, Label.ROAD_BOUNDARY, Label.PEDESTRIAN, Label.TERRAIN)):
        logits[0, lab, 0, i] = 1
    pred = coarse_predict(logits, CAMVID)
    assert [CAMVID.classes[int(k)] for k in pred.flatten()] == ["Road", "Pavement", "Pedestrian", "Tree"]
    truth = torch.tensor([[[3, 4, 10, IGNORE]]])
    iou = iou_from_confusion(confusion(pred, truth, CAMVID.num_classes))
    assert iou[3] == 1 and iou[4] == 1 and iou[9] == 0 and iou[10] == 0 and np.isnan(iou[0])


def test_augment_keeps_labels_aligned_and_is_seeded():
    lab = torch.arange(H * W).view(1, H, W).repeat(3, 1, 1) % 7
    img = (lab.float() / 6.0).unsqueeze(1).repeat(1, 3, 1, 1)  # the image encodes the label
    cfg = AugmentConfig(scale=(1.0, 2.0))
    x1, y1 = Augment(cfg, torch.Generator().manual_seed(3)).geometric(img, lab, (H, W))
    x2, y2 = Augment(cfg, torch.Generator().manual_seed(3)).geometric(img, lab, (H, W))
    assert torch.equal(x1, x2) and torch.equal(y1, y2)
    ok = y1 != IGNORE
    assert ok.float().mean() > 0.9
    # nearest sampling of a piecewise image: most pixels read back their own label
    agree = (torch.round(x1[:, 0] * 6).long() == y1)[ok].float().mean()
    assert agree > 0.6
    out = Augment(AugmentConfig(p_blur=1, p_noise=1), torch.Generator().manual_seed(0)).photometric(img)
    assert out.shape == img.shape and out.min() >= 0 and out.max() <= 1


def test_tiny_mixed_training_lowers_the_loss(camvid):
    from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig

    torch.manual_seed(0)
    samples, _ = CamVid(camvid, "train").load_all()
    real_x = torch.from_numpy(np.stack([s.image for s in samples])).permute(0, 3, 1, 2).float() / 255
    real_y = torch.from_numpy(np.stack([s.labels for s in samples])).long()
    fine_y = torch.from_numpy(CAMVID.coarse_of_fine()).long()  # not needed: synthetic labels are fine ids
    syn_y = torch.full_like(real_y, int(Label.ROAD))
    syn_y[:, :6] = int(Label.UNLABELED)
    syn_y[:, 10:, 7] = int(Label.LANE_DIVIDER)
    assert fine_y.numel() == NUM_LABELS
    cover, (_, off) = joint_cover([FINE, CAMVID])
    model = Segmenter(SegmenterConfig(input_width=W, width_mult=0.25, depth_mult=0.25, encoder_stages=3,
                                      decoder_channels=8))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    aug = Augment(AugmentConfig(scale=(0.9, 1.2)), torch.Generator().manual_seed(0))
    losses = []
    for _ in range(30):
        xr, yr = aug(real_x, real_y, (H, W))
        xs, ys = aug(real_x, syn_y, (H, W))
        yr = torch.where(yr == IGNORE, yr, yr + off)
        norm = lambda x: (x - model.rgb_mean) / model.rgb_std  # noqa: E731
        loss = marginal_nll(model(norm(xr)), yr, cover) + marginal_nll(model(norm(xs)), ys, cover)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5])


@pytest.mark.parametrize("where", ["label_map", "labels_dir", "annotation"])
def test_folder_fifo_or_device_in_place_of_a_file_is_named(folder, where):
    """A FIFO, device or file where the reader expects something else is said as such (issue #29),
    never opened (a FIFO would block) and never called "no such file"."""
    import os  # noqa: PLC0415

    if where == "label_map":
        (folder / "label_map.yaml").unlink()
        os.mkfifo(folder / "label_map.yaml")
        with pytest.raises(ConfigError, match="is a FIFO, not a file"):
            FolderDataset(folder)
    elif where == "labels_dir":
        import shutil  # noqa: PLC0415

        shutil.rmtree(folder / "labels")
        (folder / "labels").write_text("not a folder")
        with pytest.raises(DatasetError, match="is a file, not a folder"):
            FolderDataset(folder)
    else:
        lab = folder / "labels" / "a1.png"
        lab.unlink()
        lab.symlink_to("/dev/zero")
        with pytest.raises(DatasetError, match="is a device, not a file") as e:
            FolderDataset(folder)
        assert str(lab) in str(e.value)
        samples, skipped = FolderDataset(folder, skip_bad=True).load_all()
        assert len(samples) == 1 and "device" in skipped[0][1]


def test_folder_label_map_with_exotic_ids_is_refused(folder):
    (folder / "label_map.yaml").write_text("labels:\n  0x07: road\n")
    with pytest.raises(ConfigError, match="'0x07'"):
        FolderDataset(folder)
