"""Training data: synthetic drives rendered once, cached as compressed ``.npz``, held in memory.

One cache file per drive (``<cache>/<key>/drive_<seed>.npz``) holds, for ``frames`` frames
rendered every ``stride``-th step of a seeded :func:`~bev_mapper_core.synth.generate_drive`
world (short drives from many seeds give variety; the stride makes consecutive samples ~3 m
apart instead of 1 m):

* ``labels`` ``(F, N, H, W)`` uint8: full-resolution camera label images in rig order (full
  resolution so that the same file serves IPM and the Mapper interface at evaluation time);
* ``gt`` ``(F, K, Hg, Wg)`` bool: BEV ground truth of the requested classes (the renderer's
  class table is swapped for the requested classes, e.g. Cam2BEV's road / vehicle / static);
* ``visibility`` / ``ground_visibility`` ``(F, Hg, Wg)`` bool;
* ``poses`` ``(F, 4, 4)`` float64 ``odom_from_base`` and ``stamps`` ``(F,)`` int64 ns of each frame
  (temporal methods; a cache written before they existed gets them added from the drive's world,
  which costs no rendering: :func:`drive_poses`);
* ``rgb`` ``(F, N, h, w, 3)`` uint8, only when the spec asks for RGB: the camera images resized
  to ``DriveSpec.rgb`` = ``(h, w)`` with the models' own resize (:func:`resize_rgb`), so a model
  whose input is that size sees exactly what its preprocess would make of the camera image.

The key directory name encodes rig, classes, grid, frames and stride, so incompatible caches
never mix. Everything is a pure function of ``(rig, grid, classes, seed, frames, stride)``:
the same seed gives bit-identical samples, and a drive rendered on the fly equals its cache.

Seeds: training drives use ``train_seeds(seed, n)`` = ``seed * 100_000 + i`` (< ``VAL_SEED_BASE``);
held-out drives ``val_seeds(n)`` = ``VAL_SEED_BASE + i`` by default, the same for every run, so
all methods are scored on the same drives. :func:`check_disjoint` enforces that no training
seed is a validation seed.

In memory, label images can be stored already resized to the model input size with the exact
operation :meth:`BiMapper.preprocess` applies (``nearest-exact`` interpolation of the ids), so
the model sees identical inputs while RAM shrinks ~13x (preprocess skips resizing when the size
already matches).
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.rig import Rig
from ..labels.classes import NUM_LABELS, label_lut, resolve_classes

#: First validation seed; training seeds must stay below it.
VAL_SEED_BASE = 900_000_000
#: Training seeds of run seed ``s`` are ``s * TRAIN_SEED_STRIDE + i``.
TRAIN_SEED_STRIDE = 100_000
CACHE_VERSION = 1


def train_seeds(seed: int, n: int) -> tuple[int, ...]:
    """Drive seeds of the training split of run seed ``seed``."""
    if n < 1:
        raise ConfigError(f"need at least one training drive, got {n}")
    if seed < 0 or seed * TRAIN_SEED_STRIDE + n >= VAL_SEED_BASE or n > TRAIN_SEED_STRIDE:
        raise ConfigError(f"run seed {seed} with {n} drives leaves the training seed range")
    return tuple(seed * TRAIN_SEED_STRIDE + i for i in range(n))


def val_seeds(n: int, base: int = VAL_SEED_BASE) -> tuple[int, ...]:
    """Held-out drive seeds (the same for every run unless ``base`` is changed)."""
    if n < 1:
        raise ConfigError(f"need at least one validation drive, got {n}")
    return tuple(base + i for i in range(n))


def check_disjoint(train: Sequence[int], val: Sequence[int]) -> None:
    """Raise :class:`ConfigError` if a seed is in both splits."""
    both = sorted(set(train) & set(val))
    if both:
        raise ConfigError(f"validation seeds overlap training seeds: {both[:5]}")


@dataclass(frozen=True)
class DriveSpec:
    """What one cached drive holds (everything its content depends on)."""

    rig: str
    cameras: tuple[str, ...]
    classes: tuple[str, ...]
    grid: tuple[float, float, float, float, float]
    frames: int
    stride: int
    rgb: tuple[int, int] | None = None
    style: str | None = None

    def key(self) -> str:
        """Cache sub-directory name: readable prefix + hash of the full spec (fields left at
        ``None`` do not enter the hash, so caches written before they existed stay valid).
        """
        d = {k: v for k, v in asdict(self).items() if v is not None}
        h = hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:10]
        rgb = f"_rgb{self.rgb[1]}_{self.style}" if self.rgb else ""
        return f"{self.rig}_{len(self.classes)}cls_f{self.frames}s{self.stride}{rgb}_v{CACHE_VERSION}_{h}"


def drive_spec(rig: Rig, grid: BevGrid, classes: Sequence[str], frames: int, stride: int,
               rgb: tuple[int, int] | None = None, style: str | None = None) -> DriveSpec:
    """The :class:`DriveSpec` of a rig/grid/classes and sampling (``rgb``: RGB storage size
    ``(h, w)``; ``style``: the RGB images' appearance style, default ``SynthConfig.style``; label
    images and GT do not depend on it, so drives without RGB do not record it).
    """
    if frames < 1 or stride < 1:
        raise ConfigError(f"frames and stride must be >= 1, got {frames}, {stride}")
    resolve_classes(classes)
    if rgb is not None:
        if len({c.model.image_size for c in rig.cameras}) != 1:
            raise ConfigError(f"RGB training data needs cameras of one size; rig {rig.name!r} mixes sizes")
        rgb = (int(rgb[0]), int(rgb[1]))
        from ..synth.config import SynthConfig
        from ..synth.styles import check_style

        style = check_style(SynthConfig.style if style is None else style)
    else:
        style = None
    g = (grid.x_min, grid.x_max, grid.y_min, grid.y_max, grid.resolution)
    return DriveSpec(rig.name, tuple(rig.names), tuple(classes), g, int(frames), int(stride), rgb, style)


def resize_rgb(images: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(..., H, W, 3)`` uint8 -> ``(..., h, w, 3)`` uint8 with the models' RGB resize (bilinear,
    antialiased, ``align_corners=False``), rounded back to uint8.
    """
    import torch
    from torch.nn import functional as F

    lead, (H, W) = images.shape[:-3], images.shape[-3:-1]
    if (H, W) == tuple(size):
        return images
    t = torch.from_numpy(np.ascontiguousarray(images.reshape(-1, H, W, 3))).permute(0, 3, 1, 2).float()  # (M, 3, H, W)
    t = F.interpolate(t, size=tuple(size), mode="bilinear", align_corners=False, antialias=True)
    out = t.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()  # (M, h, w, 3)
    return out.reshape(*lead, *size, 3)


