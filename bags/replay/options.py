"""What a replay is asked for (:class:`ReplayOptions`), what it did (:class:`ReplayResult`), the
names of its outputs, and :class:`ReplayRun`: one replay under way, as the stages see it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.time_placement import TimePlacementConfig
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.metrics import SCOPES
from bev_mapper_core.temporal import TemporalConfig
from msg_adapters.sync import SyncConfig

from ..errors import BagError, BagExistsError
from ..io.rig_source import RigChoice
from ..io.writer import STORAGES
from .frame_scores import FrameScores

if TYPE_CHECKING:
    from bev_mapper_core.geometry.rig import Rig

    from ..io.reader import BagReader

OUT_PREFIX = "/bev/"
IMAGE_TOPIC = "/bev/image"
BAG_DIR, FRAMES_DIR, METRICS_FILE, GIF_FILE = "bev_bag", "frames", "metrics.json", "replay.gif"
REPORT_FILE, RELIABILITY_FILE = "report.html", "reliability.png"
#: :attr:`ReplayOptions.score_process`'s choices
SCORE_PROCESS = ("auto", "on", "off")
#: Every output a replay writes into its directory (``--force`` replaces them).
OUTPUT_NAMES = (BAG_DIR, FRAMES_DIR, METRICS_FILE, GIF_FILE, REPORT_FILE, RELIABILITY_FILE)


@dataclass(frozen=True)
class ReplayOptions:
    """Everything :func:`~bags.replay.core.replay` needs.

    Args:
        bag: input bag (rosbag2 directory, ``.mcap`` or ``.db3``).
        out: output directory (created if needed).
        mapper: method settings.
        grid: grid used only when the bag has no GT layers (``None`` = ``BevGrid()``).
        scope: ``'visible'`` scores cells whose GT is not -1; ``'ground'`` additionally requires,
            for flat classes, ``/bev/visibility/ground`` (the cell's ground point is seen by a
            camera); object classes keep the visible scope (see
            :class:`~bags.replay.scoring.ReplayScorer`).
        max_frames: stop after this many mapped frames (``None`` = all).
        pictures: write PNG pictures; ``frames_every``: of every k-th mapped frame (frame 0
            included; 1 = every frame). The default 10 keeps long drives cheap: a picture
            (drawing + PNG) costs about as much as mapping the frame with IPM (~6 ms) and
            ~100 kB on disk.
        gif: also write an animated GIF of the pictures.
        report: write ``report.html``.
        storage: storage of the output bag.
        force: replace existing outputs in ``out``.
        progress: show a tqdm progress bar on stderr.
        temporal: method-independent temporal fusion of the mapper's output over the last
            frames, aligned by the bag's odometry (:mod:`bev_mapper_core.temporal`; window 1 =
            off). Frames without odometry are mapped alone and counted.
        pipeline: frames in flight between the stages of the replay's pipeline
            (:mod:`bags.replay.pipeline`: one thread reads and decodes the next frames, this one maps,
            one scores the frames mapped before, one writes the frames scored before); 0 = one
            thread, every stage in turn.
            The outputs are the same either way, but the mapping latencies in ``metrics.json``
            are measured while the other stages run (0: the mapper's time alone).
        score_process: score the frames in a process of their own (:mod:`bags.replay.score_process`):
            ``'on'``, ``'off'`` or ``'auto'`` (a drive of at least
            :data:`~bags.replay.score_process.AUTO_MIN_FRAMES` frames on 2 cores or more, where
            the other jobs left at least :data:`~bags.replay.score_process.AUTO_MIN_SPARE` of a
            core free while the bag opened: :mod:`bags.replay.spare_cpu`; the process is started
            then, so its start overlaps the mapper's). The outputs are the same either way;
            ``metrics.json`` ``score_process`` says where the frames were scored. ``bev-bag
            evaluate`` turns it off: its workers already keep every core busy.
        rig: what the bag lacks about its rig (``--rig``, ``--params-file``;
            :mod:`bags.io.rig_source`).
        sync: how the cameras' images are grouped into sets (:meth:`SyncConfig.replay`).
        ego_masks: ``(camera, PNG path)`` pairs (``--ego-mask CAM=PNG``): the pixels of the ego
            vehicle itself, ignored by the method (:mod:`bev_mapper_core.geometry.ego_mask`); they
            win over the ``--params-file``'s ``ego_mask.<camera>``.
        placement: each camera placed with the ego pose (the bag's odometry or ``/tf``) of its own
            stamp, in ``base_link`` at the frame's stamp (:mod:`bev_mapper_core.placement`:
            IPM and segipm a placed rig, learned methods the moved images warped); counted in
            ``metrics.json``'s ``placement``.
    """

    bag: Path
    out: Path
    mapper: MapperConfig = field(default_factory=MapperConfig)
    grid: BevGrid | None = None
    scope: str = "visible"
    max_frames: int | None = None
    pictures: bool = True
    frames_every: int = 10
    gif: bool = False
    report: bool = True
    storage: str = "mcap"
    force: bool = False
    progress: bool = False
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    pipeline: int = 4
    score_process: str = "auto"
    rig: RigChoice = field(default_factory=RigChoice)
    sync: SyncConfig = field(default_factory=SyncConfig.replay)
    ego_masks: tuple = ()
    placement: TimePlacementConfig = field(default_factory=TimePlacementConfig)

    def __post_init__(self) -> None:
        if self.scope not in SCOPES:
            raise BagError(f"scope must be one of {list(SCOPES)}, got {self.scope!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise BagError(f"--max-frames must be >= 1, got {self.max_frames}")
        if self.pipeline < 0:
            raise BagError(f"--pipeline must be >= 0, got {self.pipeline}")
        if self.score_process not in SCORE_PROCESS:
            raise BagError(f"--score-process must be one of {list(SCORE_PROCESS)}, got {self.score_process!r}")
        if self.frames_every < 1:
            raise BagError(f"--frames-every must be >= 1, got {self.frames_every}")
        if self.storage not in STORAGES:
            raise BagError(f"storage must be one of {list(STORAGES)}, got {self.storage!r}")


@dataclass
class ReplayResult:
    """What :func:`~bags.replay.core.replay` did: the metrics dict, output paths, damage note,
    GIF note, and per mapped frame its mapping latency (ms) and, per scored frame, its IoU per class.
    """

    metrics: dict
    out: Path
    bag_path: Path
    pictures: list[Path]
    gif: Path | None = None
    gif_note: str = ""
    damage: str | None = None
    notes: list[str] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    frame_scores: FrameScores = field(default_factory=FrameScores)
    report: Path | None = None
    reliability: Path | None = None
    #: the mergeable scoring state (:meth:`~bags.replay.scoring.ReplayScorer.state`; ``None``:
    #: nothing scored), so that several replays add up exactly (``bev-bag evaluate``)
    scoring: dict | None = None


@dataclass(frozen=True)
class ReplayRun:
    """One replay under way, as its stages see it: the options, the open bag, the rig and grid
    it maps onto, the mapper, the output directory and the temporary one of the pictures, and
    the notes for the result (appended to as the stages go).
    """

    options: ReplayOptions
    reader: BagReader
    rig: Rig
    grid: BevGrid
    mapper: Any
    out: Path
    tmp_frames: Path
    notes: list[str] = field(default_factory=list)
    #: the cores the other jobs left free while the bag opened (``None``: unknown); ``metrics.json``
    #: ``score_process``
    spare_cores: float | None = None

    @property
    def input_kind(self) -> str:
        """What the mapper reads: ``'labels'`` or ``'rgb'``."""
        return self.options.mapper.input_kind


def check_outputs(out: Path, force: bool) -> None:
    """Refuse to replace the outputs of an earlier replay in ``out`` unless ``force``.

    Raises:
        BagExistsError: ``out`` is not a directory, or holds outputs and ``force`` is false.
    """
    if out.exists() and not out.is_dir():
        raise BagExistsError(f"{out} exists and is not a directory")
    existing = [n for n in OUTPUT_NAMES if (out / n).exists()]
    if existing and not force:
        raise BagExistsError(f"{out} already holds replay outputs {existing}; pass --force to "
                             "replace them")
