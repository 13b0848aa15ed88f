"""What a bag lacks about its rig, from the user: ``--rig NAME`` and ``--params-file FILE``.

A bag written by this tool carries everything a replay needs: CameraInfo per camera, the
extrinsics on ``/tf_static`` and the rig's name in its metadata (``bev_mapper.rig``). A bag
recorded elsewhere may lack the extrinsics, the name, or use other topics. :class:`RigHints`
is what the user adds, resolved from:

* ``--rig NAME``: a preset (:data:`~bev_mapper_core.geometry.rig.PRESETS`) gives the camera
  names (in its order), their extrinsics and intrinsics; any other name only names the rig
  (the shipped weights are chosen by it).
* ``--params-file FILE``: the node's own parameter file (``config/<rig>.yaml`` or yours), read
  by the node's own parser (:func:`bev_mapper_ros.config.node_config_from_params`, which
  imports no ROS): rig name, cameras, ``extrinsics.<camera>``, the topic patterns
  ``image_topic`` (with ``compressed: true`` its ``/compressed`` transport, as the node
  subscribes) / ``camera_info_topic``, ``base_frame`` and the grid.

The bag's own data wins where it has it: its CameraInfo over a preset's intrinsics, its
``/tf_static`` over given extrinsics. The flags' rig name wins over the bag's metadata key.
Without a name from either, a bag whose cameras and calibration match a preset's takes the
preset's name (:func:`matching_preset`), so the shipped weights apply whatever the bag's
directory is called; else the rig is named after the bag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import PRESETS, Rig, preset_rig

from ..errors import BagError
from . import topics as T

#: What to say wherever a bag's rig cannot be worked out.
RIG_FLAGS_HINT = ("give the rig with --rig NAME (a preset: " + ", ".join(PRESETS)
                  + ") or --params-file FILE (the node's parameter file: cameras, topics, extrinsics, grid)")
#: A bag's calibration matches a preset's within these: metres, degrees, and the intrinsics
#: (focal lengths and principal point as fractions of the image size).
MATCH_TRANSLATION_M, MATCH_ROTATION_DEG, MATCH_INTRINSICS = 0.05, 1.0, 0.01
#: The node's parameter file is at most this big (a parameter file is a few kilobytes).
MAX_PARAMS_FILE_BYTES = 1 << 20


class RigFlagError(BagError):
    """``--rig`` / ``--params-file`` cannot be used (unknown file, not the node's parameters)."""


@dataclass(frozen=True)
class RigChoice:
    """The user's flags about a bag's rig (``bev-bag replay`` / ``evaluate``).

    Args:
        name: ``--rig``: a preset or any name ('' = none).
        params_file: ``--params-file``: the node's parameter YAML (``None`` = none).
        node_name: the node whose section of the file applies (``/**`` always does).
    """

    name: str = ""
    params_file: Path | None = None
    node_name: str = "bev_mapper"

    def hints(self) -> "RigHints | None":
        """Resolve the flags (``None`` when none is given).

        Raises:
            RigFlagError: the parameter file is unusable (naming it and why).
        """
        if not self.name and self.params_file is None:
            return None
        hints = RigHints(name=self.name, source=f"--rig {self.name}" if self.name else "")
        if self.params_file is not None:
            hints = _from_params_file(Path(self.params_file), self.node_name, self.name)
        if hints.name in PRESETS:
            hints = hints.with_preset(preset_rig(hints.name))
        return hints


@dataclass(frozen=True)
class RigHints:
    """What the user says about a bag's rig (see module docstring).

    Attributes:
        name: the rig's name ('' = none given).
        cameras: camera names in rig order (empty: the bag's cameras, in its topic order).
        extrinsics: camera -> ``ego_from_cam`` 4x4, used where ``/tf_static`` has none.
        intrinsics: camera -> :class:`CameraModel`, used where the bag has no CameraInfo.
        image_topics: input kind -> topic pattern with ``{camera}``.
        camera_info_topic: CameraInfo topic pattern with ``{camera}``.
        base_frame: the ego frame of the extrinsics ('' = the reader's).
        grid: the grid of a bag without GT (``None``: not given).
        ego_masks: camera -> path of its ego-body mask PNG (the file's ``ego_mask.<camera>``).
        source: the flags, as the messages name them.
    """

    name: str = ""
    cameras: tuple[str, ...] = ()
    extrinsics: dict = field(default_factory=dict)
    intrinsics: dict = field(default_factory=dict)
    image_topics: dict = field(default_factory=lambda: {k: T.image_topic("{camera}", k) for k in T.IMAGE_KINDS})
    camera_info_topic: str = T.camera_info_topic("{camera}")
    base_frame: str = ""
    grid: BevGrid | None = None
    source: str = ""
    ego_masks: dict = field(default_factory=dict)

    def with_preset(self, rig: Rig) -> "RigHints":
        """These hints completed by a preset rig: its cameras (when none are given), and the
        extrinsics and intrinsics of those of its cameras not given otherwise.
        """
        cameras = self.cameras or rig.names
        ext = {c.name: c.ego_from_cam_array for c in rig.cameras if c.name in cameras}
        ext.update(self.extrinsics)
        intr = {c.name: c.model for c in rig.cameras if c.name in cameras}
        intr.update(self.intrinsics)
        return RigHints(self.name, tuple(cameras), ext, intr, dict(self.image_topics), self.camera_info_topic,
                        self.base_frame, self.grid, self.source, dict(self.ego_masks))


def _from_params_file(path: Path, node_name: str, rig_flag: str) -> RigHints:
    """:class:`RigHints` from the node's parameter file (``rig_flag`` overrides its ``rig``)."""
    from bev_mapper_ros.config import DEFAULT_TOPICS, node_config_from_params  # noqa: PLC0415 - ROS-free

    params = read_params_file(path, node_name)
    if rig_flag:
        params["rig"] = rig_flag
    try:
        cfg = node_config_from_params(params)
    except BevMapperError as exc:
        raise RigFlagError(f"--params-file {path}: {exc}") from None
    kind = cfg.mapper.input_kind
    topics = dict(DEFAULT_TOPICS)
    topics[kind] = cfg.image_topic or topics[kind]
    if cfg.compressed:  # the node's subscription: <image_topic>/compressed
        topics[kind] = T.compressed_topic(topics[kind])
    has_grid = any(k.startswith("grid.") for k in params)
    return RigHints(name=cfg.rig, cameras=cfg.cameras, extrinsics=dict(cfg.extrinsics), image_topics=topics,
                    camera_info_topic=cfg.camera_info_topic, base_frame=cfg.base_frame,
                    grid=cfg.grid if has_grid else None, source=f"--params-file {path}",
                    ego_masks=dict(cfg.ego_masks))


def read_params_file(path: Path, node_name: str) -> dict:
    """The flat parameters (``grid.x_min``, ``extrinsics.front``) a ROS 2 parameter file gives
    ``node_name``: its ``/**`` section, then the node's own (``name`` or ``/ns/name``).

    Raises:
        RigFlagError: missing, not a file, too big, not YAML, or no ``ros__parameters``.
    """
    if not path.exists():
        raise RigFlagError(f"--params-file {path}: no such file")
    if not path.is_file():
        raise RigFlagError(f"--params-file {path}: not a regular file")
    if path.stat().st_size > MAX_PARAMS_FILE_BYTES:
        raise RigFlagError(f"--params-file {path}: larger than {MAX_PARAMS_FILE_BYTES} bytes; not a parameter file")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError) as exc:
        why = exc.strerror if isinstance(exc, OSError) else " ".join(str(exc).split())[:200]
        raise RigFlagError(f"--params-file {path}: cannot be read as YAML: {why}") from None
    sections = [v for k, v in (doc.items() if isinstance(doc, dict) else ())
                if str(k) in ("/**", node_name) or str(k).rsplit("/", 1)[-1] == node_name]
    params: dict = {}
    for section in sections:
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            params.update(_flatten(section["ros__parameters"]))
    if not params:
        raise RigFlagError(f"--params-file {path}: no '/**' or {node_name!r} section with ros__parameters "
                           "(the node's parameter file, e.g. config/surround6.yaml)")
    return params


