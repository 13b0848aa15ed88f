"""Scoring a replay: :class:`ReplayScorer` scores each frame's prediction against the bag's GT
layers, :func:`scorer_for` builds it for a replay (with the notes on what is scored), and
:func:`percentiles` summarises the mapping latencies.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import class_cover, resolve_classes
from bev_mapper_core.mapper import BevPrediction
from bev_mapper_core.metrics import MetricAccumulator, WholeGridAccumulator, scope_masks

from ..io import topics as T
from .frame_messages import prediction_cells
from .options import ReplayRun


def no_scores() -> dict:
    """:meth:`ReplayScorer.result` when no class is scored (a new dict each time)."""
    return {"frames": 0, "classes": {}, "miou": None, "map": None, "iou_by_range": {},
            "occlusion": None, "calibration": None}


class FrameLayers(NamedTuple):
    """What a frame's GT gives the scoring of a prediction (:meth:`ReplayScorer.frame_layers`)."""

    #: ``(C', H, W)`` bool, per scored class its GT layers united
    gt: np.ndarray
    #: ``(H, W)`` bool, the cells whose GT is known
    visible: np.ndarray
    #: ``(C', H, W)`` bool full truth (``/bev/truth/<class>``), or ``None``
    truth: np.ndarray | None
    #: ``(H, W)`` bool, the cells some camera sees (``/bev/visibility/any``, else ``visible``)
    seen: np.ndarray
    #: ``(H, W)`` bool, the cells whose ground point is seen, or ``None``
    ground: np.ndarray | None


class ReplayScorer:
    """Scores a frame's prediction against its GT with the one
    :class:`~bev_mapper_core.metrics.MetricAccumulator`, in the chosen scope.

    The per-class masks come from :func:`~bev_mapper_core.metrics.scope_masks`: ``visible``
    scores the cells whose GT is known (not -1); ``ground`` (with a ground visibility layer)
    scores flat classes only where the ground is seen too, object classes keep the visible
    scope, since an object hides its own ground. Classes the bag has no GT for are not scored.

    Beside it a :class:`~bev_mapper_core.metrics.WholeGridAccumulator` scores the probabilities
    as published (rounded to whole percent, as in the OccupancyGrids) over the whole grid: the
    hidden cells are those ``/bev/visibility/any`` marks unseen (bags without it: the cells
    whose GT is -1), the false claims are counted against ``/bev/truth/<class>`` when the bag
    has it, and the ECE is taken in the same scope masks as the IoU.
    """

    def __init__(self, grid: BevGrid, pred_names, gt_names, ground: bool) -> None:
        #: what builds the same scorer elsewhere (:mod:`bags.replay.score_process`)
        self.args = (grid, tuple(pred_names), tuple(gt_names or ()), ground)
        #: predicted class -> the GT layers that mean the same (see ``class_cover``)
        self.class_map = {}
        for c in pred_names:
            cover = class_cover(c, tuple(gt_names)) if gt_names else None
            if cover is not None:
                self.class_map[c] = cover
        names = tuple(self.class_map)
        self.classes = resolve_classes(names) if names else ()
        self.unscored = [c for c in pred_names if c not in self.class_map]
        self.scope_used = None if not names else ("ground" if ground else "visible")
        self.acc = MetricAccumulator(grid, names) if names else None
        self.whole = WholeGridAccumulator(grid, names, self.acc.threshold) if names else None
        self._names = names
        self._pred_idx = [list(pred_names).index(c) for c in names]
        self._gt_idx = [[list(gt_names).index(g) for g in self.class_map[c]] for c in names]
        self._single = [idx[0] for idx in self._gt_idx] if all(len(i) == 1 for i in self._gt_idx) else None
        self._known_idx = sorted({i for idx in self._gt_idx for i in idx})  # the layers 'visible' needs
        # the GT layers read, as a slice (a view, no copy) when they are the first ones in order
        self._gt_take = _as_slice(self._single) if self._single is not None else None
        self._known_take = _as_slice(self._known_idx)
        self._all_pred = self._pred_idx == list(range(len(pred_names)))  # every predicted class, in order

    @property
    def mapped(self) -> dict[str, list[str]]:
        """Predicted classes scored against GT layers of other names: ``{class: [gt layers]}``."""
        return {c: list(g) for c, g in self.class_map.items() if g != (c,)}

    def update(self, frame, pred: BevPrediction, cells: np.ndarray | None = None):
        """Score one frame; returns ``(gt (C', H, W) bool, visible (H, W))`` or ``(None, None)``.

        ``cells``: the prediction's OccupancyGrid cells ``(C, H*W)`` int8
        (:func:`~bags.replay.frame_messages.occupancy_cells`), computed here when not given.
        """
        layers = self.frame_layers(frame)
        if layers is None:
            return None, None
        self.add(layers, pred, cells)
        return layers.gt, layers.visible

    def frame_layers(self, frame) -> FrameLayers | None:
        """The layers of ``frame`` that score a prediction (``None``: nothing to score)."""
        if self.acc is None or frame.gt is None:
            return None
        # a class covered by several GT layers is their union, known where all of them are
        gt = self._union(frame.gt)  # (C', H, W)
        visible = np.logical_and.reduce(frame.gt_known[self._known_take], axis=0)  # (H, W)
        truth = None if frame.truth is None else self._union(frame.truth)
        seen = frame.visibility if frame.visibility is not None else visible
        return FrameLayers(gt, visible, truth, seen, frame.ground_visibility)

    def add(self, layers: FrameLayers, pred: BevPrediction, cells: np.ndarray | None = None) -> np.ndarray:
        """Score ``pred`` against a frame's :meth:`frame_layers`; returns (and keeps in
        ``frame_iou``) the frame's own IoU per scored class (NaN: undefined), as
        :class:`~bags.replay.frame_scores.FrameScores` would score it. ``cells``: as in
        :meth:`update`.
        """
        masks = scope_masks(self._names, layers.visible, layers.ground, self.scope_used)
        probs = pred.probs if self._all_pred else pred.probs[self._pred_idx]  # (C', H, W)
        self.frame_iou = self.acc.update(probs, layers.gt, masks, pred.known)
        # whole percent, as in the OccupancyGrids (their bytes; the unknown cells' are not counted)
        cells = prediction_cells(pred) if cells is None else cells
        percent = cells.view(np.uint8).reshape(pred.probs.shape)  # (C, H*W) -> (C, H, W)
        if not self._all_pred:
            percent = percent[self._pred_idx]
        self.whole.update(None, pred.known, layers.seen, layers.gt, layers.truth, masks, percent=percent)
        return self.frame_iou

    def _union(self, layers: np.ndarray) -> np.ndarray:
        """``(C', H, W)`` bool: per scored class, its GT layers ``>= 0.5`` (bool layers: those
        already), united.
        """
        def half(taken: np.ndarray) -> np.ndarray:
            return taken if taken.dtype == np.bool_ else taken >= 0.5

        if self._single is not None:  # one layer per class: no union to take
            return half(layers[self._gt_take])
        return np.stack([half(layers[idx]).any(axis=0) for idx in self._gt_idx])

    def state(self) -> dict | None:
        """The mergeable state ``{"metrics": MetricAccumulator state, "whole":
        WholeGridAccumulator state}`` (see :mod:`bev_mapper_core.metrics`), ``None`` when no
        class is scored.
        """
        if self.acc is None:
            return None
        return {"metrics": self.acc.state(), "whole": self.whole.state()}

    def load_state(self, state: dict | None) -> None:
        """Take the scores of a twin scorer (its :meth:`state`) as this one's."""
        if self.acc is not None and state is not None:
            self.acc = MetricAccumulator.from_state(state["metrics"])
            self.whole = WholeGridAccumulator.from_state(state["whole"])

    @staticmethod
    def result_of(state: dict | None) -> dict:
        """:meth:`result` of a (merged) :meth:`state` (``None``: :func:`no_scores`)."""
        if state is None:
            return no_scores()
        return _scorer_result(MetricAccumulator.from_state(state["metrics"]),
                              WholeGridAccumulator.from_state(state["whole"]))

    def result(self) -> dict:
        """:meth:`MetricAccumulator.result` over the scored classes, in mapper order, plus the
        ``occlusion`` and ``calibration`` parts of :meth:`WholeGridAccumulator.result` (``None``
        when nothing is scored).
        """
        if self.acc is None:
            return no_scores()
        return _scorer_result(self.acc, self.whole)


