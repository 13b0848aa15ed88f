"""Label images from other segmenters: upstream ids (or palette colours) -> this package's :class:`Label`.

The mappers read label images in this package's own ids (:class:`~bev_mapper_core.labels.classes.Label`,
mono8). A :class:`LabelMap` converts what a real segmenter publishes into those ids with ONE
lookup table, applied once per image before any mapper sees it (the node and the bag tools do
that as they decode an image). :func:`label_map` resolves the ``label_map`` setting:

* ``native`` (the default): mono8 images of this package's :class:`Label` ids, passed through;
* ``cityscapes_ids``: mono8 Cityscapes ``labelIds`` 0..33;
* ``cityscapes_train_ids``: mono8 Cityscapes ``trainIds`` 0..18, 255 = ignore;
* ``cam2bev``: rgb8 colour-coded semantic images in Cam2BEV's palette (RGB order);
* the path of a YAML file (format below), mono8 ids or an rgb8 palette.

Cityscapes classes map onto :class:`Label` as: road, parking -> ROAD; sidewalk -> SIDEWALK;
car, truck, bus, caravan, trailer, train, motorcycle, bicycle -> VEHICLE; person, rider ->
PEDESTRIAN; building, wall -> BUILDING; fence, guard rail, pole, polegroup, traffic light,
traffic sign, static, dynamic -> OBSTACLE; vegetation, terrain, ground -> TERRAIN; everything
else (unlabeled, ego vehicle, rectification border, out of roi, rail track, bridge, tunnel, sky,
trainId 255) -> UNLABELED (there is no sky label; a bridge or tunnel does not stand on the
ground where it shows in the image). **Cityscapes has no lane-marking, crossing or curb class**:
markings are part of ``road``, so a Cityscapes segmenter never yields LANE_DIVIDER,
PED_CROSSING or ROAD_BOUNDARY, and the ``lane_divider``, ``ped_crossing`` and ``road_boundary``
layers stay empty (drivable, sidewalk, vehicle and pedestrian work). Cam2BEV's palette holds the
same classes in Cityscapes' colours and maps the same way.

YAML format (any other segmenter)::

    # mono8 label images: upstream id (0..255) -> label name
    encoding: mono8        # optional, mono8 is the default
    labels:
      0: road
      1: sidewalk
      13: vehicle

    # rgb8 label images (a colour palette): colour -> label name
    encoding: rgb8
    labels:
      "128,64,128": road   # "R,G,B", "R G B" or "#RRGGBB"
      "#F423E8": sidewalk

Label names are the :class:`Label` members in lower case (:data:`LABEL_NAMES`: ``road``,
``lane_divider``, ``ped_crossing``, ``road_boundary``, ``sidewalk``, ``vehicle``,
``pedestrian``, ``obstacle``, ``building``, ``terrain``, ``unlabeled``). Ids or colours the map
does not name become UNLABELED; an rgb8 colour must match exactly (no nearest colour: label
images must travel losslessly, raw or PNG, never JPEG). The file is read with limits
(a regular file of at most :data:`MAX_FILE_BYTES`, :data:`MAX_YAML_DEPTH` levels and
:data:`MAX_YAML_NODES` nodes, no YAML anchors or aliases, no duplicate keys; ids in ASCII decimal only); every defect is a
:class:`~bev_mapper_core.errors.ConfigError`.
"""

from __future__ import annotations

import functools
import os
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputError
from .classes import NUM_LABELS, Label

NATIVE = "native"
#: The preset names (the one source of the CLI choices and parameter texts), default first.
PRESET_NAMES: tuple[str, ...] = (NATIVE, "cityscapes_ids", "cityscapes_train_ids", "cam2bev")
#: Image encodings a label map expects.
LABEL_MAP_ENCODINGS: tuple[str, ...] = ("mono8", "rgb8")
#: Label names a YAML file may use (the :class:`Label` members, lower case).
LABEL_NAMES: tuple[str, ...] = tuple(m.name.lower() for m in Label)
#: Largest label-map YAML file read (bytes).
MAX_FILE_BYTES = 1 << 20
#: Most colours of an rgb8 palette.
MAX_PALETTE_COLORS = 4096
#: Deepest nesting of mappings and lists a label-map YAML file may have (the format needs 2).
MAX_YAML_DEPTH = 16
#: Most YAML nodes (scalars, mappings, lists) a label-map file may hold (a full palette and
#: ignore list need ~16,000).
MAX_YAML_NODES = 50_000
#: Longest text of a value quoted in an error message (characters).
MAX_QUOTE = 60
_BLOCK_PIXELS = 1 << 20

