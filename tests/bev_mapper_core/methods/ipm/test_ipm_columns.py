"""IPM's occlusion search per image column (issue #28) against the polar raster's search."""

import dataclasses

import numpy as np
import pytest

from bev_mapper_core.geometry.grid import BevGrid, grid_preset
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.columns import rig_columns
from bev_mapper_core.methods.ipm.mapper import IpmMapper, LineOfSight
from bev_mapper_core.methods.ipm.occlusion import OcclusionModel
from bev_mapper_core.synth import SynthConfig, generate_drive


class PolarIpm(IpmMapper):
    occlusion_columns = False


@pytest.mark.parametrize("rig_name,grid", [("surround6", BevGrid()), ("cam2bev4", BevGrid()),
                                           ("front1", grid_preset("ahead"))])
def test_column_search_agrees_with_the_polar_raster(rig_name, grid):
    """On synthetic drives with cars, pedestrians and buildings, the two searches hide nearly the
    same cells: the known flag differs on under 1 % of the grid, both hide hundreds of cells the
    classical IPM calls known, and the cells both call known get the same probabilities from
    every camera that sees them in both."""
    rig = preset_rig(rig_name)
    config = MapperConfig(method="ipm")
    columns, polar = IpmMapper(rig, grid, config), PolarIpm(rig, grid, config)
    classical = IpmMapper(rig, grid, MapperConfig(method="ipm", ipm_occlusion=False))
    assert columns.sight.columns and not polar.sight.columns
    hidden_total = 0
    for f in generate_drive(rig, grid, SynthConfig(frames=3, seed=950_000_020)):
        images = {n: c.labels for n, c in f.cameras.items()}
        a, b, c = columns.map(images), polar.map(images), classical.map(images)
        assert (a.known != b.known).mean() < 0.01
        assert not (a.known & ~c.known).any()  # occlusion only ever removes cells
        hidden_total += int((c.known & ~a.known).sum())
        both = a.known & b.known
        agree = (np.abs(a.probs - b.probs).max(axis=0) == 0) | ~both
        assert agree[both].mean() > 0.97
    assert hidden_total > 300


def test_line_of_sight_known_is_the_ipm_known():
    """``LineOfSight.known`` (the learned methods' line of sight) with the column search gives
    the cells IPM's map calls known, on every camera and with one missing."""
    rig, grid = preset_rig("surround6"), BevGrid()
    mapper = IpmMapper(rig, grid, MapperConfig(method="ipm"))
    sight = LineOfSight(rig, grid, OcclusionModel(), columns=True)
    for f in generate_drive(rig, grid, SynthConfig(frames=2, seed=950_000_021)):
        images = {n: c.labels for n, c in f.cameras.items()}
        for subset in (images, {n: v for n, v in images.items() if n != "front"}):
            np.testing.assert_array_equal(sight.known(subset), mapper.map(subset).known)
    with pytest.raises(ValueError):
        sight.camera_valid("front", np.zeros(grid.shape, np.uint8))


def _hidden_frames(rig, grid, seed):
    """Synthetic frames plus harder ones: random occluder labels (second near edges), a camera
    that sees no occluder, one that sees nothing but an occluder and one with finite shadows."""
    rng = np.random.default_rng(seed)
    frames = [{n: c.labels for n, c in f.cameras.items()} for f in generate_drive(rig, grid, SynthConfig(frames=2, seed=seed))]
    names = list(frames[0])
    mixed = {n: rng.choice(np.array([0, 1, 6, 7, 8, 9], np.uint8), v.shape) for n, v in frames[0].items()}
    mixed[names[0]] = np.zeros_like(mixed[names[0]])  # no occluder at all
    mixed[names[-1]] = np.full_like(mixed[names[-1]], 6)  # every pixel a car
    return frames + [mixed]


@pytest.mark.parametrize("rig_name,grid", [("surround6", BevGrid()), ("cam2bev4", BevGrid()),
                                           ("front1", grid_preset("ahead"))])
def test_joint_search_is_each_cameras_own(rig_name, grid):
    """The cameras' joint search (one pass for all) hides, per camera, exactly what that
    camera's search alone hides, whichever cameras are present; and the lowest-occluder shortcut
    and the range test of the occluding ids give the same cells as the key image's minimum and
    the label lookups (the general path)."""
    rig = preset_rig(rig_name)
    sight = LineOfSight(rig, grid, OcclusionModel(), columns=True)
    assert sight._rig_columns.row_code is not None  # every shipped camera's keys fall row by row
    general = LineOfSight(rig, grid, OcclusionModel(), columns=True)
    general._rig_columns = dataclasses.replace(general._rig_columns, row_code=None)
    assert sight._column_occlusion._range == (6, 9)
    general._column_occlusion._range = None  # and label lookups, not the range tests of ids 6..9
    some_hidden = 0
    for images in _hidden_frames(rig, grid, 950_000_022):
        ids = {n: sight.gathers[n].gather(v) for n, v in images.items()}
        joint = sight.hidden_all(images, ids)
        assert list(joint) == [c.name for c in rig.cameras]
        for name, labels in images.items():
            alone = sight.hidden(name, labels, ids[name])
            assert (alone is None) == (joint[name] is None)
            if alone is not None:
                np.testing.assert_array_equal(alone, joint[name])
                assert (np.diff(alone) > 0).all()
                some_hidden += 1
        if len(images) > 1:  # a camera missing: the others' cells as before
            rest = {n: v for n, v in list(images.items())[1:]}
            for name, h in sight.hidden_all(rest, ids).items():
                assert (h is None) == (joint[name] is None) and (h is None or np.array_equal(h, joint[name]))
        for name, h in general.hidden_all(images, ids).items():
            assert (h is None) == (joint[name] is None) and (h is None or np.array_equal(h, joint[name]))
    assert some_hidden > 0
    assert sight.hidden_all({}, {}) == {}


def test_joint_raster_without_falling_keys_uses_the_key_image():
    """A raster whose keys do not fall row by row (here: upside down) gets no lowest-occluder
    shortcut: its search takes the key image's minimum."""
    rig, grid = preset_rig("front1"), grid_preset("ahead")
    sight = LineOfSight(rig, grid, OcclusionModel(), columns=True)
    cr = sight.column_rasters["front"]
    flipped = rig_columns({"front": dataclasses.replace(cr, key=cr.key[::-1].copy())})
    assert flipped.row_code is None and sight._rig_columns.row_code is not None
    assert rig_columns({"front": cr}).row_code is not None