def render_drive(rig: Rig, grid: BevGrid, classes: Sequence[str], seed: int, frames: int,
                 stride: int = 3, rgb: tuple[int, int] | None = None,
                 style: str | None = None) -> dict[str, np.ndarray]:
    """Render one drive: frames ``0, stride, 2*stride, ...`` of the world of ``seed``.

    Returns the arrays described in the module docstring. ``gt`` is built for ``classes`` by
    giving the renderer the class table of those classes (it only uses it to build GT).
    """
    from ..synth import SynthConfig
    from ..synth.drive import DriveRenderer
    from ..synth.world import build_world

    cls = resolve_classes(classes)
    cfg = SynthConfig(frames=(frames - 1) * stride + 1, seed=int(seed), **({"style": style} if style else {}))
    renderer = DriveRenderer(build_world(cfg), rig, grid)
    renderer.lut = label_lut(cls)  # GT of the requested classes
    labels, gt, vis, gvis, rgbs, poses, stamps = [], [], [], [], [], [], []
    for i in range(frames):
        f = renderer.frame(i * stride)
        poses.append(f.world_from_ego)
        stamps.append(f.stamp_ns)
        labels.append(np.stack([f.cameras[n].labels for n in rig.names]))
        if rgb is not None:
            rgbs.append(resize_rgb(np.stack([f.cameras[n].rgb for n in rig.names]), rgb))
        gt.append(f.gt.astype(bool))
        vis.append(f.visibility.astype(bool))
        gvis.append((f.ground_visibility if f.ground_visibility is not None else f.visibility).astype(bool))
    out = {"labels": np.stack(labels).astype(np.uint8), "gt": np.stack(gt), "visibility": np.stack(vis),
           "ground_visibility": np.stack(gvis), "poses": np.stack(poses).astype(np.float64),
           "stamps": np.asarray(stamps, np.int64)}
    if rgb is not None:
        out["rgb"] = np.stack(rgbs)
    return out