_U = Label
# Cityscapes (cityscapesScripts, cityscapesscripts/helpers/labels.py): name, labelId, trainId
# (255 = ignored in training) -> Label. The one place the Cityscapes semantics are written.
_CITYSCAPES: tuple[tuple[str, int, int, Label], ...] = (
    ("unlabeled", 0, 255, _U.UNLABELED), ("ego vehicle", 1, 255, _U.UNLABELED),
    ("rectification border", 2, 255, _U.UNLABELED), ("out of roi", 3, 255, _U.UNLABELED),
    ("static", 4, 255, _U.OBSTACLE), ("dynamic", 5, 255, _U.OBSTACLE), ("ground", 6, 255, _U.TERRAIN),
    ("road", 7, 0, _U.ROAD), ("sidewalk", 8, 1, _U.SIDEWALK), ("parking", 9, 255, _U.ROAD),
    ("rail track", 10, 255, _U.UNLABELED), ("building", 11, 2, _U.BUILDING), ("wall", 12, 3, _U.BUILDING),
    ("fence", 13, 4, _U.OBSTACLE), ("guard rail", 14, 255, _U.OBSTACLE), ("bridge", 15, 255, _U.UNLABELED),
    ("tunnel", 16, 255, _U.UNLABELED), ("pole", 17, 5, _U.OBSTACLE), ("polegroup", 18, 255, _U.OBSTACLE),
    ("traffic light", 19, 6, _U.OBSTACLE), ("traffic sign", 20, 7, _U.OBSTACLE),
    ("vegetation", 21, 8, _U.TERRAIN), ("terrain", 22, 9, _U.TERRAIN), ("sky", 23, 10, _U.UNLABELED),
    ("person", 24, 11, _U.PEDESTRIAN), ("rider", 25, 12, _U.PEDESTRIAN), ("car", 26, 13, _U.VEHICLE),
    ("truck", 27, 14, _U.VEHICLE), ("bus", 28, 15, _U.VEHICLE), ("caravan", 29, 255, _U.VEHICLE),
    ("trailer", 30, 255, _U.VEHICLE), ("train", 31, 16, _U.VEHICLE), ("motorcycle", 32, 17, _U.VEHICLE),
    ("bicycle", 33, 18, _U.VEHICLE),
)
_CITYSCAPES_LABEL = {name: label for name, _, _, label in _CITYSCAPES}
# Cam2BEV's input palette (RGB), from ika-rwth-aachen/Cam2BEV
# model/one_hot_conversion/convert_30.xml (every class of its semantic camera images, the
# ``fromColour`` attributes; Cam2BEV reads its PNGs as RGB, model/utils.py load_image). Names
# are Cityscapes', so the classes map as above. Unlike Cityscapes, it gives person
# (255, 0, 0) and rider (220, 20, 60); "static" is black. Its "occluded" (150, 150, 150) only
# occurs in the BEV ground truth and stays unmapped.
_CAM2BEV_PALETTE: tuple[tuple[str, tuple[int, int, int]], ...] = (
    ("static", (0, 0, 0)), ("dynamic", (111, 74, 0)), ("ground", (81, 0, 81)), ("road", (128, 64, 128)),
    ("sidewalk", (244, 35, 232)), ("parking", (250, 170, 160)), ("rail track", (230, 150, 140)),
    ("building", (70, 70, 70)), ("wall", (102, 102, 156)), ("fence", (190, 153, 153)),
    ("guard rail", (180, 165, 180)), ("bridge", (150, 100, 100)), ("tunnel", (150, 120, 90)),
    ("pole", (153, 153, 153)), ("polegroup", (153, 153, 153)), ("traffic light", (250, 170, 30)),
    ("traffic sign", (220, 220, 0)), ("vegetation", (107, 142, 35)), ("terrain", (152, 251, 152)),
    ("sky", (70, 130, 180)), ("person", (255, 0, 0)), ("rider", (220, 20, 60)), ("car", (0, 0, 142)),
    ("truck", (0, 0, 70)), ("bus", (0, 60, 100)), ("caravan", (0, 0, 90)), ("trailer", (0, 0, 110)),
    ("train", (0, 80, 100)), ("motorcycle", (0, 0, 230)), ("bicycle", (119, 11, 32)),
)


