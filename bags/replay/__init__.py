"""Replay: a bag's frames mapped offline, deterministically (no ROS graph, no DDS), scored against
its GT layers, and written as a BEV bag, pictures, ``report.html`` and ``metrics.json``.

Public names: :func:`replay`, :class:`ReplayOptions`, :class:`ReplayResult`, :class:`ReplayScorer`
(the scorer, whose mergeable state ``bev-bag evaluate`` adds up), :func:`percentiles` (of the
latencies), and the output names :data:`BAG_DIR`, :data:`FRAMES_DIR`, :data:`METRICS_FILE`,
:data:`GIF_FILE`, :data:`REPORT_FILE`, :data:`RELIABILITY_FILE`, :data:`IMAGE_TOPIC`.

Modules: :mod:`~bags.replay.core` (:func:`replay`, see its docstring for the outputs),
:mod:`~bags.replay.options`, :mod:`~bags.replay.mapping`, :mod:`~bags.replay.scoring`,
:mod:`~bags.replay.outputs`, :mod:`~bags.replay.frame_messages` (a frame's messages in the output
bag), :mod:`~bags.replay.frame_scores` and :mod:`~bags.replay.pipeline`.
"""

from .core import replay
from .options import (
    BAG_DIR,
    FRAMES_DIR,
    GIF_FILE,
    IMAGE_TOPIC,
    METRICS_FILE,
    RELIABILITY_FILE,
    REPORT_FILE,
    ReplayOptions,
    ReplayResult,
)
from .scoring import ReplayScorer, percentiles

__all__ = ["BAG_DIR", "FRAMES_DIR", "GIF_FILE", "IMAGE_TOPIC", "METRICS_FILE", "RELIABILITY_FILE", "REPORT_FILE",
           "ReplayOptions", "ReplayResult", "ReplayScorer", "percentiles", "replay"]