def _flatten(d: dict, prefix: str = "", depth: int = 0) -> dict:
    """``{'grid': {'x_min': 1}}`` -> ``{'grid.x_min': 1}`` (ROS's nested parameter names)."""
    if depth > 8:
        raise RigFlagError(f"parameters nested deeper than 8 levels at {prefix!r}")
    out = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, name + ".", depth + 1))
        else:
            out[name] = v
    return out


def matching_preset(rig: Rig) -> str | None:
    """The preset whose cameras (by name) and calibration ``rig`` has, else ``None``.

    Extrinsics within :data:`MATCH_TRANSLATION_M` / :data:`MATCH_ROTATION_DEG`; intrinsics
    compared as fractions of each image's size (within :data:`MATCH_INTRINSICS`), so a bag of
    full-resolution images matches a preset that delivers them binned.
    """
    for name in PRESETS:
        preset = preset_rig(name)
        if set(preset.names) != set(rig.names):
            continue
        if all(_same_camera(rig[c.name], c) for c in preset.cameras):
            return name
    return None


def _same_camera(a, b) -> bool:
    Ta, Tb = a.ego_from_cam_array, b.ego_from_cam_array
    if np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) > MATCH_TRANSLATION_M:
        return False
    cos = (np.trace(Ta[:3, :3].T @ Tb[:3, :3]) - 1.0) / 2.0
    if math.degrees(math.acos(max(-1.0, min(1.0, cos)))) > MATCH_ROTATION_DEG:
        return False
    return np.allclose(_relative_intrinsics(a.model), _relative_intrinsics(b.model), atol=MATCH_INTRINSICS)


def _relative_intrinsics(model: CameraModel) -> np.ndarray:
    """``(fx / W, fy / H, cx / W, cy / H)`` of the delivered images."""
    W, H = model.image_size
    K = model.effective().K_array
    return np.array([K[0, 0] / W, K[1, 1] / H, K[0, 2] / W, K[1, 2] / H])