def pack_rgb(rgb) -> np.ndarray:
    """Colours ``(..., 3)`` uint8 -> packed ``0xRRGGBB`` uint32 ``(...)``."""
    a = np.asarray(rgb, dtype=np.uint32)
    return (a[..., 0] << 16) | (a[..., 1] << 8) | a[..., 2]


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LabelMap:
    """One lookup table from upstream label images to :class:`Label` ids.

    Attributes:
        name: the spec it came from (a preset name or the YAML path).
        encoding: the label images it expects: ``mono8`` (ids) or ``rgb8`` (a colour palette).
        table: mono8: ``(256,)`` uint8, the Label id of each upstream id. rgb8: ``(K,)`` uint8,
            the Label id of each colour in ``colors``.
        colors: rgb8: ``(K,)`` uint32 packed ``0xRRGGBB``, strictly ascending; mono8: empty.
            (Applied through a dense table over all 2^24 colours, built on first use: exact
            matches only, anything else is UNLABELED.)

    Raises:
        ConfigError: tables of the wrong shape, type or order, or ids that are no Label.
    """

    name: str
    encoding: str
    table: np.ndarray
    colors: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))

    def __post_init__(self) -> None:
        if self.encoding not in LABEL_MAP_ENCODINGS:
            raise ConfigError(f"label map {self.name!r}: encoding must be one of {list(LABEL_MAP_ENCODINGS)}, "
                              f"got {self.encoding!r}")
        table, colors = np.asarray(self.table), np.asarray(self.colors)
        if table.dtype != np.uint8 or table.ndim != 1 or (table >= NUM_LABELS).any():
            raise ConfigError(f"label map {self.name!r}: the table must be uint8 Label ids (< {NUM_LABELS})")
        if self.encoding == "mono8":
            if table.shape != (256,) or colors.size:
                raise ConfigError(f"label map {self.name!r}: a mono8 table has 256 entries and no colours")
        elif colors.dtype != np.uint32 or colors.shape != table.shape or not 0 < colors.size <= MAX_PALETTE_COLORS \
                or (np.diff(colors.astype(np.int64)) <= 0).any() or (colors > 0xFFFFFF).any():
            raise ConfigError(f"label map {self.name!r}: an rgb8 map needs 1..{MAX_PALETTE_COLORS} ascending "
                              "packed colours, one Label id each")
        object.__setattr__(self, "table", _frozen(table))
        object.__setattr__(self, "colors", _frozen(colors))
        object.__setattr__(self, "_passthrough", self.encoding == "mono8" and bool(
            np.array_equal(table, _native_table())))

    @property
    def passthrough(self) -> bool:
        """True for the native table: :meth:`apply` returns the image itself (ids >=
        NUM_LABELS, which the table sends to UNLABELED, already mean unlabeled to every mapper).
        """
        return self._passthrough

    def apply(self, image) -> np.ndarray:
        """Upstream label image -> ``(H, W)`` uint8 :class:`Label` ids (unmapped: UNLABELED).

        Args:
            image: mono8 maps: ``(H, W)`` uint8 ids; rgb8 maps: ``(H, W, 3)`` uint8 RGB.

        Raises:
            InputError: the image has another shape or dtype.
        """
        img = np.asarray(image)
        if self.encoding == "mono8":
            if img.ndim != 2 or img.dtype != np.uint8:
                raise InputError(f"label map {self.name!r} takes (H, W) uint8 mono8 label images, "
                                 f"got shape {img.shape} {img.dtype}")
            return img if self.passthrough else self.table[img]
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise InputError(f"label map {self.name!r} takes (H, W, 3) uint8 rgb8 label images, "
                             f"got shape {img.shape} {img.dtype}")
        lut = self._dense()
        out = np.empty(img.shape[:2], np.uint8)
        rows = max(1, _BLOCK_PIXELS // max(1, img.shape[1]))  # bounded temporaries, also for 8K images
        for r in range(0, img.shape[0], rows):
            block = img[r:r + rows]
            packed = block[..., 0].astype(np.uint32) << 16  # (h, W, 3) -> (h, W) 0xRRGGBB
            packed |= block[..., 1].astype(np.uint32) << 8
            packed |= block[..., 2]
            out[r:r + rows] = lut[packed]
        return out

    def _dense(self) -> np.ndarray:
        """rgb8: the table spread over every 24-bit colour (16 MiB, built on first use): one
        lookup per pixel, 10-20x faster than a search among the palette colours.
        """
        lut = getattr(self, "_lut", None)
        if lut is None:
            lut = np.full(1 << 24, Label.UNLABELED, np.uint8)
            lut[self.colors] = self.table
            object.__setattr__(self, "_lut", lut)
        return lut

    def to_dict(self) -> dict:
        """The YAML file's mapping (see the module docstring); unmapped entries are left out."""
        if self.encoding == "mono8":
            labels = {int(i): LABEL_NAMES[v] for i, v in enumerate(self.table) if v != Label.UNLABELED}
        else:
            labels = {f"{c >> 16},{(c >> 8) & 255},{c & 255}": LABEL_NAMES[v]
                      for c, v in zip(self.colors.tolist(), self.table.tolist())}
        return {"encoding": self.encoding, "labels": labels}


@functools.lru_cache(maxsize=1)
def _native_table() -> np.ndarray:
    t = np.arange(256, dtype=np.uint8)
    t[NUM_LABELS:] = Label.UNLABELED
    return _frozen(t)


def _mono8(name: str, pairs) -> LabelMap:
    table = np.full(256, Label.UNLABELED, np.uint8)
    for upstream, label in pairs:
        table[upstream] = label
    return LabelMap(name, "mono8", table)


def _rgb8(name: str, pairs) -> LabelMap:
    entries: dict[int, int] = {}
    for color, label in pairs:
        entries[int(pack_rgb(color))] = int(label)
    keys = sorted(entries)
    return LabelMap(name, "rgb8", np.array([entries[k] for k in keys], np.uint8), np.array(keys, np.uint32))


@functools.cache
def _preset(name: str) -> LabelMap:
    if name == NATIVE:
        return LabelMap(NATIVE, "mono8", _native_table())
    if name == "cityscapes_ids":
        return _mono8(name, ((i, lab) for _, i, _, lab in _CITYSCAPES))
    if name == "cityscapes_train_ids":
        return _mono8(name, ((t, lab) for _, _, t, lab in _CITYSCAPES if t != 255))
    if name == "cam2bev":
        return _rgb8(name, ((rgb, _CITYSCAPES_LABEL[n]) for n, rgb in _CAM2BEV_PALETTE))
    raise ConfigError(f"unknown label map preset {name!r}; presets: {list(PRESET_NAMES)}")


def quote(value) -> str:
    """``repr(value)``, cut to :data:`MAX_QUOTE` characters: an error message stays one short
    line whatever a file holds.
    """
    text = repr(value)
    return text if len(text) <= MAX_QUOTE else f"{text[:MAX_QUOTE - 12]}...({len(text)} chars)"


def file_kind(path: Path) -> str | None:
    """What ``path`` is (``"file"``, ``"directory"``, ``"FIFO"``, ``"device"``, ``"socket"``),
    following links; None when nothing is there (or it cannot be looked at).
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "directory"
    if stat.S_ISFIFO(mode):
        return "FIFO"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "device"
    return "socket" if stat.S_ISSOCK(mode) else "special file"


def label_map(spec: str) -> LabelMap:
    """The :class:`LabelMap` a ``label_map`` setting names: a preset (:data:`PRESET_NAMES`) or
    the path of a YAML file (see the module docstring).

    Raises:
        ConfigError: neither a preset nor a readable, valid label-map file.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"label_map must be one of {list(PRESET_NAMES)} or the path of a YAML file, "
                          f"got {quote(spec)}")
    if spec in PRESET_NAMES:
        return _preset(spec)
    path = Path(spec).expanduser()
    if file_kind(path) is None:
        raise ConfigError(f"label_map {quote(spec)} is no preset ({', '.join(PRESET_NAMES)}) and no such file "
                          "exists (a YAML file of upstream id -> label name)")
    return load_label_map(path, name=spec)


