"""A mapped frame's messages in the output bag: ``/bev/<class>`` OccupancyGrids and the
``/bev/image`` picture, serialized once per frame.

The grids of one frame share their header and info and differ only in their cells, the last
field of an OccupancyGrid: the first class's message is serialized by rosbags, the others are
its bytes up to the cells followed by their own cells (the bytes rosbags would write for them).
The whole-percent values behind the cells (:func:`published_percent`) are computed once for
all classes and shared with the scorer, which scores the probabilities as published.

From one frame to the next, the bytes before the cells (and before the picture's pixels) differ
only in the stamp (:class:`_Heads`): once the first frame's messages, serialized by rosbags, have
been found equal to a template serialized at stamp 0 with the stamp written in, later frames
take the template with their stamp written in, and rosbags serializes nothing.
"""

from __future__ import annotations

import struct
import weakref

import numpy as np

from bev_mapper_core.geometry.grid import OCC_UNKNOWN, BevGrid
from bev_mapper_core.labels.classes import bev_picture
from bev_mapper_core.mapper import BevPrediction
from msg_adapters import make_image, make_occupancy_grid, ns_to_sec_nanosec

from ..io.writer import BagWriter
from .options import IMAGE_TOPIC, OUT_PREFIX


def published_percent(probs: np.ndarray) -> np.ndarray:
    """``(C, H, W)`` whole percent of ``probs`` ``(C, H, W)`` as the OccupancyGrids publish it
    (``rint(clip(p, 0, 1) * 100)``, :meth:`BevGrid.to_occupancy`'s arithmetic), in ``probs``' dtype.
    """
    out = np.clip(probs, 0.0, 1.0)
    np.multiply(out, 100.0, out=out)  # in place: the same products as clip(...) * 100.0
    return np.rint(out, out=out)


def occupancy_cells(percent: np.ndarray, known: np.ndarray | None) -> np.ndarray:
    """``(C, H*W)`` int8 OccupancyGrid data of every class (unknown cells -1), as
    :meth:`BevGrid.to_occupancy` gives each.
    """
    with np.errstate(invalid="ignore"):  # NaN only in unknown cells, overwritten below
        cells = percent.astype(np.int8)
    if known is not None:
        k = np.asarray(known, dtype=bool).view(np.uint8)  # (H, W) 1 known, 0 not
        np.multiply(cells, k, out=cells, casting="unsafe")  # unknown cells 0 (faster than a masked write)
        cells += k.astype(np.int8) + np.int8(OCC_UNKNOWN)  # unknown cells -1, the others as they are
    return cells.reshape(len(cells), -1)  # (C, H, W) -> (C, H*W)


def prediction_cells(pred: BevPrediction) -> np.ndarray:
    """``(C, H*W)`` int8 OccupancyGrid cells of ``pred`` as published: :func:`occupancy_cells`
    of its :func:`published_percent`.
    """
    return occupancy_cells(published_percent(pred.probs), pred.known)


_STAMP = struct.Struct("<iI")  # builtin_interfaces/Time: sec int32, nanosec uint32
_STAMP_AT = 4  # the header's stamp: the first field after the 4-byte CDR encapsulation header


