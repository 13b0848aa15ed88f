"""Scoring a replay in a process of its own: :class:`ScoringProcess`.

The scoring of a frame (IoU, Chamfer distances, the whole-grid counts) is numpy and OpenCV work
that holds the GIL much of the time, so in threads it overlaps the reading, mapping and writing
only in part. A :class:`ScoringProcess` runs a twin of the replay's
:class:`~bags.replay.scoring.ReplayScorer` in a child process (a fresh interpreter running this
module: nothing of the parent's threads or locks is inherited, and unlike ``multiprocessing``'s
``spawn`` the caller's main module is not run again there) and hands it each frame through a
shared memory map (a file in ``/dev/shm``, removed once both processes have mapped it): the prediction's
probabilities and known cells, and the frame's :class:`~bags.replay.scoring.FrameLayers` (computed
in the replay's process, which needs them for the pictures anyway). The child scores the frames
in the order they were submitted and answers each with the frame's IoU; the replay takes the
answers in the same order (:meth:`ScoringProcess.take`). The child also draws the pictures of the
frames it scores (it holds their prediction, GT and score) and, given the mapper's classes,
computes what the replay publishes of them: the OccupancyGrid cells and, while the replay's
process does not wait for the child's answers, the ``/bev/image`` picture, left in the frame's
slot for the replay to write (work taken off the busier process: when the replay's process
waits, it draws the picture itself). At the end the child's scores come back
as its scorer's mergeable state (:meth:`~bags.replay.scoring.ReplayScorer.state`), which the
replay's scorer loads: the same numbers as scoring in the replay's process, frame for frame
(the same arithmetic in the same order).

A failure in the child (its exception, or the child's death) is raised by the next call of the
replay's process; :meth:`ScoringProcess.close` (``abandon=True`` after a failure elsewhere) stops
the child and frees the shared memory in every case.
"""

from __future__ import annotations

import mmap
import os
import pickle
import subprocess
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import bev_picture
from bev_mapper_core.mapper import BevPrediction

from ..errors import BagError
from ..memory import keep_freed_memory
from ..report.pictures import save_comparison
from .frame_messages import prediction_cells
from .frame_scores import FrameScores, caption
from .scoring import FrameLayers, ReplayScorer
from .spare_cpu import usable_cpus

#: frames in flight between the replay's process and the scoring process (one shared-memory slot each)
DEPTH = 3
#: ``ReplayOptions.score_process`` ``"auto"`` scores in a process of its own only for drives at
#: least this long (starting the process costs about a second) on machines with 2 cores or more
AUTO_MIN_FRAMES = 100
#: ``"auto"`` scores in a process of its own only where the other jobs leave at least this much of
#: a core free beside the replay's own: with another replay on the 2 cores, a scoring process made
#: the command slower (18.1 against 17.2 ms a frame), on a quiet machine faster
#: (``bench/bench_replay_e2e.py``, docs/SPEED.md)
AUTO_MIN_SPARE = 0.5
#: seconds to wait for the child to exit before it is killed
_JOIN_S = 10.0
#: the child draws a frame's ``/bev/image`` while the replay's process waits less than this for
#: an answer, on average over the last answers (:attr:`ScoringProcess.waited_s`)
DRAW_WAIT_S = 0.5e-3


class ScoringError(BagError):
    """The scoring process failed or exited."""


@dataclass(frozen=True)
class Pictures:
    """What the scoring process needs to draw the pictures of the frames it scores."""

    #: the method's name (the pictures' title)
    method: str
    #: the mapper's classes, in layer order
    classes: tuple
    #: the folder the pictures are written into
    directory: str


@dataclass(frozen=True)
class _Field:
    """One array of a slot: its name, shape, dtype and byte offset in the slot."""

    name: str
    shape: tuple[int, ...]
    dtype: str
    offset: int

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape)) * np.dtype(self.dtype).itemsize