def read_yaml_document(path: Path, where: str):
    """The YAML document of a label-map file (a regular file of at most ``MAX_FILE_BYTES``,
    UTF-8, safe loader, no anchors or aliases, no duplicate keys, at most :data:`MAX_YAML_DEPTH` levels and
    :data:`MAX_YAML_NODES` nodes; integers only in ASCII decimal, other number forms stay text);
    the one reader of label-map YAML, also for dataset folders. Bounded: a hostile file is
    refused within a fraction of a second.

    Raises:
        ConfigError: missing, no regular file (a directory, FIFO, device), unreadable, too
            large, not UTF-8, not valid YAML, too deep or too many nodes.
    """
    return _parse_yaml(_yaml_text(path, where), where)


def _yaml_text(path: Path, where: str) -> str:
    """The text of a regular file of at most ``MAX_FILE_BYTES``: opened without blocking (a
    FIFO never waits for a writer), checked on the open descriptor, read with a cap.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        raise ConfigError(f"cannot read {where}: {reason}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = file_kind(path) or "special file"
            raise ConfigError(f"{where} is a {kind}, not a file")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read {where}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(f"{where}: more than the {MAX_FILE_BYTES} bytes a label map may have")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{where} is not UTF-8 text") from None


_DECIMAL = re.compile(r"[-+]?[0-9]+", re.ASCII)


def _loader_class(where: str):
    """A safe YAML loader (libyaml's parser when present) whose integers are ASCII decimal only
    (``0x1F``, ``0o17``, ``1_000``, ``1:20`` stay text) and whose mappings refuse duplicate keys.
    """
    import yaml  # noqa: PLC0415 - only label-map files need it

    base = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

    class Loader(base):
        def construct_yaml_int(self, node):
            text = self.construct_scalar(node)
            return int(text, 10) if _DECIMAL.fullmatch(text) else text  # other forms stay text

        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                except TypeError:  # unhashable: the base class says so
                    break
                if duplicate:
                    raise ConfigError(f"{where}: key {quote(key)} appears twice")
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    Loader.add_constructor("tag:yaml.org,2002:int", Loader.construct_yaml_int)
    return Loader


def _check_events(text: str, where: str) -> None:
    """Walk the YAML event stream once (no objects built): refuse anchors and aliases, nesting deeper than
    :data:`MAX_YAML_DEPTH` and more than :data:`MAX_YAML_NODES` nodes, stopping at the first.
    """
    import yaml  # noqa: PLC0415

    depth = nodes = 0
    for ev in yaml.parse(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
        if isinstance(ev, yaml.AliasEvent):
            raise ConfigError(f"{where}: YAML aliases (*name) are not allowed in a label map")
        if isinstance(ev, yaml.NodeEvent) and ev.anchor is not None:  # the schema has no use for one
            raise ConfigError(f"{where}: YAML anchors (&{quote(ev.anchor)[1:-1]}, line {ev.start_mark.line + 1}) and "
                              "aliases are not allowed in a label map: write each entry out")
        if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise ConfigError(f"{where}: nested more than {MAX_YAML_DEPTH} levels deep "
                                  f"(line {ev.start_mark.line + 1})")
        elif isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1
        if isinstance(ev, yaml.NodeEvent):
            nodes += 1
            if nodes > MAX_YAML_NODES:
                raise ConfigError(f"{where}: more than {MAX_YAML_NODES} YAML nodes")


def _parse_yaml(text: str, where: str):
    """The YAML document of ``text``: bounded (:func:`_check_events`), then the strict loader."""
    import yaml  # noqa: PLC0415

    try:
        _check_events(text, where)
        return yaml.load(text, Loader=_loader_class(where))  # a SafeLoader subclass
    except yaml.YAMLError as exc:
        detail = " ".join(str(exc).split())
        if len(detail) > 200:
            detail = detail[:200] + "..."
        raise ConfigError(f"{where} is not valid YAML: {detail}") from None
    except RecursionError:  # not reached with the depth bound; never a traceback
        raise ConfigError(f"{where}: nested too deeply") from None


def load_label_map(path: str | Path, name: str | None = None) -> LabelMap:
    """Read a label-map YAML file (format: module docstring).

    Raises:
        ConfigError: unreadable, too large, not YAML, or not a label map (naming what is wrong).
    """
    path = Path(path)
    where = f"label map {path}"
    return label_map_from_dict(read_yaml_document(path, where), name or str(path), where)


_COLOR = re.compile(r"([0-9]{1,3}) *[, ] *([0-9]{1,3}) *[, ] *([0-9]{1,3})", re.ASCII)
_HEX = re.compile(r"#([0-9a-fA-F]{6})", re.ASCII)
_ID = re.compile(r"[0-9]{1,3}", re.ASCII)


def _color(key, where: str) -> tuple[int, int, int]:
    m = _COLOR.fullmatch(key.strip(" ")) if isinstance(key, str) else None
    if m:
        rgb = tuple(int(v, 10) for v in m.groups())
        if max(rgb) <= 255:
            return rgb
    m = _HEX.fullmatch(key.strip(" ")) if isinstance(key, str) else None
    if m:
        v = int(m.group(1), 16)
        return v >> 16, (v >> 8) & 255, v & 255
    raise ConfigError(f"{where}: colour {quote(key)} must be 'R,G,B' (0..255 each, ASCII digits), 'R G B' or "
                      "'#RRGGBB', quoted")


def _upstream_id(key, where: str) -> int:
    """An upstream id: an integer, or a quoted string of 1-3 ASCII digits; 0..255."""
    if isinstance(key, str) and _ID.fullmatch(key):
        key = int(key, 10)
    if isinstance(key, bool) or not isinstance(key, int) or not 0 <= key <= 255:
        raise ConfigError(f"{where}: upstream id {quote(key)} must be an integer 0..255 in ASCII decimal digits "
                          "(mono8)")
    return key


def _label(value, key, where: str) -> int:
    name = value.strip().lower() if isinstance(value, str) else None
    if name not in LABEL_NAMES:
        raise ConfigError(f"{where}: {quote(key)} maps to {quote(value)}, which is no label; "
                          f"labels: {', '.join(LABEL_NAMES)}")
    return LABEL_NAMES.index(name)


def label_map_from_dict(doc, name: str, where: str | None = None) -> LabelMap:
    """A :class:`LabelMap` from the YAML file's mapping (module docstring); ``where`` names the
    source in error messages.

    Raises:
        ConfigError: not such a mapping: unknown keys, a bad encoding, ids or colours, unknown
            label names, an id or colour given twice, or no entry at all.
    """
    where = where or f"label map {name!r}"
    if not isinstance(doc, dict):
        raise ConfigError(f"{where} must be a mapping with 'labels' (and optionally 'encoding'), got {type(doc).__name__}")
    unknown = sorted(map(str, set(doc) - {"encoding", "labels"}))
    if unknown:
        raise ConfigError(f"{where}: unknown keys {quote(unknown[:5])}; a label map has 'encoding' and 'labels'")
    encoding = doc.get("encoding", "mono8")
    if not isinstance(encoding, str) or encoding not in LABEL_MAP_ENCODINGS:
        raise ConfigError(f"{where}: encoding must be one of {list(LABEL_MAP_ENCODINGS)}, got {quote(encoding)}")
    labels = doc.get("labels")
    if not isinstance(labels, dict) or not labels:
        raise ConfigError(f"{where}: 'labels' must be a non-empty mapping of upstream "
                          f"{'id' if encoding == 'mono8' else 'colour'} -> label name")
    if encoding == "rgb8" and len(labels) > MAX_PALETTE_COLORS:
        raise ConfigError(f"{where}: {len(labels)} colours, more than {MAX_PALETTE_COLORS}")
    seen: dict = {}
    for key, value in labels.items():
        k = _upstream_id(key, where) if encoding == "mono8" else _color(key, where)
        if k in seen:
            raise ConfigError(f"{where}: {quote(key)} names the same {'id' if encoding == 'mono8' else 'colour'} "
                              f"as {quote(seen[k][0])}")
        seen[k] = (key, _label(value, key, where))
    pairs = [(k, lab) for k, (_, lab) in seen.items()]
    return _mono8(name, pairs) if encoding == "mono8" else _rgb8(name, pairs)


__all__ = [
    "LABEL_MAP_ENCODINGS",
    "LABEL_NAMES",
    "MAX_FILE_BYTES",
    "MAX_PALETTE_COLORS",
    "MAX_YAML_DEPTH",
    "MAX_YAML_NODES",
    "NATIVE",
    "PRESET_NAMES",
    "LabelMap",
    "label_map",
    "label_map_from_dict",
    "load_label_map",
    "file_kind",
    "pack_rgb",
    "quote",
    "read_yaml_document",
]
