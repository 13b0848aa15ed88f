"""Ego-body masks: the pixels of a camera that show the ego vehicle itself (hood, trunk, mirrors).

Those pixels are *not seen*: a :class:`~bev_mapper_core.geometry.rig.RigCamera` carrying an
:class:`EgoMask` gives no ground cell whose pixel is masked (:func:`~.projection.remap_table`
leaves such cells out of its ``valid``, so IPM and every method's frustum / known mask leave them
to the other cameras or unknown, with no per-frame cost), and the mappers set the masked pixels
of label images to ``UNLABELED`` (:meth:`~bev_mapper_core.mapper.Mapper.mask_ego`), so no method
reads the hood as a vehicle.

A mask is given as a PNG of the camera's delivered image size (nonzero = ego body, one value
only: a binary image) or as polygons of ``[u, v]`` image pixels, filled. A mask follows scaled
cameras (the learned methods' resized inputs) by looking its pixels up proportionally.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import CalibrationError

#: a mask covering more than this fraction of its image is said (it may be inverted)
LARGE_FRACTION = 0.5


class EgoMaskError(CalibrationError):
    """An ego-body mask is unusable: missing or unreadable file, not binary, wrong size."""


@dataclass(frozen=True, eq=False)
class EgoMask:
    """Which pixels of one camera's image are the ego vehicle.

    Compared and hashed by identity (a :class:`RigCamera` holding one stays hashable).

    Args:
        pixels: ``(h, w)`` bool, True = ego body, at the camera's delivered image size.
        source: where it came from (a file name), for messages.
    """

    pixels: np.ndarray
    source: str = ""
    _resized: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        px = np.asarray(self.pixels)
        if px.ndim != 2 or px.dtype != bool or px.size == 0:
            raise EgoMaskError(f"ego mask {self.source!r} must be a non-empty (h, w) bool array, "
                               f"got {px.shape} {px.dtype}")
        px = np.ascontiguousarray(px)
        px.setflags(write=False)
        object.__setattr__(self, "pixels", px)

    def __repr__(self) -> str:
        w, h = self.size
        return f"EgoMask({self.source or 'array'!r}, {w}x{h}, {self.fraction:.1%} masked)"

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the mask."""
        return self.pixels.shape[1], self.pixels.shape[0]

    @property
    def fraction(self) -> float:
        """Fraction of the image that is ego body."""
        return float(self.pixels.mean())

    @property
    def all_masked(self) -> bool:
        """Every pixel is ego body: the camera sees nothing."""
        return bool(self.pixels.all())

    def at(self, width: int, height: int) -> np.ndarray:
        """The mask ``(height, width)`` bool for an image of that size (nearest; cached)."""
        if (width, height) == self.size:
            return self.pixels
        out = self._resized.get((width, height))
        if out is None:
            out = self._resized[(width, height)] = self.covers_grid(width, height)
        return out

    def covers_grid(self, width: int, height: int) -> np.ndarray:
        """``(height, width)``: whether each pixel centre of a ``width`` x ``height`` image falls
        on ego body (the image seen at another scale).
        """
        us, vs = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        uv = np.stack([us.ravel(), vs.ravel()], axis=1)  # (h*w, 2)
        return self.covers(uv, (width, height)).reshape(height, width)

    def covers(self, uv: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
        """``(N,)`` bool: pixels ``uv`` ``(N, 2)`` of an image of ``image_size`` = ``(w, h)`` lie
        on ego body. At the mask's own size the pixel is the one ``cv2.remap`` (nearest) reads;
        at another size the point is scaled proportionally. NaN / outside: False.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        w, h = image_size
        mw, mh = self.size
        ok = np.all(np.isfinite(uv), axis=1)
        safe = np.where(ok[:, None], uv, 0.0)
        if (w, h) == (mw, mh):
            iu, iv = np.rint(safe[:, 0]), np.rint(safe[:, 1])
        else:
            iu = np.floor((safe[:, 0] + 0.5) * mw / w)
            iv = np.floor((safe[:, 1] + 0.5) * mh / h)
        ok &= (iu >= 0) & (iu < mw) & (iv >= 0) & (iv < mh)
        iu = np.clip(iu, 0, mw - 1).astype(np.int64)
        iv = np.clip(iv, 0, mh - 1).astype(np.int64)
        return ok & self.pixels[iv, iu]


def mask_from_array(image: np.ndarray, source: str = "") -> EgoMask:
    """An :class:`EgoMask` from a grey (or equal-channel colour) image: nonzero = ego body.

    Raises:
        EgoMaskError: not binary (more than one nonzero value, or colours).
    """
    img = np.asarray(image)
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = img[..., :3]
        if not np.all(img == img[..., :1]):
            raise EgoMaskError(f"ego mask {source!r} is not binary: it has colours (want a grey PNG, "
                               f"0 = seen, one nonzero value = ego body)")
        img = img[..., 0]
    if img.ndim != 2:
        raise EgoMaskError(f"ego mask {source!r} must be a 2-D image, got shape {img.shape}")
    values = np.unique(img)
    nonzero = values[values != 0]
    if len(nonzero) > 1:
        shown = ", ".join(str(v) for v in nonzero[:5]) + (", ..." if len(nonzero) > 5 else "")
        raise EgoMaskError(f"ego mask {source!r} is not binary: {len(nonzero)} nonzero values ({shown}); "
                           f"want 0 = seen and one value (e.g. 255) = ego body")
    return EgoMask(img != 0, source)


def load_ego_mask(path: str | Path) -> EgoMask:
    """Read a mask PNG (nonzero = ego body).

    Raises:
        EgoMaskError: missing or unreadable file, not binary.
    """
    path = Path(path)
    if not path.is_file():
        raise EgoMaskError(f"ego mask {str(path)!r}: no such file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise EgoMaskError(f"ego mask {str(path)!r}: not an image OpenCV can read")
    return mask_from_array(img, str(path))


def polygon_mask(polygons: Sequence[Sequence[Sequence[float]]], image_size: tuple[int, int],
                 source: str = "polygons") -> EgoMask:
    """A mask of ``image_size`` = ``(w, h)`` from polygons of ``[u, v]`` pixels, filled.

    Raises:
        EgoMaskError: a polygon of fewer than 3 points or non-finite coordinates.
    """
    w, h = image_size
    img = np.zeros((h, w), np.uint8)
    pts = []
    for i, poly in enumerate(polygons):
        arr = np.asarray(poly, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 3 or not np.all(np.isfinite(arr)):
            raise EgoMaskError(f"{source}: polygon {i} must be 3 or more finite [u, v] points, got {poly!r}")
        pts.append(np.rint(arr).astype(np.int32))
    cv2.fillPoly(img, pts, 1)
    return EgoMask(img != 0, source)


def check_mask(mask: EgoMask, camera_name: str, image_size: tuple[int, int]) -> None:
    """Check ``mask`` against its camera's delivered ``image_size`` = ``(w, h)``.

    Raises:
        EgoMaskError: another size (the message names the camera and both sizes).
    """
    if mask.size != tuple(image_size):
        raise EgoMaskError(f"camera {camera_name!r}: ego mask {mask.source!r} is {mask.size[0]}x{mask.size[1]}, "
                           f"the camera's images are {image_size[0]}x{image_size[1]}")


def attach_ego_masks(rig, masks: Mapping[str, EgoMask]):
    """``rig`` with each camera of ``masks`` carrying its mask, and the problems found.

    Returns:
        ``(rig, problems)``: problems maps a camera name to why its mask was not attached
        (wrong size, or a camera the rig does not have); those cameras carry no mask.
    """
    problems: dict[str, str] = {}
    cams = []
    names = set(rig.names)
    for name in masks:
        if name not in names:
            problems[name] = f"ego mask for {name!r}, which is no camera of rig {rig.name!r} ({list(rig.names)})"
    for cam in rig.cameras:
        mask = masks.get(cam.name)
        if mask is not None:
            try:
                check_mask(mask, cam.name, cam.model.image_size)
            except EgoMaskError as exc:
                problems[cam.name] = str(exc)
                mask = None
        cams.append(cam if cam.ego_mask is mask else replace(cam, ego_mask=mask))
    return replace(rig, cameras=tuple(cams)), problems


def with_ego_masks(rig, masks: Mapping[str, EgoMask]):
    """``rig`` with the masks attached (see :func:`attach_ego_masks`).

    Raises:
        EgoMaskError: any mask of the wrong size or for an unknown camera, or masks that cover
            every camera's whole image (nothing would be mapped).
    """
    out, problems = attach_ego_masks(rig, masks)
    if problems:
        raise EgoMaskError("; ".join(problems.values()))
    if out.cameras and all(c.ego_mask is not None and c.ego_mask.all_masked for c in out.cameras):
        raise EgoMaskError(f"the ego masks cover the whole image of every camera of rig {out.name!r}: "
                           "nothing would be mapped (inverted? nonzero = ego body)")
    return out


def mask_notes(rig) -> list[str]:
    """What to tell a person about the rig's masks: cameras masked entirely or mostly."""
    notes = []
    for cam in rig.cameras:
        m = cam.ego_mask
        if m is None:
            continue
        if m.all_masked:
            notes.append(f"camera {cam.name!r}: its ego mask {m.source!r} covers the whole image: "
                         f"the camera adds nothing to the map")
        elif m.fraction > LARGE_FRACTION:
            notes.append(f"camera {cam.name!r}: its ego mask {m.source!r} covers {m.fraction:.0%} of the "
                         f"image (inverted? nonzero = ego body)")
    return notes


__all__ = ["EgoMask", "EgoMaskError", "attach_ego_masks", "check_mask", "load_ego_mask", "mask_from_array",
           "mask_notes", "polygon_mask", "with_ego_masks"]