class _Heads:
    """The bytes before the cells of a ``/bev/<class>`` grid and before the pixels of the
    ``/bev/image`` picture, per stamp, for one output bag (see module docstring).

    A template is the message serialized by rosbags at stamp 0 less its array's bytes; the
    stamp's 8 bytes sit at :data:`_STAMP_AT` (and, in a grid, at ``info.map_load_time``, found by
    serializing at a second stamp). A template is used only once a frame serialized by rosbags
    has given the same bytes; if one ever does not, that kind goes through rosbags for good.
    """

    def __init__(self) -> None:
        self._templates: dict[tuple, tuple[bytes, tuple[int, ...]] | None] = {}
        self._verified: dict[tuple, bool] = {}

    def head(self, key: tuple, stamp: int) -> bytes | None:
        """The head of ``key`` at ``stamp``, or ``None`` while it is not verified (or failed)."""
        if not self._verified.get(key):
            return None
        return self._patched(self._templates[key], stamp)

    @staticmethod
    def _patched(template: tuple[bytes, tuple[int, ...]] | None, stamp: int) -> bytes | None:
        if template is None:
            return None
        sec, nanosec = ns_to_sec_nanosec(stamp)
        if not (-2**31 <= sec < 2**31 and 0 <= nanosec < 2**32):
            return None  # rosbags' own error for it
        head = bytearray(template[0])
        for at in template[1]:
            _STAMP.pack_into(head, at, sec, nanosec)
        return bytes(head)

    def check(self, key: tuple, make, n: int, stamp: int, first: bytes) -> None:
        """Compare the rosbags bytes ``first`` (``n`` array bytes at the end) of a message at
        ``stamp`` with the template of ``key`` (``make(stamp)``: the message, serialized,
        with an all-zero array of ``n`` bytes); verified when equal, given up when not.
        """
        if key in self._verified:
            return
        template = None
        try:
            at0, at1 = make(0), make(1_000_000_002)  # sec 1, nanosec 2: their first bytes differ
            differ = [i for i, (a, b) in enumerate(zip(at0[:len(at0) - n], at1)) if a != b]  # sec, nanosec of each stamp
            stamps = differ[0::2]
            expect = [at + k for at in stamps for k in (0, 4)]
            if (len(at0) == len(at1) > n and stamps[:1] == [_STAMP_AT] and differ == expect
                    and at0.endswith(bytes(n))):
                template = (at0[:len(at0) - n], tuple(stamps))
        except Exception:  # noqa: BLE001 - no template: rosbags serializes every frame
            template = None
        head = self._patched(template, stamp)
        ok = head is not None and first[:len(first) - n] == head
        self._templates[key] = template if ok else None
        self._verified[key] = ok


_HEADS: weakref.WeakKeyDictionary[BagWriter, _Heads] = weakref.WeakKeyDictionary()


def write_frame_messages(bw: BagWriter, grid: BevGrid, mapper, pred: BevPrediction, stamp: int, ego: str,
                         cells: np.ndarray | None = None, picture: np.ndarray | None = None) -> None:
    """``/bev/<class>`` grids and the ``/bev/image`` picture of one frame (``cells``: the
    frame's :func:`occupancy_cells`; ``picture``: its ``bev_picture``; each computed here when
    not given).
    """
    heads = _HEADS.get(bw)
    if heads is None:
        heads = _HEADS[bw] = _Heads()
    names = mapper.class_names
    if cells is None:
        cells = prediction_cells(pred)
    n = cells.shape[1]
    key = ("grid", grid, ego, n)
    head = heads.head(key, stamp) if n == grid.width * grid.height and pred.probs.shape[1:] == grid.shape else None
    if head is not None:
        for ci, c in enumerate(names):
            bw.write_raw(OUT_PREFIX + c, b"".join((head, cells[ci])), stamp)
    else:
        first = bw.serialize(OUT_PREFIX + names[0], make_occupancy_grid(
            bw.factory, grid, pred.probs[0], pred.known, stamp, ego))
        if first.endswith(cells[0].tobytes()):
            head = first[:len(first) - n]  # everything before the cells (their count included)
            for ci, c in enumerate(names):
                bw.write_raw(OUT_PREFIX + c, first if ci == 0 else head + cells[ci].tobytes(), stamp)
            if n == grid.width * grid.height:
                zeros = np.zeros(grid.shape, np.float32)
                heads.check(key, lambda t: bw.serialize(OUT_PREFIX + names[0], make_occupancy_grid(
                    bw.factory, grid, zeros, None, t, ego)), n, stamp, first)
        else:  # not laid out as expected: every grid through rosbags
            for ci, c in enumerate(names):
                bw.write(OUT_PREFIX + c, make_occupancy_grid(bw.factory, grid, pred.probs[ci], pred.known,
                                                             stamp, ego), stamp)
    if picture is None:
        picture = bev_picture(grid, pred.probs, mapper.classes, pred.known)
    key = ("image", picture.shape, ego)
    head = None
    if picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[2] == 3 and picture.flags.c_contiguous:
        head = heads.head(key, stamp)
    if head is not None:
        bw.write_raw(IMAGE_TOPIC, b"".join((head, picture)), stamp)
        return
    first = bw.serialize(IMAGE_TOPIC, make_image(bw.factory, picture, "rgb8", stamp, ego))
    bw.write_raw(IMAGE_TOPIC, first, stamp)
    if picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[2] == 3 and picture.flags.c_contiguous:
        blank = np.zeros_like(picture)
        heads.check(key, lambda t: bw.serialize(IMAGE_TOPIC, make_image(bw.factory, blank, "rgb8", t, ego)),
                    picture.nbytes, stamp, first)
