"""IPM's occlusion search per image column (issue #28) against the polar raster's search."""

import numpy as np
import pytest

from bev_mapper_core.geometry.grid import BevGrid, grid_preset
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.mapper import MapperConfig
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
