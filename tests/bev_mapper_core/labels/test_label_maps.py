"""Label images from other segmenters (issue #12 part 4): the label maps of the core, their YAML
files, and the adapters that decode label images through them."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import yaml
from label_map_helpers import CITYSCAPES, L, all_native, equivalent_native, to_upstream
from rosbags.typesys import Stores, get_typestore

import msg_adapters as ma
from bev_mapper_core.errors import ConfigError, InputError
from bev_mapper_core.labels.classes import NUM_LABELS, Label
from bev_mapper_core.labels.label_maps import (
    LABEL_NAMES,
    MAX_FILE_BYTES,
    NATIVE,
    PRESET_NAMES,
    LabelMap,
    label_map,
    label_map_from_dict,
    load_label_map,
)
from bev_mapper_core.mapper import MapperConfig

FACTORY = ma.RosbagsFactory(get_typestore(Stores.ROS2_JAZZY))

# ------------------------------------------------------------------ presets
def test_preset_names_resolve_and_native_is_the_default():
    assert PRESET_NAMES[0] == NATIVE == MapperConfig.label_map
    for name in PRESET_NAMES:
        lm = label_map(name)
        assert lm.name == name and lm.encoding == ("rgb8" if name == "cam2bev" else "mono8")
        assert label_map(name) is lm  # presets are built once
        assert not lm.table.flags.writeable and (lm.table < NUM_LABELS).all()


@pytest.mark.parametrize("scheme, col", [("cityscapes_ids", 0), ("cityscapes_train_ids", 1)])
def test_cityscapes_ids_map_to_labels(scheme, col):
    lm = label_map(scheme)
    pairs = [(v[col], v[3]) for v in CITYSCAPES.values() if v[col] != 255]
    ids = np.array([[p[0] for p in pairs]], np.uint8)
    want = np.array([[p[1] for p in pairs]], np.uint8)
    np.testing.assert_array_equal(lm.apply(ids), want)
    # unmapped ids are unlabeled: beyond 33 (labelIds) / 18 (trainIds), and trainId 255
    unmapped = np.array([[34, 100, 254, 255]] if col == 0 else [[19, 33, 200, 255]], np.uint8)
    assert (lm.apply(unmapped) == L.UNLABELED).all()
    # Cityscapes has no lane-marking, crossing or curb class
    assert not set(lm.table.tolist()) & {L.LANE_DIVIDER, L.PED_CROSSING, L.ROAD_BOUNDARY}


def test_cam2bev_palette_image_maps_to_labels():
    lm = label_map("cam2bev")
    named = [(v[2], v[3]) for v in CITYSCAPES.values() if v[2] is not None]
    rgb = np.array([[c for c, _ in named]], np.uint8)  # (1, K, 3)
    np.testing.assert_array_equal(lm.apply(rgb), [[lab for _, lab in named]])
    # anything but an exact palette colour is unlabeled: off by one, Cam2BEV's BEV-only "occluded", ...
    odd = np.array([[(128, 64, 129), (150, 150, 150), (255, 255, 255), (1, 2, 3)]], np.uint8)
    assert (lm.apply(odd) == L.UNLABELED).all()
    # a large image (mapped in blocks of rows): every pixel as a per-pixel lookup says
    palette = {tuple(c): lab for c, lab in named}
    colors = np.array([c for c, _ in named] + [(1, 2, 3)], np.uint8)
    big = colors[np.random.default_rng(3).integers(0, len(colors), (1100, 1001))]  # > 2^20 px
    got = lm.apply(big)
    assert got.shape == (1100, 1001)
    for i, c in enumerate(colors):
        assert (got[(big == c).all(-1)] == palette.get(tuple(c), L.UNLABELED)).all(), i


def test_native_passes_images_through():
    lm = label_map(NATIVE)
    img = np.array([[0, 5, 10, 11, 200]], np.uint8)
    assert lm.passthrough and lm.apply(img) is img  # no copy, ids >= NUM_LABELS as they are ...
    assert (lm.table[NUM_LABELS:] == L.UNLABELED).all()  # ... which every mapper reads as unlabeled
    np.testing.assert_array_equal(lm.table[:NUM_LABELS], np.arange(NUM_LABELS))


@pytest.mark.parametrize("scheme", ["cityscapes_ids", "cityscapes_train_ids", "cam2bev"])
def test_upstream_images_give_the_equivalent_native_image(scheme):
    native = all_native()
    np.testing.assert_array_equal(label_map(scheme).apply(to_upstream(native, scheme)), equivalent_native(native))


def test_apply_refuses_images_of_the_wrong_shape():
    with pytest.raises(InputError, match=r"cityscapes_ids.*\(H, W\) uint8 mono8"):
        label_map("cityscapes_ids").apply(np.zeros((2, 3, 3), np.uint8))
    with pytest.raises(InputError, match="mono8"):
        label_map(NATIVE).apply(np.zeros((2, 3), np.uint16))
    with pytest.raises(InputError, match=r"cam2bev.*\(H, W, 3\) uint8 rgb8"):
        label_map("cam2bev").apply(np.zeros((2, 3), np.uint8))
    with pytest.raises(InputError, match="rgb8"):
        label_map("cam2bev").apply(np.zeros((2, 3, 4), np.uint8))


def test_label_map_dataclass_checks_its_tables():
    with pytest.raises(ConfigError, match="256 entries"):
        LabelMap("x", "mono8", np.zeros(10, np.uint8))
    with pytest.raises(ConfigError, match="Label ids"):
        LabelMap("x", "mono8", np.full(256, NUM_LABELS, np.uint8))
    with pytest.raises(ConfigError, match="ascending"):
        LabelMap("x", "rgb8", np.zeros(2, np.uint8), np.array([5, 3], np.uint32))
    with pytest.raises(ConfigError, match="encoding"):
        LabelMap("x", "rgb16", np.zeros(256, np.uint8))


# ------------------------------------------------------------------ YAML files
@pytest.mark.parametrize("name", PRESET_NAMES)
def test_yaml_round_trip_of_every_preset(tmp_path, name):
    lm = label_map(name)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(lm.to_dict()))
    back = label_map(str(path))
    assert back.name == str(path) and back.encoding == lm.encoding
    np.testing.assert_array_equal(back.table, lm.table)
    np.testing.assert_array_equal(back.colors, lm.colors)


def test_hand_written_yaml_files(tmp_path):
    mono = tmp_path / "ids.yaml"
    mono.write_text("# my segmenter\nlabels:\n  3: road\n  '4': Vehicle\n  9: unlabeled\n  250: pedestrian\n")
    lm = load_label_map(mono)
    assert lm.encoding == "mono8"
    np.testing.assert_array_equal(lm.apply(np.array([[3, 4, 9, 250, 0, 5]], np.uint8)),
                                  [[L.ROAD, L.VEHICLE, 0, L.PEDESTRIAN, 0, 0]])
    rgb = tmp_path / "palette.yaml"
    rgb.write_text('encoding: rgb8\nlabels:\n  "10,20,30": sidewalk\n  "#FF0000": vehicle\n  "1 2 3": lane_divider\n')
    lm = label_map(str(rgb))
    img = np.array([[(10, 20, 30), (255, 0, 0), (1, 2, 3), (10, 20, 31), (0, 0, 0)]], np.uint8)
    np.testing.assert_array_equal(lm.apply(img), [[L.SIDEWALK, L.VEHICLE, L.LANE_DIVIDER, 0, 0]])
    assert set(LABEL_NAMES) == {m.name.lower() for m in Label}


BAD_YAML = [
    ("labels: [1, 2", "not valid YAML"),
    ("- 1\n- 2\n", "must be a mapping"),
    ("labels: {1: road}\nencodign: mono8\n", "unknown keys"),
    ("encoding: mono16\nlabels: {1: road}\n", "encoding must be one of"),
    ("labels: {}\n", "non-empty mapping"),
    ("encoding: mono8\n", "non-empty mapping"),
    ("labels: {256: road}\n", "0..255"),
    ("labels: {-1: road}\n", "0..255"),
    ("labels: {true: road}\n", "0..255"),
    ("labels: {1.5: road}\n", "0..255"),
    ("labels: {'128,64,128': road}\n", "0..255"),
    ("labels: {1: roads}\n", "which is no label"),
    ("labels: {1: 7}\n", "which is no label"),
    ("labels: {1: road, 1: vehicle}\n", "appears twice"),
    ("labels: {1: road, '1': vehicle}\n", "same id"),
    ("encoding: rgb8\nlabels: {'300,0,0': road}\n", "must be 'R,G,B'"),
    ("encoding: rgb8\nlabels: {7: road}\n", "must be 'R,G,B'"),
    ("encoding: rgb8\nlabels: {'1,2,3': road, '#010203': vehicle}\n", "same colour"),
    ("encoding: rgb8\nlabels: {[1, 2, 3]: road}\n", "not valid YAML"),
    ("a: &x road\nlabels: {1: *x}\n", "aliases"),
]


@pytest.mark.parametrize("text, message", BAD_YAML)
def test_bad_yaml_files_are_clear_config_errors(tmp_path, text, message):
    path = tmp_path / "map.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        label_map(str(path))
    assert str(path) in str(info.value)


def test_bad_specs_and_files(tmp_path):
    for spec in ("", "   ", "cityscapes", str(tmp_path / "missing.yaml")):
        with pytest.raises(ConfigError, match="label_map"):
            label_map(spec)
    with pytest.raises(ConfigError, match="no such file"):
        label_map("cityscape_ids")  # a typo of a preset
    big = tmp_path / "big.yaml"
    big.write_text("labels:\n" + "  # padding\n" * (MAX_FILE_BYTES // 10))
    with pytest.raises(ConfigError, match="more than"):
        label_map(str(big))
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"labels: {1: road}\n\xff\xfe")
    with pytest.raises(ConfigError, match="UTF-8"):
        label_map(str(binary))
    with pytest.raises(ConfigError, match="is a directory, not a file"):
        label_map(str(tmp_path))  # a directory is named as such
    with pytest.raises(ConfigError, match="must be a mapping"):
        label_map_from_dict(None, "x")


def test_mapper_config_checks_the_label_map(tmp_path):
    assert MapperConfig().label_map == NATIVE
    assert MapperConfig(label_map="cam2bev").label_map == "cam2bev"
    with pytest.raises(ConfigError, match="no preset"):
        MapperConfig(label_map="cityscapes")
    with pytest.raises(ConfigError, match="applies to label images"):
        MapperConfig(method="bimapper", input_kind="rgb", label_map="cityscapes_ids")
    bad = tmp_path / "bad.yaml"
    bad.write_text("labels: {1: nothing}\n")
    with pytest.raises(ConfigError, match="which is no label"):
        MapperConfig(label_map=str(bad))


def test_train_config_takes_a_label_map_for_bags_only():
    from bev_mapper_core.training.config import TrainConfig

    assert TrainConfig().label_map == MapperConfig.label_map
    assert TrainConfig(bag=("b",), val_bag=("v",), label_map="cityscapes_ids").label_map == "cityscapes_ids"
    with pytest.raises(ConfigError, match="label images of bags"):
        TrainConfig(label_map="cityscapes_ids")
    with pytest.raises(ConfigError, match="no preset"):
        TrainConfig(bag=("b",), label_map="nope")


# ------------------------------------------------------------------ adapters
def _msg(array, encoding):
    return ma.make_image(FACTORY, array, encoding, 0, "cam")


def _png(array) -> object:
    arr = array if array.ndim == 2 else cv2.cvtColor(array, cv2.COLOR_RGB2BGR if array.shape[2] == 3 else cv2.COLOR_RGBA2BGRA)
    ok, data = cv2.imencode(".png", arr)
    assert ok
    return FACTORY.msg("sensor_msgs/msg/CompressedImage", header=ma.make_header(FACTORY, 0, "cam"),
                       format="png", data=FACTORY.uint8_seq(data.reshape(-1)))


@pytest.mark.parametrize("scheme", ["cityscapes_ids", "cityscapes_train_ids", "cam2bev"])
def test_adapters_decode_upstream_label_images_to_labels(scheme):
    native = all_native()
    upstream = to_upstream(native, scheme)
    lm, want = label_map(scheme), equivalent_native(native)
    encodings = ("rgb8", "bgr8") if lm.encoding == "rgb8" else ("mono8", "8UC1")
    for enc in encodings:
        got = ma.image_to_labels(_msg(upstream, enc), (native.shape[1], native.shape[0]), label_map=lm)
        assert got.dtype == np.uint8
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(ma.compressed_to_labels(_png(upstream), label_map=lm), want)


def test_adapters_refuse_encodings_the_label_map_does_not_take():
    native = all_native()
    rgb = to_upstream(native, "cam2bev")
    with pytest.raises(ma.EncodingError, match=r"label images must be mono8 or 8UC1 for label_map 'native', got 'rgb8'"):
        ma.image_to_labels(_msg(rgb, "rgb8"))
    with pytest.raises(ma.EncodingError, match=r"must be rgb8 or bgr8 for label_map 'cam2bev', got 'mono8'.*mono8 label_map"):
        ma.image_to_labels(_msg(native, "mono8"), label_map=label_map("cam2bev"))
    with pytest.raises(ma.EncodingError, match="'rgba8'"):
        ma.image_to_labels(_msg(np.dstack([rgb, rgb[..., :1]]), "rgba8"), label_map=label_map("cam2bev"))
    with pytest.raises(ma.EncodingError, match="8-bit single-channel for label_map 'cityscapes_ids'"):
        ma.compressed_to_labels(_png(rgb), label_map=label_map("cityscapes_ids"))
    with pytest.raises(ma.EncodingError, match="8-bit RGB for label_map 'cam2bev', got 1 channel"):
        ma.compressed_to_labels(_png(native), label_map=label_map("cam2bev"))
    with pytest.raises(ma.EncodingError, match="4 channel"):
        ma.compressed_to_labels(_png(np.dstack([rgb, rgb[..., :1]])), label_map=label_map("cam2bev"))
    with pytest.raises(ma.EncodingError, match="uint16"):
        ma.compressed_to_labels(_png(native.astype(np.uint16)))


def test_adapters_keep_size_checks_and_limits_for_every_label_map():
    rgb = to_upstream(all_native(), "cam2bev")  # 3 x 22
    lm = label_map("cam2bev")
    with pytest.raises(ma.EncodingError, match="is 22x3, expected 22x4"):
        ma.image_to_labels(_msg(rgb, "rgb8"), (22, 4), label_map=lm)
    with pytest.raises(ma.EncodingError, match="maximum of 50 pixels"):
        ma.image_to_labels(_msg(rgb, "rgb8"), label_map=lm, limits=ma.AdapterLimits(max_image_pixels=50))
    with pytest.raises(ma.EncodingError, match="maximum of 50 pixels"):
        ma.compressed_to_labels(_png(rgb), label_map=lm, limits=ma.AdapterLimits(max_image_pixels=50))
    msg = _msg(rgb, "rgb8")
    msg = dataclasses.replace(msg, data=msg.data[:-1])  # truncated
    with pytest.raises(ma.EncodingError, match="bytes"):
        ma.image_to_labels(msg, label_map=lm)


# Hostile and careless label-map files (issue #29): each is one short ConfigError line naming
# the file (and the entry), found without building the document when it is a bomb.
HOSTILE_YAML = [
    ("labels: {0x10: road}\n", "'0x10'"),  # hex: YAML 1.1 would read 16
    ("labels: {0o17: road}\n", "'0o17'"),
    ("labels: {1_0: road}\n", "'1_0'"),
    ("labels: {1:20: road}\n", "'1:20'"),  # sexagesimal
    ("labels: {\u0663: road}\n", "ASCII decimal"),  # Arabic-Indic three
    ("labels: {\uff13: road}\n", "ASCII decimal"),  # full-width three
    ("labels: {'\u00b2': road}\n", "ASCII decimal"),  # superscript two (int() raises ValueError)
    ("labels: {\u00b2: road}\n", "ASCII decimal"),
    ("labels: {' 3': road}\n", "' 3'"),
    ("labels: {'3 ': road}\n", "'3 '"),
    ("labels: {!!int '0x10': road}\n", "'0x10'"),
    ("labels: {300: road}\n", "0..255"),
    ("labels: {1: roadz}\n", "'roadz', which is no label"),
    ("encoding: rgb8\nlabels: {'\u0661,2,3': road}\n", "colour"),
    ("encoding: rgb8\nlabels: {'1,2': road}\n", "colour '1,2'"),
    ("encoding: rgb8\nlabels: {'#12345G': road}\n", "colour"),
    ("encoding: [mono8]\nlabels: {1: road}\n", "encoding must be one of"),
    ("labels: {!!python/object/apply:os.system ['true']: road}\n", "not valid YAML"),
    ("labels: " + "[" * 50_000 + "]" * 50_000 + "\n", "(nested|nesting)"),  # was 80 s, then RecursionError
    ("labels: " + "{a: " * 30_000 + "1" + "}" * 30_000 + "\n", "nested more than"),  # was RecursionError
    ("labels:\n" + "".join(f"  x{i}: road\n" for i in range(60_000))[:MAX_FILE_BYTES - 10], "YAML nodes"),
    ("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\nc: [*b, *b, *b, *b, *b]\n"
     "labels: {1: road}\n", "aliases"),
    # an anchor without an alias (issue #41): refused, as the schema has none (the map itself parses
    # as {0: road}, so a bag of this package's ids gives mIoU 0.0; the anchor is named, not ignored)
    ("labels: &x {0: road}\n", r"YAML anchors \(&x, line 1\)"),
    ("encoding: mono8\nlabels:\n  0: &r road\n", r"anchors \(&r, line 3\)"),
    ("labels: {1: " + "x" * 1_000_000 + "}\n", "which is no label"),  # a 1 MB name: a short line
    ("labels:\n  ? " + "y" * 1_000_000 + "\n  : road\n", "upstream id"),  # a 1 MB key
]


@pytest.mark.parametrize("text, message", HOSTILE_YAML, ids=range(len(HOSTILE_YAML)))
def test_hostile_yaml_files_are_one_short_error_line(tmp_path, text, message):
    path = tmp_path / "map.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=message) as info:
        label_map(str(path))
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg and len(msg) < 400


def test_ids_in_plain_ascii_decimal_still_read(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("labels: {10: road, '011': vehicle, 255: pedestrian}\n")  # '011' is eleven, not octal
    assert label_map(str(path)).to_dict()["labels"] == {10: "road", 11: "vehicle", 255: "pedestrian"}


@pytest.mark.parametrize("kind", ["directory", "FIFO", "device"])
def test_a_directory_fifo_or_device_is_named_as_such(tmp_path, kind):
    import os  # noqa: PLC0415

    path = tmp_path / "map.yaml"
    if kind == "directory":
        path.mkdir()
    elif kind == "FIFO":
        os.mkfifo(path)  # no writer: the reader must not wait for one
    else:
        path.symlink_to("/dev/zero")  # endless: never read
    with pytest.raises(ConfigError, match=f"is a {kind}, not a file") as info:
        label_map(str(path))
    assert str(path) in str(info.value)