def _layout(n_pred: int, n_scored: int, shape: tuple[int, int],
            image: tuple[int, ...] = (0, 0, 3)) -> tuple[tuple[_Field, ...], int]:
    """The fields of one slot and its size in bytes (each field 64-byte aligned); ``image``:
    the shape of the ``/bev/image`` picture the child draws (none: 0 pixels).
    """
    spec = [("probs", (n_pred, *shape), "float32"), ("known", shape, "bool"),
            ("cells", (n_pred, shape[0] * shape[1]), "int8"), ("image", image, "uint8"),
            ("gt", (n_scored, *shape), "bool"), ("visible", shape, "bool"),
            ("truth", (n_scored, *shape), "bool"), ("seen", shape, "bool"), ("ground", shape, "bool")]
    fields, offset = [], 0
    for name, fshape, dtype in spec:
        f = _Field(name, tuple(fshape), dtype, offset)
        fields.append(f)
        offset += -(-f.nbytes // 64) * 64
    return tuple(fields), offset


def _views(buffer, fields: tuple[_Field, ...], size: int, slot: int) -> dict[str, np.ndarray]:
    """The arrays of slot ``slot`` in ``buffer``, as numpy views."""
    base = slot * size
    return {f.name: np.frombuffer(buffer, f.dtype, int(np.prod(f.shape)), base + f.offset).reshape(f.shape)
            for f in fields}


def start_child() -> subprocess.Popen:
    """Start a scoring process's interpreter now (its start and imports take about 0.4 s, which
    then overlap the replay's own start); :class:`ScoringProcess` takes it over, :func:`stop_child`
    stops it (also one taken over or already stopped).
    """
    return subprocess.Popen([sys.executable, "-c", f"from {__name__} import main; main()"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE)


def stop_child(proc: subprocess.Popen | None) -> None:
    """Close a child's input (it exits at its end), make sure it did (killed after
    :data:`_JOIN_S` seconds); ``None`` or a stopped child: nothing to do.
    """
    if proc is None:
        return
    for stream in (proc.stdin, proc.stdout):
        try:
            stream.close()
        except OSError:
            pass
    try:
        proc.wait(_JOIN_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def use_process(setting: str, frames: int | None, spare: float | None = None) -> bool:
    """Whether a replay of ``frames`` frames (``None``: unknown) scores in a process of its own
    for ``ReplayOptions.score_process`` = ``setting``. ``"auto"``: a long drive on 2 cores or
    more, where the other jobs leave at least :data:`AUTO_MIN_SPARE` of a core free beside the
    replay's own (``spare``: :meth:`~bags.replay.spare_cpu.CpuWatch.spare_cores`; ``None``:
    unknown, taken as free).
    """
    if setting != "auto":
        return setting == "on"
    if len(usable_cpus()) < 2 or frames is None or frames < AUTO_MIN_FRAMES:
        return False
    return spare is None or spare >= AUTO_MIN_SPARE


class ScoringProcess:
    """A twin of ``scorer`` in a child process, fed through shared memory (module docstring).

    Args:
        scorer: the replay's scorer (its :attr:`~bags.replay.scoring.ReplayScorer.args` build the twin).
        n_pred: classes of the mapper's predictions; ``shape``: the grid's ``(H, W)``.
        depth: frames in flight (slots of shared memory).
        pictures: what the child needs to draw the comparison pictures (``None``: none asked).
        child: the child, started earlier by :func:`start_child` (``None``: started here); from
            here on this object owns it.
        published: the mapper's classes: the child also computes each frame's OccupancyGrid
            cells and, while the replay waits less than :data:`DRAW_WAIT_S` for its answers,
            its ``/bev/image`` picture (:meth:`take` returns them); ``None``: neither.

    Raises:
        ScoringError: the child did not start.
    """

    def __init__(self, scorer: ReplayScorer, n_pred: int, shape: tuple[int, int], depth: int = DEPTH,
                 pictures: Pictures | None = None, published: tuple | None = None,
                 child: subprocess.Popen | None = None) -> None:
        self.depth = depth
        self._published = published is not None
        image = (0, 0, 3)
        if published is not None:  # the picture's size, from the (cached) painter of the grid
            grid = scorer.args[0]
            image = bev_picture(grid, np.zeros((len(published), *grid.shape), np.float32), published).shape
        self._fields, self._size = _layout(n_pred, len(scorer.classes), tuple(shape), image)
        fd, path = tempfile.mkstemp(prefix="bev-bag-scoring-", dir=_shared_dir())
        try:
            os.ftruncate(fd, self._size * depth)
            self._map = mmap.mmap(fd, self._size * depth)
        except BaseException:
            os.unlink(path)
            raise
        finally:
            os.close(fd)
        self._proc = child
        try:
            if self._proc is None:
                self._proc = start_child()
            grid, *rest = scorer.args
            self._send((path, self._fields, self._size, depth, (grid.to_dict(), *rest), pictures,
                        published))  # no cached arrays
            self._recv()  # mapped: the file can go
        except BaseException:
            self.close(abandon=True)
            raise
        finally:
            os.unlink(path)
        self._slots = [_views(self._map, self._fields, self._size, k) for k in range(depth)]  # built once
        self._free = deque(range(depth))
        self._busy: deque[tuple[int, bool]] = deque()  # (slot, picture drawn there) of the frames submitted, oldest first
        #: seconds the replay's process waited for an answer, a moving average over the last ones
        self.waited_s = 0.0

    def submit(self, layers: FrameLayers, pred: BevPrediction, cells: np.ndarray | None = None,
               picture: tuple[str, int, int] | None = None) -> None:
        """Copy a frame into a free slot and have the child score it (the caller :meth:`take` s
        the oldest answer first while the slots are :attr:`full`); ``cells``: its OccupancyGrid
        cells (:func:`~bags.replay.frame_messages.occupancy_cells`), which the child computes
        when not given; ``picture``: ``(file
        name, frame index, stamp)``, the child also draws the frame's picture into
        ``pictures.directory``.
        """
        if not self._free:
            raise RuntimeError("every slot is in use: take() the oldest answer first")
        views = self._slots[self._free[0]]
        if pred.probs.dtype != views["probs"].dtype or pred.probs.shape != views["probs"].shape:
            raise ScoringError(f"the scoring process takes {views['probs'].shape} float32 probabilities, "
                               f"got {pred.probs.shape} {pred.probs.dtype}")
        slot = self._free.popleft()
        np.copyto(views["probs"], pred.probs)
        if cells is not None:
            np.copyto(views["cells"], cells)
        present = {"known": pred.known is not None, "truth": layers.truth is not None,
                   "ground": layers.ground is not None}
        for name, value in (("known", pred.known), ("gt", layers.gt), ("visible", layers.visible),
                            ("truth", layers.truth), ("seen", layers.seen), ("ground", layers.ground)):
            if value is not None:
                np.copyto(views[name], value)
        present["cells"] = cells is not None
        present["image"] = self._published and self.waited_s < DRAW_WAIT_S  # else the replay draws it
        self._busy.append((slot, present["image"]))
        self._send(("frame", slot, tuple(pred.classes), present, picture))

    @property
    def full(self) -> bool:
        """True when every slot holds a frame being scored."""
        return not self._free

    @property
    def pending(self) -> int:
        """Frames submitted whose answer was not taken yet."""
        return len(self._busy)

    def take(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """The oldest frame submitted (waits for it): its IoU per scored class, and, when the
        child computes what is published (``published``), its OccupancyGrid cells ``(C, H*W)``
        int8 and (when it drew it, see :data:`DRAW_WAIT_S`) its ``/bev/image`` picture (copies:
        the slot is free again); ``None`` for what it did not compute.

        Raises:
            the child's exception, re-raised; ScoringError: the child exited.
        """
        if not self._busy:
            raise RuntimeError("no frame is being scored")
        slot, image = self._busy.popleft()
        try:
            start = time.perf_counter()
            iou = self._recv()  # its IoU, or its error raised here: either way the slot is free again
            self.waited_s += 0.2 * (time.perf_counter() - start - self.waited_s)
            if not self._published:
                return iou, None, None
            views = self._slots[slot]
            return iou, views["cells"].copy(), views["image"].copy() if image else None
        finally:
            self._free.append(slot)

    def close(self, abandon: bool = False) -> dict | None:
        """Stop the child; unless ``abandon``, first take its scores: the state of its scorer
        (:meth:`~bags.replay.scoring.ReplayScorer.state`). Every frame's answer must have been taken.
        """
        try:
            if abandon:
                return None
            if self._busy:
                raise RuntimeError(f"{len(self._busy)} answers not taken")
            self._send(("state",))
            return self._recv()
        finally:
            self._stop()

    def _send(self, message) -> None:
        try:
            pickle.dump(message, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            raise self._died() from None

    def _recv(self):
        try:
            kind, value = pickle.load(self._proc.stdout)
        except (EOFError, OSError, ValueError, pickle.UnpicklingError):
            raise self._died() from None
        if kind == "error":
            raise value
        return value

    def _died(self) -> ScoringError:
        try:
            code = None if self._proc is None else self._proc.wait(_JOIN_S)
        except subprocess.TimeoutExpired:
            code = None
        return ScoringError(f"the scoring process exited unexpectedly (exit code {code}); "
                            "replay with --score-process off to score in the replay's own process")

    def _stop(self) -> None:
        """Close the child's input (it exits at its end), make sure it did; release the map."""
        proc, self._proc = self._proc, None
        try:
            stop_child(proc)
        finally:
            self._slots = None  # the views of the map, which would keep it open
            try:
                self._map.close()
            except BufferError:  # a view of it still referenced (an exception's frames): freed with it
                pass


def _shared_dir() -> str | None:
    """Where the shared map's file lives: ``/dev/shm`` (memory) where there is one."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


def _serve(inp, out) -> None:
    """The child: map the shared file, then score each frame of the slot named in a message, in
    order, and answer its IoU (or the exception it raised); answer ``("state",)`` with the
    scorer's state; exit at the end of the input.
    """
    try:
        path, fields, size, depth, (grid, *args), pictures, published = pickle.load(inp)
    except EOFError:  # stopped before it was needed (stop_child)
        return
    with open(path, "r+b") as f:
        shared = mmap.mmap(f.fileno(), size * depth)
    slots = [_views(shared, fields, size, k) for k in range(depth)]
    grid = BevGrid.from_dict(grid)
    scorer = ReplayScorer(grid, *args)

    def answer(kind, value) -> None:
        try:
            pickle.dump((kind, value), out, protocol=pickle.HIGHEST_PROTOCOL)
        except (pickle.PicklingError, TypeError, AttributeError):  # an exception that does not pickle
            pickle.dump(("error", ScoringError(f"scoring failed: {value!r}")), out)
        out.flush()

    answer("ready", None)
    while True:
        try:
            message = pickle.load(inp)
        except EOFError:
            return
        try:
            if message[0] == "state":
                answer("state", scorer.state())
                continue
            _, slot, names, present, picture = message
            v = slots[slot]
            layers = FrameLayers(v["gt"], v["visible"], v["truth"] if present["truth"] else None,
                                 v["seen"], v["ground"] if present["ground"] else None)
            pred = BevPrediction(names, v["probs"], v["known"] if present["known"] else None)
            if not present["cells"]:  # as the replay's process computes them (FrameSink.finish)
                np.copyto(v["cells"], prediction_cells(pred))
            iou = scorer.add(layers, pred, v["cells"])
            if present["image"]:  # as write_frame_messages draws it
                np.copyto(v["image"], bev_picture(grid, pred.probs, published, pred.known))
            if picture is not None:
                _draw(pictures, picture, grid, scorer, layers, pred, iou)
            answer("iou", iou)
        except Exception as exc:  # noqa: BLE001 - handed to the replay, which raises it
            answer("error", exc)


def _draw(pictures: Pictures, picture: tuple[str, int, int], grid: BevGrid, scorer: ReplayScorer,
          layers: FrameLayers, pred: BevPrediction, iou: np.ndarray) -> None:
    """The frame's picture, as the replay's process draws it (:class:`~bags.replay.outputs.FrameSink`)."""
    name, index, stamp_ns = picture
    score = FrameScores().add_ious(index, stamp_ns, [c.name for c in scorer.classes], iou)
    save_comparison(Path(pictures.directory) / name, grid, pred.probs, pred.known, pictures.classes, layers.gt,
                    layers.visible, scorer.classes, method=pictures.method,
                    caption=caption(index, stamp_ns, score), ious=score.ious)


def main() -> None:
    """Entry point of the child: messages on stdin, answers on what was stdout (stdout itself now
    goes to stderr, so that nothing printed can corrupt the answers).
    """
    keep_freed_memory()  # the per-frame arrays reuse the heap (bags/memory.py)
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    try:
        _serve(sys.stdin.buffer, out)
    except (BrokenPipeError, KeyboardInterrupt):
        pass


__all__ = ["AUTO_MIN_FRAMES", "AUTO_MIN_SPARE", "DEPTH", "Pictures", "ScoringError", "ScoringProcess", "start_child", "stop_child",
           "use_process"]
