"""``bev-bag info BAG``: what a bag holds, as the bev_mapper tools see it.

Topics with type, message count and rate; the cameras found, each with its calibration
(image size, distortion model, focal lengths) and whether ``/tf_static`` connects its optical
frame to the ego frame; the GT layers and their grid; the duration. Works on rosbag2
directories (mcap, sqlite3) and plain ``.mcap`` / ``.db3`` files; a damaged bag is described
up to the damage, with a note. Topics whose type differs from the one their name calls for
(``/odom`` carrying images, ...) are listed and not decoded. A camera's images may be
``sensor_msgs/CompressedImage`` on its image topic or on ``<image topic>/compressed`` (said as
``(compressed)``); GT layers of classes this package does not define are listed as skipped. Exit status 1 for a damaged bag
or topics of the wrong type (after printing the description).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from bev_mapper_core.errors import BevMapperError
from msg_adapters import TfTree, camera_info_to_model

from ..errors import BagCorruptError
from ..io import topics as T
from ..io.input_checks import DECODE_ERRORS, expected_type
from ..io.reader import BagReader

HELP = "describe a bag: topics, cameras and calibration, GT layers, duration"


def _storage(path: Path) -> str:
    files = [path] if path.is_file() else sorted(path.iterdir())
    for f in files:
        if f.suffix == ".mcap":
            return "mcap" if path.is_dir() else "mcap file"
        if f.suffix == ".db3":
            return "sqlite3" if path.is_dir() else "sqlite3 file"
    return "unknown"


def _times(reader: BagReader) -> tuple[dict[str, list[int]], str | None]:
    """Per topic ``[first_ns, last_ns, count]`` from a pass over the bag; and a damage note.

    Intact bags are scanned without deserializing (rosbags raw messages); damaged ones through
    the reader's stream fallback, up to the damage.
    """
    times: dict[str, list[int]] = {}

    def see(topic: str, t: int) -> None:
        rec = times.setdefault(topic, [t, t, 0])
        rec[0], rec[1], rec[2] = min(rec[0], t), max(rec[1], t), rec[2] + 1

    try:
        if reader.damage is None:
            from rosbags.highlevel import AnyReader  # noqa: PLC0415

            with AnyReader([reader.path]) as raw:
                try:
                    for conn, t, _ in raw.messages():
                        if t < 0:
                            raise ValueError(f"{conn.topic} has the negative log time {t}")
                        see(conn.topic, int(t))
                except Exception as exc:  # storage errors mid-file are damage
                    raise BagCorruptError(f"{reader.path}: damaged: {type(exc).__name__}: {exc}") from None
        else:
            for m in reader.messages():
                see(m.topic, m.log_ns)
    except BagCorruptError as exc:
        return times, str(exc)
    return times, reader.damage


def _calibration(reader: BagReader) -> tuple[list[dict], list[str]]:
    """Per camera: first CameraInfo's model and whether /tf_static gives its extrinsics."""
    names = reader.camera_names
    infos: dict[str, Any] = {}
    tree = TfTree()
    problems = []
    wanted = {t for t in {T.camera_info_topic(n) for n in names} | {T.TF_STATIC}
              if t in reader.topics and reader.topics[t].msgtype == expected_type(t)}
    try:
        for m in reader.messages(wanted):
            if m.topic == T.TF_STATIC:
                try:
                    tree.add_message(m.msg)
                except (BevMapperError, *DECODE_ERRORS) as exc:
                    problems.append(f"/tf_static: {exc}")
            else:
                infos.setdefault(T.parse_camera_topic(m.topic)[0], m.msg)
    except BagCorruptError:
        pass  # reported by the time scan
    cams = []
    for n in reader.uncalibrated_cameras:
        cams.append({"name": n, "calibration": None, "extrinsics": None, **_images(reader, n),
                     "problem": "images but no camera_info topic"})
    for n in names:
        cam: dict[str, Any] = {"name": n, "calibration": None, "extrinsics": None, **_images(reader, n)}
        msg = infos.get(n)
        if msg is None:
            cam["problem"] = "no CameraInfo message"
            cams.append(cam)
            continue
        try:
            frame = str(msg.header.frame_id).lstrip("/")
            cam["frame_id"] = frame
            model = camera_info_to_model(msg)
            w, h = model.image_size
            K = model.effective().K_array
            cam["calibration"] = {"width": w, "height": h, "model": model.distortion_model,
                                  "fx": round(float(K[0, 0]), 3), "fy": round(float(K[1, 1]), 3),
                                  "cx": round(float(K[0, 2]), 3), "cy": round(float(K[1, 2]), 3)}
        except (BevMapperError, *DECODE_ERRORS) as exc:
            cam["problem"] = str(exc)
        try:
            M = tree.lookup(reader.ego_frame, cam["frame_id"])
            cam["extrinsics"] = {"xyz": [round(float(v), 4) for v in M[:3, 3]]}
        except (KeyError, BevMapperError, *DECODE_ERRORS):
            cam["extrinsics"] = None
        cams.append(cam)
    return cams, problems


