"""Appearance styles of the synthetic world: seeded, named, validated, and appearance only
(the same seed under two styles = the same labels, depth, ground truth, visibility and poses)."""

from __future__ import annotations

import json
from dataclasses import fields, replace

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.synth import DriveRenderer, SynthConfig, build_world, generate_drive
from bev_mapper_core.synth.render import Look
from bev_mapper_core.synth.styles import (
    HELD_OUT_STYLE,
    MIXED,
    STYLE_CHOICES,
    STYLES,
    TRAINING_STYLES,
    check_style,
    resolve_style,
    style_look,
)

GRID = BevGrid(-12.0, 12.0, -6.0, 6.0, 0.5)  # 48 x 24 cells: cheap ground truth
GRID_ARGS = ["--grid-x-min", "-12", "--grid-x-max", "12", "--grid-y-min", "-6", "--grid-y-max",
             "6", "--grid-res", "0.5"]
SEED = 7
#: mean absolute RGB difference (DN, all cameras) that two styles of one frame must exceed; the
#: closest pair (classic vs noon) measured 12.5-15.4 on seeds 2, 7, 11
MIN_MAD = 8.0


@pytest.fixture(scope="module")
def rig():
    return preset_rig("surround6").scaled(0.25)  # 100x56 images


@pytest.fixture(scope="module")
def world():
    return build_world(SynthConfig(frames=2, seed=SEED, style="noon"))


def _frames_in_every_style(world, rig, k: int) -> dict:
    """Frame ``k`` of ``world`` rendered in every style (the world built once)."""
    out = {}
    for name in STYLES:
        w = replace(world, config=replace(world.config, style=name))
        r = DriveRenderer(w, rig, GRID)
        assert r.style == name
        out[name] = r.frame(k)
    return out


def _rgb(frame) -> np.ndarray:
    return np.stack([c.rgb for c in frame.cameras.values()]).astype(np.float64)


def test_names_held_out_and_training_styles():
    assert 6 <= len(STYLES) <= 10 and all(s.summary for s in STYLES.values())
    assert HELD_OUT_STYLE in STYLES and HELD_OUT_STYLE not in TRAINING_STYLES
    assert set(TRAINING_STYLES) | {HELD_OUT_STYLE} == set(STYLES)
    assert STYLE_CHOICES == (MIXED, *STYLES) and MIXED not in STYLES
    assert SynthConfig().style == MIXED
    SynthConfig(style=HELD_OUT_STYLE)  # selectable by name, for testing


def test_bad_style_names_are_config_errors():
    for bad in ("sunny", "", "Noon", 3, None):
        with pytest.raises(ConfigError, match="choices: mixed, classic"):
            SynthConfig(style=bad)
        with pytest.raises(ConfigError):
            resolve_style(bad, 0)
    assert check_style("night") == "night"
    with pytest.raises(ConfigError, match="must be a number"):  # the other fields stay numbers
        SynthConfig(seed="1")


def test_mixed_never_picks_the_held_out_style_and_is_deterministic():
    picks = [resolve_style(MIXED, s) for s in range(400)]
    assert HELD_OUT_STYLE not in picks
    assert set(picks) == set(TRAINING_STYLES)  # every training style occurs
    assert max(picks.count(n) for n in TRAINING_STYLES) < 0.3 * len(picks)
    assert picks == [resolve_style(MIXED, s) for s in range(400)]
    assert all(resolve_style(n, 5) == n for n in STYLES)


def test_style_looks_are_seeded_distributions():
    for name in STYLES:
        a, b, c = style_look(name, 3), style_look(name, 3), style_look(name, 4)
        for f in fields(Look):
            assert np.array_equal(getattr(a, f.name), getattr(b, f.name)), (name, f.name)
        assert not np.array_equal(a.ground, c.ground), name
    # classic is Look.random on its original stream: the look of drives made before styles
    ref = Look.random(np.random.default_rng([3, 9]), 0.5)
    got = style_look("classic", 3, 0.5)
    assert all(np.array_equal(getattr(ref, f.name), getattr(got, f.name)) for f in fields(Look))
    assert style_look("night", 3, 2.0).noise == pytest.approx(2 * style_look("night", 3).noise)


def test_same_seed_and_style_is_bit_identical(rig):
    for name in ("rain", "night"):  # blur, wet road; lit windows, high noise
        cfg = SynthConfig(frames=1, seed=SEED, style=name)
        a, b = next(generate_drive(rig, GRID, cfg)), next(generate_drive(rig, GRID, cfg))
        for cam in a.cameras:
            np.testing.assert_array_equal(a.cameras[cam].rgb, b.cameras[cam].rgb)