def drive_poses(seed: int, frames: int, stride: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """``(poses (F, 4, 4) odom_from_base, stamps (F,) ns)`` of the frames :func:`render_drive`
    renders, from the drive's world alone (no image is rendered).
    """
    from ..synth import SynthConfig
    from ..synth.world import build_world

    cfg = SynthConfig(frames=(frames - 1) * stride + 1, seed=int(seed))
    world = build_world(cfg)
    poses = np.stack([world.ego_pose(i * stride) for i in range(frames)]).astype(np.float64)
    return poses, np.asarray([cfg.frame_stamp_ns(i * stride) for i in range(frames)], np.int64)


def drive_path(cache_dir: str | os.PathLike, spec: DriveSpec, seed: int) -> Path:
    """Cache file of drive ``seed``."""
    return Path(cache_dir) / spec.key() / f"drive_{int(seed)}.npz"


def load_or_render(rig: Rig, grid: BevGrid, spec: DriveSpec, seed: int,
                   cache_dir: str | os.PathLike | None) -> dict[str, np.ndarray]:
    """A drive from the cache, rendering (and caching) it first if needed.

    A cache file that cannot be read is re-rendered (and overwritten).
    """
    if cache_dir is not None:
        path = drive_path(cache_dir, spec, seed)
        if path.is_file():
            try:
                keys = ("labels", "gt", "visibility", "ground_visibility") + (("rgb",) if spec.rgb else ())
                with np.load(path, allow_pickle=False) as z:
                    d = {k: z[k] for k in keys}
                    timed = "poses" in z.files and "stamps" in z.files
                    if timed:
                        d["poses"], d["stamps"] = z["poses"], z["stamps"]
                if (d["labels"].shape[:2] == (spec.frames, len(spec.cameras)) and d["gt"].shape[1] == len(spec.classes)
                        and (not spec.rgb or d["rgb"].shape[2:4] == spec.rgb)):
                    if not timed:  # written before drives kept their poses: add them
                        d["poses"], d["stamps"] = drive_poses(seed, spec.frames, spec.stride)
                        _write_cache(path, d)
                    return d
            except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError):
                pass
    d = render_drive(rig, grid, spec.classes, seed, spec.frames, spec.stride, spec.rgb, spec.style)
    if cache_dir is not None:
        write_spec(path.parent, spec)
        _write_cache(path, d)
    return d


def write_spec(key_dir: str | os.PathLike, spec: DriveSpec) -> None:
    """Create the cache key directory ``key_dir`` with its ``spec.json`` (written atomically, once)."""
    key_dir = Path(key_dir)
    key_dir.mkdir(parents=True, exist_ok=True)
    meta = key_dir / "spec.json"
    if not meta.exists():
        tmp = meta.with_name(f"spec.{os.getpid()}.tmp.json")
        tmp.write_text(json.dumps(asdict(spec), indent=1))
        os.replace(tmp, meta)