def _images(reader: BagReader, camera: str) -> dict[str, list[str]]:
    """``images``: the image kinds the bag has of ``camera`` (as Image or CompressedImage, on the
    image topic or its ``/compressed`` transport); ``compressed``: those of them compressed.
    """
    kinds = [k for k in T.IMAGE_KINDS if reader.image_topic(camera, k) in reader.topics]
    return {"images": kinds, "compressed": [k for k in kinds if reader.is_compressed(reader.image_topic(camera, k))]}


#: A camera with fewer images of a kind than this share of the camera with the most is said to
#: be thinned out (``bev-bag info``'s problems).
THIN_SHARE = 0.9


def _thin_cameras(reader: BagReader, names: list[str], counts: dict[str, int]) -> list[str]:
    """Problems: a camera with no images, or far fewer than the others, of a kind some camera has
    (replay then maps sets without it: ``metrics.json`` ``sync``).
    """
    out = []
    for kind in T.IMAGE_KINDS:
        n = {c: counts.get(reader.image_topic(c, kind), 0) for c in names}
        most = max(n.values(), default=0)
        for c, k in n.items():
            if most and k < THIN_SHARE * most:
                what = "no" if k == 0 else f"only {k}"
                out.append(f"camera {c!r} has {what} {kind} images, the others up to {most}: replay maps "
                           f"{most - k} set(s) without it (metrics.json: sync)")
    return out


def describe(path: Path) -> dict:
    """Everything ``bev-bag info`` prints, as a JSON-able dict."""
    with BagReader(path) as reader:
        times, damage = _times(reader)
        topics = []
        for name, s in sorted(reader.topics.items()):
            first, last, n = times.get(name, [None, None, 0])
            rate = (n - 1) * 1e9 / (last - first) if n > 1 and last > first else None
            topics.append({"topic": name, "type": s.msgtype, "count": n if damage else s.count,
                           "rate_hz": None if rate is None else round(rate, 3)})
        cams, problems = _calibration(reader)
        counts = {t["topic"]: t["count"] for t in topics}
        problems += _thin_cameras(reader, [c["name"] for c in cams if c["calibration"]], counts)
        wrong_types = reader.type_problems
        gt = list(reader.gt_classes)
        grid = None
        if gt:
            try:
                grid = reader.grid()
            except BevMapperError as exc:
                if not wrong_types:
                    problems.append(str(exc))
        starts = [v[0] for v in times.values()]
        ends = [v[1] for v in times.values()]
        return {
            "bag": str(path),
            "storage": _storage(path),
            "messages": sum(v[2] for v in times.values()),
            "start_ns": min(starts) if starts else None,
            "duration_s": round((max(ends) - min(starts)) / 1e9, 6) if starts else 0.0,
            "topics": topics,
            "cameras": cams,
            "ego_frame": reader.ego_frame,
            "gt_layers": gt,
            "skipped_gt_layers": list(reader.unknown_gt_classes),
            "gt_grid": grid.to_dict() if grid is not None else None,
            "ground_visibility": T.GROUND_VISIBILITY in reader.topics,
            "any_visibility": T.ANY_VISIBILITY in reader.topics,
            "truth_layers": list(reader.truth_classes),
            "odometry": T.ODOM in reader.topics,
            "custom_data": reader.custom_data,
            "damage": damage,
            "wrong_types": wrong_types,
            "problems": problems,
        }


