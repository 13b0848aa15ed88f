"""Safe reading of a rosbag2 ``metadata.yaml``.

The file is untrusted input, read before any storage file is touched, so it is read with
limits:

* at most :data:`MAX_METADATA_BYTES` bytes, UTF-8 text;
* parsed with PyYAML's safe loader into a node graph first; aliases are allowed (some YAML
  writers emit them for repeated values), but the document expanded through its aliases may
  hold at most :data:`MAX_METADATA_NODES` nodes: a 1 KB "billion laughs" alias bomb expands
  to 9**9 strings and is refused before anything is built from it (recursive aliases too);
* schema-checked: a mapping with a ``rosbag2_bagfile_information`` mapping holding the keys
  rosbag2 and rosbags rely on, with the right types (:func:`check_schema`), and
  ``custom_data`` a mapping of strings to strings.

:func:`read_metadata` returns the ``rosbag2_bagfile_information`` mapping, or raises
:class:`MetadataError` saying what is wrong.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import BagFormatError

#: Largest metadata.yaml read (bytes); rosbag2 writes ~1 KB per topic.
MAX_METADATA_BYTES = 4 << 20
#: Most YAML nodes the document may expand to through its aliases.
MAX_METADATA_NODES = 200_000

INFO_KEY = "rosbag2_bagfile_information"


class MetadataError(BagFormatError):
    """``metadata.yaml`` is unreadable, too large, an alias bomb or not rosbag2 metadata."""


def _loader():
    import yaml

    return getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _expanded_nodes(root) -> int:
    """Number of nodes of the document with every alias expanded (memoized, cycle-safe)."""
    from yaml.nodes import MappingNode, SequenceNode

    sizes: dict[int, int] = {}
    active: set[int] = set()
    stack: list[tuple[Any, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        nid = id(node)
        if done:
            if isinstance(node, MappingNode):
                kids = [n for kv in node.value for n in kv]
            else:
                kids = node.value
            sizes[nid] = min(1 + sum(sizes[id(k)] for k in kids), 1 << 62)
            active.discard(nid)
            continue
        if nid in sizes:
            continue
        if not isinstance(node, (MappingNode, SequenceNode)):
            sizes[nid] = 1
            continue
        if nid in active:
            raise MetadataError("recursive YAML alias")
        active.add(nid)
        stack.append((node, True))
        kids = [n for kv in node.value for n in kv] if isinstance(node, MappingNode) else node.value
        stack.extend((k, False) for k in kids if id(k) not in sizes)
    return sizes[id(root)]


def parse_yaml(data: bytes, name: str = "metadata.yaml") -> Any:
    """Parse bounded, alias-bomb-safe YAML bytes (see module docstring)."""
    import yaml

    if len(data) > MAX_METADATA_BYTES:
        raise MetadataError(f"{name} is {len(data)} bytes, more than the {MAX_METADATA_BYTES} "
                            "a rosbag2 metadata file can need")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MetadataError(f"{name} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    loader = _loader()(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        n = _expanded_nodes(node)
        if n > MAX_METADATA_NODES:
            raise MetadataError(f"{name} expands through its YAML aliases to {n} nodes, more "
                                f"than the {MAX_METADATA_NODES} allowed (an alias bomb?)")
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        raise MetadataError(f"{name} is not valid YAML: {' '.join(str(exc).split())}") from None
    finally:
        loader.dispose()


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _expect(where: str, value: Any, kind: str) -> None:
    ok = {"int": _is_int(value), "str": isinstance(value, str),
          "list": isinstance(value, list), "map": isinstance(value, dict)}[kind]
    if not ok:
        names = {"int": "an integer", "str": "a string", "list": "a list", "map": "a mapping"}
        raise MetadataError(f"metadata.yaml: {where} is {type(value).__name__} "
                            f"{_short(value)}, expected {names[kind]}")


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


_REQUIRED = {"version": "int", "storage_identifier": "str", "relative_file_paths": "list",
             "duration": "map", "starting_time": "map", "message_count": "int",
             "topics_with_message_count": "list"}
_OPTIONAL = {"compression_format": "str", "compression_mode": "str", "files": "list",
             "ros_distro": "str"}


def check_schema(doc: Any) -> dict:
    """The ``rosbag2_bagfile_information`` mapping of a parsed document, schema-checked."""
    if not isinstance(doc, dict):
        raise MetadataError(f"metadata.yaml holds a {type(doc).__name__}, expected a mapping")
    if INFO_KEY not in doc:
        raise MetadataError(f"metadata.yaml has no {INFO_KEY!r} key (keys: "
                            f"{_short(sorted(map(str, doc)))})")
    info = doc[INFO_KEY]
    _expect(INFO_KEY, info, "map")
    for key, kind in _REQUIRED.items():
        if key not in info:
            raise MetadataError(f"metadata.yaml: {INFO_KEY} lacks {key!r}")
        _expect(key, info[key], kind)
    for key, kind in _OPTIONAL.items():
        if info.get(key) is not None:
            _expect(key, info[key], kind)
    if not 1 <= info["version"] <= 9:
        raise MetadataError(f"metadata.yaml: unsupported rosbag2 version {info['version']}")
    _expect("duration.nanoseconds", info["duration"].get("nanoseconds"), "int")
    _expect("starting_time.nanoseconds_since_epoch",
            info["starting_time"].get("nanoseconds_since_epoch"), "int")
    for i, p in enumerate(info["relative_file_paths"]):
        _expect(f"relative_file_paths[{i}]", p, "str")
    for i, entry in enumerate(info["topics_with_message_count"]):
        where = f"topics_with_message_count[{i}]"
        _expect(where, entry, "map")
        _expect(f"{where}.message_count", entry.get("message_count"), "int")
        meta = entry.get("topic_metadata")
        _expect(f"{where}.topic_metadata", meta, "map")
        for key in ("name", "type", "serialization_format"):
            _expect(f"{where}.topic_metadata.{key}", meta.get(key), "str")
        qos = meta.get("offered_qos_profiles")
        if qos is not None and not isinstance(qos, (str, list)):
            _expect(f"{where}.topic_metadata.offered_qos_profiles", qos, "list")
    for i, entry in enumerate(info.get("files") or ()):
        _expect(f"files[{i}]", entry, "map")
        _expect(f"files[{i}].path", entry.get("path"), "str")
    custom = info.get("custom_data")
    if custom is not None:
        _expect("custom_data", custom, "map")
        for key, value in custom.items():
            _expect(f"custom_data key {_short(key)}", key, "str")
            _expect(f"custom_data[{key!r}]", value, "str")
    return info


def read_metadata(bag_dir: Path) -> dict | None:
    """The checked ``rosbag2_bagfile_information`` of ``bag_dir/metadata.yaml``; ``None`` when
    the file is missing or empty.

    Raises:
        MetadataError: unreadable, oversized, an alias bomb, or not rosbag2 metadata.
    """
    meta = Path(bag_dir) / "metadata.yaml"
    try:
        size = meta.stat().st_size
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise MetadataError(f"{meta}: {exc}") from None
    if size > MAX_METADATA_BYTES:
        raise MetadataError(f"metadata.yaml is {size} bytes, more than the "
                            f"{MAX_METADATA_BYTES} a rosbag2 metadata file can need")
    try:
        data = meta.read_bytes()
    except OSError as exc:
        raise MetadataError(f"{meta}: {exc}") from None
    doc = parse_yaml(data)
    if doc is None:
        return None
    return check_schema(doc)