#: Timestamp of every ``.npz`` member (zip's earliest date): the file's bytes depend on its arrays only.
ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def _write_cache(path: Path, d: dict[str, np.ndarray]) -> None:
    """Write a drive's arrays atomically (another process may be reading the file).

    The layout of ``np.savez_compressed`` (deflated zip64 members ``<name>.npy``), but with a
    fixed member timestamp instead of the wall clock, so that the same arrays always give the
    same bytes (``bev-bag synth-many`` output does not depend on when or where it ran).
    """
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
    try:
        zf = zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True)
        try:
            for name, value in d.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=ZIP_DATE)
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o600 << 16  # what ZipFile.open(name, "w") gives
                with zf.open(info, "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)
        except BaseException:
            # Interrupted while zipfile opens a member (SIGTERM's exception can be raised there):
            # its close() would then refuse the half-open member with a ValueError that hides the
            # real exception (bev-train printed a traceback and exited 1 instead of 143). The
            # abandoned file is removed below; zipfile has no public way to drop the member.
            zf._writing = False  # noqa: SLF001
            raise
        finally:
            zf.close()
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def resize_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(..., H, W)`` uint8 ids -> ``(..., h, w)`` with exactly :meth:`BiMapper.preprocess`'s
    resize (``F.interpolate(mode="nearest-exact")``); unknown ids become 0 as there.
    """
    import torch
    from torch.nn import functional as F

    lead, (H, W) = labels.shape[:-2], labels.shape[-2:]
    h, w = size
    out = labels
    if (H, W) != (h, w):
        t = torch.from_numpy(np.ascontiguousarray(labels.reshape(-1, 1, H, W))).float()
        out = F.interpolate(t, size=(h, w), mode="nearest-exact").to(torch.uint8).numpy().reshape(*lead, h, w)
    return np.where(out < NUM_LABELS, out, 0).astype(np.uint8)


class FrameSet:
    """Frames held in memory: ``labels`` (M, N, h, w) uint8, ``target`` (M, K, Hg, Wg) bool,
    ``mask`` (M, Hg, Wg) bool (+ ``ground_mask``), with :meth:`batches` for training.

    ``rgb`` (M, N, h, w, 3) uint8, when loaded, holds the camera images (batches carry it as
    ``rgb``). ``poses`` (M, 4, 4) ``odom_from_base``, ``stamps`` (M,) ns and ``drives`` (M,)
    (which drive each frame is from; frames of a drive are consecutive and in order), when
    known, make the frames a sequence: batches carry ``poses`` / ``stamps`` / ``drives``, and with
    :attr:`window` > 1 every batch is a batch of windows (see :meth:`batch`).

    ``class_mask`` (M, K, Hg, Wg) bool, when given, narrows ``mask`` per class: the cells whose
    ground truth of that class is known (an imported dataset's class without a source, or a box
    below its filter, is unknown there, not absent); batches carry it as ``class_mask``, and the
    losses and the scoring train and score each class on ``mask & class_mask`` only.
    """

    def __init__(self, labels: np.ndarray, target: np.ndarray, mask: np.ndarray,
                 ground_mask: np.ndarray | None = None, camera_names: Sequence[str] = (),
                 rgb: np.ndarray | None = None, poses: np.ndarray | None = None,
                 stamps: np.ndarray | None = None, drives: np.ndarray | None = None,
                 class_mask: np.ndarray | None = None) -> None:
        if not (len(labels) == len(target) == len(mask)) or (rgb is not None and len(rgb) != len(labels)):
            raise ConfigError("labels, rgb, target and mask must have the same number of frames")
        if (poses is None) != (stamps is None) or (poses is None) != (drives is None):
            raise ConfigError("poses, stamps and drives come together")
        if poses is not None and not (len(poses) == len(stamps) == len(drives) == len(labels)):
            raise ConfigError("poses, stamps and drives must have one entry per frame")
        if class_mask is not None and class_mask.shape != target.shape:
            raise ConfigError(f"class_mask {class_mask.shape} must have the target's shape {target.shape}")
        self.labels, self.target, self.mask, self.rgb = labels, target, mask, rgb
        self.class_mask = class_mask
        self.ground_mask = mask if ground_mask is None else ground_mask
        self.camera_names = tuple(camera_names)
        self.poses, self.stamps, self.drives = poses, stamps, drives
        #: frames per sample of :meth:`batch` (the frame and the ``window - 1`` before it)
        self.window = 1

    def __len__(self) -> int:
        return len(self.labels)

    def windows(self, idx: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (B, T), present (B, T))``: the frames ``idx - T + 1 .. idx`` of each frame's
        drive, oldest first; before a drive's first frame ``present`` is False (the id repeats
        the frame itself).
        """
        if self.drives is None:
            raise ConfigError("these frames have no poses: they cannot form windows")
        idx = np.asarray(idx)
        ids = idx[:, None] + np.arange(-window + 1, 1)[None]  # (B, T)
        clipped = np.clip(ids, 0, len(self) - 1)
        present = (ids >= 0) & (self.drives[clipped] == self.drives[idx][:, None])
        return np.where(present, clipped, idx[:, None]), present

    def batch(self, idx: np.ndarray) -> dict:
        """Torch batch of frames ``idx``: ``images`` (B, N, h, w) uint8, ``target`` float, ``mask``
        bool, ``index`` (B,) int64 (the frames' ids in this set, e.g. for cached features)[,
        ``rgb``; ``class_mask`` (B, K, Hg, Wg) bool; ``poses`` (B, 4, 4) float64, ``stamps``, ``drives`` (B,)].

        With :attr:`window` ``T`` > 1, each sample is the window ending at its frame:
        ``images`` (B, T, N, h, w), ``rgb`` (B, T, N, h, w, 3), ``poses`` (B, T, 4, 4) and
        ``present`` (B, T) bool (see :meth:`windows`); ``target`` and ``mask`` are the last frame's.
        """
        import torch

        idx = np.asarray(idx)
        out = {"target": torch.from_numpy(self.target[idx]).float(), "mask": torch.from_numpy(self.mask[idx]),
               "index": torch.from_numpy(idx.astype(np.int64))}
        if self.class_mask is not None:
            out["class_mask"] = torch.from_numpy(self.class_mask[idx])
        if self.window > 1:
            ids, present = self.windows(idx, self.window)
            out["present"] = torch.from_numpy(present)
        else:
            ids = idx
        out["images"] = torch.from_numpy(self.labels[ids])
        if self.rgb is not None:
            out["rgb"] = torch.from_numpy(self.rgb[ids])
        if self.poses is not None:
            out["poses"] = torch.from_numpy(self.poses[ids])
            out["stamps"] = torch.from_numpy(self.stamps[idx])
            out["drives"] = torch.from_numpy(self.drives[idx])
        return out

    def batch_indices(self, batch_size: int, seed: int, epoch: int, limit: int | None = None,
                      shuffle: bool = True) -> Iterator[np.ndarray]:
        """Frame ids of each batch of one epoch, order a function of ``(seed, epoch)``; at most
        ``limit`` frames (the last batch may be shorter).
        """
        n = len(self)
        order = np.random.default_rng([seed, epoch, 17]).permutation(n) if shuffle else np.arange(n)
        if limit is not None and limit < n:
            order = order[:limit]
        for i in range(0, len(order), batch_size):
            yield order[i:i + batch_size]

    def batches(self, batch_size: int, seed: int, epoch: int, limit: int | None = None,
                shuffle: bool = True, shard: tuple[int, int] = (0, 1)) -> Iterator[dict]:
        """Batches of one epoch, order a function of ``(seed, epoch)``; at most ``limit`` frames.

        ``shard = (rank, world)``: rank ``rank``'s part of each batch (:func:`shard_slice`; the
        ranks' parts together are the batch); a batch of fewer than ``world`` frames (a short
        last one) is skipped, so that every rank takes the same steps.
        """
        for idx in self.batch_indices(batch_size, seed, epoch, limit, shuffle):
            part = shard_slice(len(idx), *shard)
            if part is not None:
                yield self.batch(idx[part])


def shard_slice(n: int, rank: int, world: int) -> slice | None:
    """Rank ``rank``'s contiguous part of a batch of ``n`` frames split over ``world`` ranks
    (sizes differ by at most one, larger parts first), or None when ``n < world`` (some rank
    would get nothing: the batch is skipped by every rank).
    """
    if world == 1:
        return slice(0, n)
    if n < world:
        return None
    base, extra = divmod(n, world)
    lo = rank * base + min(rank, extra)
    return slice(lo, lo + base + (rank < extra))


def synth_frameset(rig: Rig, grid: BevGrid, classes: Sequence[str], seeds: Sequence[int], frames: int,
                   stride: int = 3, cache_dir: str | os.PathLike | None = None,
                   input_size: tuple[int, int] | None = None, progress: bool = False,
                   rgb: tuple[int, int] | None = None, style: str | None = None) -> FrameSet:
    """Load (rendering missing drives) the drives ``seeds`` into a :class:`FrameSet`.

    ``input_size`` = (h, w): store labels resized as the model's preprocess would (see module
    docstring); ``None`` keeps full resolution. ``rgb`` = (h, w): also load the camera images
    at that size, in appearance ``style`` (default ``SynthConfig.style``).
    """
    spec = drive_spec(rig, grid, classes, frames, stride, rgb, style)
    it = seeds
    if progress:
        from tqdm import tqdm

        it = tqdm(seeds, desc=f"drives {rig.name}", unit="drive")
    L, T, M, G, R, P, S, D = [], [], [], [], [], [], [], []
    for i, s in enumerate(it):
        d = load_or_render(rig, grid, spec, s, cache_dir)
        P.append(d["poses"])
        S.append(d["stamps"])
        D.append(np.full(len(d["poses"]), i, np.int64))
        lab = d["labels"] if input_size is None else resize_labels(d["labels"], input_size)
        L.append(lab)
        T.append(d["gt"])
        M.append(d["visibility"])
        G.append(d["ground_visibility"])
        if rgb is not None:
            R.append(d["rgb"])
    return FrameSet(np.concatenate(L), np.concatenate(T), np.concatenate(M), np.concatenate(G), rig.names,
                    np.concatenate(R) if R else None, np.concatenate(P), np.concatenate(S), np.concatenate(D))


def main(argv: list[str] | None = None) -> int:
    """``python -m bev_mapper_core.training.data``: render the cache ahead of training."""
    import argparse

    from ..geometry.rig import preset_rig
    from ..labels.classes import BEV_CLASS_NAMES, CAM2BEV_CLASSES

    ap = argparse.ArgumentParser(description="Render synthetic training/validation drives into a cache.")
    ap.add_argument("--rig", default="surround6")
    ap.add_argument("--classes", default="standard", help="standard | cam2bev | comma list")
    ap.add_argument("--cache", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-drives", type=int, default=30)
    ap.add_argument("--val-drives", type=int, default=6)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--stride", type=int, default=3)
    a = ap.parse_args(argv)
    classes = (BEV_CLASS_NAMES if a.classes == "standard" else tuple(c.name for c in CAM2BEV_CLASSES)
               if a.classes == "cam2bev" else tuple(a.classes.split(",")))
    rig, grid = preset_rig(a.rig), BevGrid()
    seeds = list(val_seeds(a.val_drives)) + list(train_seeds(a.seed, a.train_drives))
    synth_frameset(rig, grid, classes, seeds, a.frames, a.stride, a.cache, progress=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