def format_info(d: dict) -> str:
    """Human-readable text of :func:`describe`'s dict."""
    lines = [f"bag:        {d['bag']} ({d['storage']})",
             f"duration:   {d['duration_s']:.3f} s, {d['messages']} messages"]
    if d["custom_data"]:
        lines.append("custom:     " + ", ".join(f"{k}={v}" for k, v in d["custom_data"].items()
                                                if len(v) < 40))
    tw = max([5] + [len(t["topic"]) for t in d["topics"]])
    yw = max([4] + [len(t["type"]) for t in d["topics"]])
    lines += ["", f"topics ({len(d['topics'])}):",
              f"  {'topic':<{tw}}  {'type':<{yw}}  {'count':>6}  {'rate Hz':>8}"]
    for t in d["topics"]:
        rate = "-" if t["rate_hz"] is None else f"{t['rate_hz']:.2f}"
        lines.append(f"  {t['topic']:<{tw}}  {t['type']:<{yw}}  {t['count']:>6}  {rate:>8}")
    lines += ["", f"cameras ({len(d['cameras'])}), extrinsics {d['ego_frame']} <- optical frame:"]
    for c in d["cameras"]:
        cal = c["calibration"]
        text = (f"{cal['width']}x{cal['height']} {cal['model']} fx {cal['fx']} fy {cal['fy']}"
                if cal else f"NO CALIBRATION ({c.get('problem', '?')})")
        ext = "extrinsics in /tf_static" if c["extrinsics"] else "NO extrinsics in /tf_static"
        frame = c.get("frame_id", "?")
        images = [f"{k} (compressed)" if k in c.get("compressed", ()) else k for k in c["images"]]
        lines.append(f"  {c['name']:<12} {text}; frame {frame}; {ext}; "
                     f"images: {', '.join(images) or 'none'}")
    if not d["cameras"]:
        lines.append("  none (no /cameras/<name>/camera_info topics)")
    lines.append("")
    if d["gt_layers"]:
        g = d["gt_grid"]
        grid = (f"{round((g['x_max'] - g['x_min']) / g['resolution'])}x"
                f"{round((g['y_max'] - g['y_min']) / g['resolution'])} cells at {g['resolution']} m, "
                f"x [{g['x_min']}, {g['x_max']}] y [{g['y_min']}, {g['y_max']}]") if g else "?"
        lines.append(f"GT layers ({len(d['gt_layers'])}): {', '.join(d['gt_layers'])}")
        lines.append(f"GT grid:    {grid}")
        lines.append(f"ground visibility layer: {'yes' if d['ground_visibility'] else 'no'}")
        lines.append(f"any visibility layer:    {'yes' if d.get('any_visibility') else 'no'}")
        truth = d.get("truth_layers") or []
        lines.append(f"full-truth layers ({len(truth)}): {', '.join(truth) or 'none'}")
    else:
        lines.append("GT layers:  none")
    if d.get("skipped_gt_layers"):
        lines.append(f"GT layers of unknown classes (skipped by replay): {', '.join(d['skipped_gt_layers'])}")
    lines.append(f"odometry:   {'yes' if d['odometry'] else 'no'}")
    for p in d["wrong_types"]:
        lines.append(f"WRONG TYPE: {p}")
    for p in d["problems"]:
        lines.append(f"problem:    {p}")
    if d["damage"]:
        lines.append(f"DAMAGED:    {d['damage']}")
    return "\n".join(lines)


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag info``."""
    p.add_argument("bag", type=Path, help="rosbag2 directory, .mcap or .db3 file")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag info``; exit 1 (after printing) when the bag is damaged or has topics of
    the wrong type.
    """
    d = describe(args.bag)
    print(json.dumps(d, indent=2) if args.json else format_info(d))
    if d["wrong_types"]:
        print(f"error: {args.bag}: " + "; ".join(d["wrong_types"]), file=sys.stderr)
    if d["damage"]:
        print(f"error: {d['damage']}", file=sys.stderr)
    return 1 if d["damage"] or d["wrong_types"] else 0