def test_two_styles_same_drive_different_pictures(rig):
    """Built through generate_drive from two configs: only the RGB images differ."""
    wa = build_world(SynthConfig(frames=2, seed=SEED, style="vivid"))
    wb = build_world(SynthConfig(frames=2, seed=SEED, style="fog"))
    for f in ("ego", "ego_speed", "ego_yaw_rate", "obj_pose"):
        np.testing.assert_array_equal(getattr(wa, f), getattr(wb, f))
    for f in ("center", "z0", "size", "yaw", "label", "color", "kind", "obj"):
        np.testing.assert_array_equal(getattr(wa.parts, f), getattr(wb.parts, f))
    assert wa.tracks.keys() == wb.tracks.keys()
    assert all(np.array_equal(wa.tracks[i], wb.tracks[i], equal_nan=True) for i in wa.tracks)
    a = list(generate_drive(rig, GRID, SynthConfig(frames=2, seed=SEED, style="vivid")))
    b = list(generate_drive(rig, GRID, SynthConfig(frames=2, seed=SEED, style="fog")))
    for fa, fb in zip(a, b):
        for f in ("stamp_ns", "world_from_ego", "linear_velocity", "angular_velocity", "gt",
                  "visibility", "ground_visibility"):
            np.testing.assert_array_equal(getattr(fa, f), getattr(fb, f))
        for cam in fa.cameras:
            np.testing.assert_array_equal(fa.cameras[cam].labels, fb.cameras[cam].labels)
            assert fa.cameras[cam].stamp_ns == fb.cameras[cam].stamp_ns
        assert np.abs(_rgb(fa) - _rgb(fb)).mean() > MIN_MAD


def test_every_style_changes_only_the_rgb(world, rig):
    frames = _frames_in_every_style(world, rig, 1)
    ref = frames["noon"]
    for name, f in frames.items():
        for field in ("gt", "visibility", "ground_visibility", "world_from_ego"):
            np.testing.assert_array_equal(getattr(f, field), getattr(ref, field), err_msg=name)
        for cam in f.cameras:
            np.testing.assert_array_equal(f.cameras[cam].labels, ref.cameras[cam].labels)
    names = list(frames)
    means = {n: _rgb(frames[n]).reshape(-1, 3).mean(0) for n in names}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            mad = np.abs(_rgb(frames[a]) - _rgb(frames[b])).mean()
            assert mad > MIN_MAD, (a, b, mad)
            assert np.abs(means[a] - means[b]).max() > 2.0, (a, b, means[a], means[b])
    assert means["night"].mean() < min(means[n].mean() for n in names if n != "night")
    assert means["fog"].std() < means["vivid"].std()  # grey fog, colourful vivid


def test_depth_and_box_buffers_do_not_depend_on_the_look(world, rig):
    r = DriveRenderer(world, rig, GRID)
    cam, pose, boxes = r.cams[0], world.ego_pose(0), world.boxes_at(0, world.config.cull_distance)
    outs = [cam.render(pose, boxes, world.ground, style_look(n, SEED), np.random.default_rng(0))
            for n in ("classic", "rain", "night")]
    for o in outs[1:]:
        np.testing.assert_array_equal(o.depth, outs[0].depth)
        np.testing.assert_array_equal(o.part, outs[0].part)
        np.testing.assert_array_equal(o.labels, outs[0].labels)


def test_cli_style_flag_and_bag_metadata(tmp_path, capsys):
    from bags.cli.info import describe, format_info
    from bags.cli.main import build_parser, main
    from bags.io.reader import BagReader

    out = tmp_path / "night"
    assert main(["synth", str(out), "--frames", "2", "--seed", "3", "--scale", "0.25",
                 "--style", "night", *GRID_ARGS]) == 0
    with BagReader(out) as r:
        custom = r.custom_data
    assert custom["bev_mapper.style"] == "night"
    assert json.loads(custom["bev_mapper.synth"])["style"] == "night"
    assert "bev_mapper.style=night" in format_info(describe(out))
    # the default is SynthConfig's, resolved per seed in the metadata
    assert build_parser().parse_args(["synth", "o"]).style == SynthConfig().style == MIXED
    with pytest.raises(SystemExit):
        build_parser().parse_args(["synth", "o", "--style", "sunset"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        build_parser().parse_args(["synth", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert f"{HELD_OUT_STYLE} is held out" in help_text and "--style" in help_text


def test_docs_table_every_style():
    """docs/BAGS.md (the bag tool's guide, linked from the README) has a row for every style."""
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[3] / "docs" / "BAGS.md").read_text()
    rows = {line.split("`")[1]: line for line in readme.splitlines()
            if line.startswith("| `") and line.split("`")[1] in STYLES}
    assert set(rows) == set(STYLES)
    assert "held out" in rows[HELD_OUT_STYLE]
