"""Declared calibration, images and ground truth of a synthetic bag agree.

IPM of the bag's label images, built only from the bag's own CameraInfo and /tf_static, must find
the flat classes where the bag's ground-truth grids have them. A wrong sign in an extrinsic, a
transposed grid or a mis-scaled intrinsic anywhere between the renderer, the bag writer, the
reader and the IPM would break this.
"""

import pytest

from bags.cli.synth import SynthBagOptions, synth_bag
from bags.io.reader import BagReader
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.metrics import MetricAccumulator
from bev_mapper_core.synth import SynthConfig

pytestmark = pytest.mark.slow  # renders and writes an 8-frame drive on the full grid

SEED_WITH_CROSSING = 7  # this drive passes a pedestrian crossing within 20 m


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    out = tmp_path_factory.mktemp("agree") / "drive"
    synth_bag(SynthBagOptions(out=out, rig="surround6", scale=0.5, storage="mcap",
                              grid=BevGrid(), synth=SynthConfig(frames=8, seed=SEED_WITH_CROSSING)))
    with BagReader(out) as reader:
        rig, grid = reader.rig(), reader.grid()
        assert grid == BevGrid()
        # the classical IPM (flat-ground smear) and the default one (occlusion reasoning)
        mappers = {occ: IpmMapper(rig, grid, MapperConfig(method="ipm", ipm_occlusion=occ))
                   for occ in (False, True)}
        near = grid.ranges < 20.0
        acc = {(occ, scope): MetricAccumulator(grid, reader.gt_classes, range_bands=((0, 20),))
               for occ in mappers for scope in ("visible", "ground", "whole")}
        n = 0
        for frame in reader.frames(rgb=False, odom=False):
            for occ, mapper in mappers.items():
                pred = mapper.map(frame.labels)
                idx = [pred.classes.index(c) for c in reader.gt_classes]
                visible = frame.gt_known[0] & near
                acc[occ, "visible"].update(pred.probs[idx], frame.gt >= 0.5, visible, pred.known)
                acc[occ, "ground"].update(pred.probs[idx], frame.gt >= 0.5,
                                          visible & frame.ground_visibility, pred.known)
                acc[occ, "whole"].update(pred.probs[idx], frame.gt >= 0.5, frame.gt_known[0],
                                         pred.known)
            n += 1
    assert n == 8
    out = {scope: acc[True, scope].result()["classes"] for scope in ("visible", "ground", "whole")}
    out["classic"] = {scope: acc[False, scope].result()["classes"] for scope in ("ground", "whole")}
    return out


def test_ipm_finds_flat_classes_where_gt_has_them(scored):
    for ground in (scored["ground"], scored["classic"]["ground"]):
        assert ground["drivable"]["iou"] >= 0.9
        assert ground["ped_crossing"]["iou"] >= 0.7
        assert ground["sidewalk"]["iou"] >= 0.85
        assert ground["lane_divider"]["iou"] >= 0.5


def test_classic_ipm_smears_vehicles_and_occlusion_reasoning_does_not(scored):
    """Off-ground objects are the classical IPM's known failure: far worse than the flat
    classes. With the occlusion reasoning (the default) the smear behind the near edge is
    unknown instead."""
    visible = scored["classic"]["whole"]
    assert visible["vehicle"]["iou"] < visible["drivable"]["iou"] - 0.2
    # The smear makes IPM's vehicle cells mostly false positives beyond the true footprint.
    assert visible["vehicle"]["cd_p"] > 3 * visible["drivable"]["cd_p"]
    honest = scored["whole"]["vehicle"]
    assert honest["iou"] > visible["vehicle"]["iou"]
    assert honest["cd_p"] < visible["vehicle"]["cd_p"] / 3