def _as_slice(idx: list[int]) -> slice | list[int]:
    """``idx`` as the slice that reads the same layers when they are consecutive from 0 (numpy
    then reads a view instead of copying), else ``idx`` itself.
    """
    return slice(0, len(idx)) if idx == list(range(len(idx))) else idx


def _scorer_result(acc: MetricAccumulator, whole: WholeGridAccumulator) -> dict:
    """The scores of :meth:`ReplayScorer.result` from its two accumulators."""
    w = whole.result()
    w["occlusion"]["frames_with_truth"] = w["frames_with_truth"]
    return {**acc.result(), "occlusion": w["occlusion"], "calibration": w["calibration"]}


def scorer_for(run: ReplayRun) -> ReplayScorer:
    """The scorer of ``run``'s mapper classes against its bag's GT layers, in the asked scope;
    notes what is scored against what (and what not) in ``run.notes``.
    """
    reader, scope = run.reader, run.options.scope
    gt_names = reader.gt_classes
    has_ground = T.GROUND_VISIBILITY in reader.topics
    scorer = ReplayScorer(run.grid, run.mapper.class_names, gt_names, ground=scope == "ground" and has_ground)
    if gt_names and scorer.mapped:
        run.notes.append("classes scored against GT layers of the same definition: "
                         + ", ".join(f"{c} = {' + '.join(g)}" for c, g in scorer.mapped.items()))
    if gt_names and scorer.unscored:
        run.notes.append(f"WARNING: NOT SCORED: {scorer.unscored}: the bag has no GT layer of that definition "
                         f"(its GT layers: {list(gt_names)}); mIoU is over {list(scorer.class_map)} only")
    if scope == "ground" and gt_names and not has_ground:
        run.notes.append("scope 'ground' requested but the bag has no /bev/visibility/ground: "
                         "scoring visible cells only")
    return scorer


def percentiles(values: list[float]) -> dict:
    """``p50``, ``p95``, ``mean`` and ``max`` of ``values``, rounded to 3 decimals (``None`` if empty)."""
    if not values:
        return {"p50": None, "p95": None, "mean": None, "max": None}
    a = np.asarray(values, np.float64)
    return {"p50": round(float(np.percentile(a, 50)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "mean": round(float(a.mean()), 3), "max": round(float(a.max()), 3)}
