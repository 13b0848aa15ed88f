"""Issue #38: a method that refuses an input or rig names the methods that do run there as
shipped and how to train its weights, computed from the table of methods (``METHODS``), not
written into the messages.
"""

from __future__ import annotations

from types import MappingProxyType

import pytest

import bev_mapper_core.methods as methods
from bev_mapper_core.errors import ConfigError
from bev_mapper_core.mapper import MapperConfig, preflight
from bev_mapper_core.methods import MethodSpec, alternatives, runnable_methods

SIX = ("front", "front_right", "back_right", "back", "back_left", "front_left")


def _refusal(rig: str, cameras=None, **config) -> str:
    with pytest.raises(ConfigError) as exc:
        preflight(MapperConfig(**config), rig, None, cameras)
    return str(exc.value)


def test_ipm_refusing_rgb_names_what_runs_on_rgb_of_the_rig():
    msg = _refusal("surround6", SIX, method="ipm", input_kind="rgb")
    assert msg.startswith("IPM maps semantic label images only")
    assert "segipm (RGB images, any calibrated rig)" in msg
    assert "bimapper (RGB through the shipped segmenter, then its shipped label weights for rig 'surround6')" in msg
    assert " ipm (" not in msg and "bev-train" not in msg  # IPM is training-free


def test_bimapper_without_weights_says_how_to_get_them_and_what_runs_instead():
    msg = _refusal("surround6", method="bimapper", input_kind="rgb", segmenter="none")
    assert "none shipped for rig 'surround6' / input 'rgb'" in msg
    assert "segmenter 'auto' (not 'none')" in msg
    assert "methods that run on RGB images of rig 'surround6' as shipped: segipm" in msg
    assert "bev-train --method bimapper --rig surround6 --input rgb --out runs/NAME, then pass weights=<file>" in msg
    assert "use method 'ipm'" not in msg  # IPM does not map RGB
    msg = _refusal("mine", method="bimapper", input_kind="rgb", segmenter="none")
    assert "none shipped for rig 'mine' / input 'rgb'" in msg and "segmenter 'auto' (not 'none')" in msg
    assert "bimapper (RGB through the shipped segmenter, then its shipped label weights for any rig)" not in msg
    assert ("to train bimapper weights: bev-train --method bimapper --rig random --streams lv --ipm-skip --input rgb "
            "--out runs/NAME (weights for any rig; rig 'mine' is no preset)") in msg
    msg = _refusal("mine", method="s2g2", input_kind="rgb")
    assert "bev-train trains the preset rigs surround6, cam2bev4, front1; rig 'mine' is none of them" in msg


def test_the_weights_for_any_rig_run_on_a_rig_without_its_own():
    """Issue #38: no refusal for a rig that is no preset: Bi-Mapper maps it with the weights for any rig."""
    preflight(MapperConfig(method="bimapper"), "mine", None, ("a", "b", "c"))
    preflight(MapperConfig(method="bimapper", input_kind="rgb"), "mine", None, ("a", "b", "c"))
    assert "bimapper (its shipped weights for any rig, label images)" in runnable_methods("labels", "mine")
    assert ("bimapper (RGB through the shipped segmenter, then its shipped label weights for any rig)"
            in runnable_methods("rgb", "mine"))


def test_other_refusals_name_the_alternatives():
    msg = _refusal("front1", method="segipm", input_kind="labels")
    assert "ipm (label images, any calibrated rig)" in msg
    assert "bimapper (its shipped weights for rig 'front1', label images)" in msg
    msg = _refusal("front1", method="s2g2", input_kind="labels")
    assert "bev-train --method s2g2 --rig front1 --input labels --grid ahead --unlabeled-drives N" in msg
    msg = _refusal("surround6", SIX, method="focusbev", input_kind="rgb")
    assert "FocusBEV is monocular" in msg and "segipm" in msg
    assert "bev-train" not in msg  # no monocular weights for six cameras


def test_the_alternatives_come_from_the_table(monkeypatch, tmp_path):
    """A method added to the table is named; one whose files are not shipped is not."""
    toy = MethodSpec(mapper="toy.module:Toy", trainer=None, inputs=("rgb",))
    monkeypatch.setattr(methods, "METHODS", MappingProxyType({**methods.METHODS, "toy": toy}))
    assert "toy (RGB images, any calibrated rig)" in runnable_methods("rgb", "surround6")
    assert "toy" not in " ".join(runnable_methods("labels", "surround6"))
    monkeypatch.setattr(methods, "WEIGHTS_DIR", tmp_path)  # nothing shipped
    assert runnable_methods("rgb", "front1") == ("toy (RGB images, any calibrated rig)",)
    assert alternatives("toy", "rgb", "front1") == "no other method runs on RGB images of rig 'front1' as shipped"
    assert runnable_methods("labels", "front1", exclude=("ipm",)) == ()
