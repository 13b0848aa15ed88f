"""Issue #38: ``bev-bag replay`` refusing a method on the bag's input says what runs there instead
(the core's message, computed from the table of methods), and asks for ``--rig`` only where the
rig's name is a guess (no preset).
"""

from __future__ import annotations

import pytest
from bag_helpers import replay_ipm, synth_small

from bags.cli.main import main

pytest.importorskip("bev_mapper_core.synth")


def test_ipm_on_rgb_names_segipm_and_no_rig_flags(tmp_path, capsys):
    bag = synth_small(tmp_path / "drive", frames=1)
    capsys.readouterr()
    assert replay_ipm(bag, tmp_path / "out", "--input", "rgb") == 1
    err = capsys.readouterr().err
    assert err.startswith("error: IPM maps semantic label images only") and "Traceback" not in err
    assert "segipm (RGB images, any calibrated rig)" in err and "--rig" not in err  # surround6 is a preset
    assert main(["replay", str(bag), "--out", str(tmp_path / "out"), "--quiet", "--rig", "mine", "--input", "rgb",
                 "--segmenter", "none"]) == 1
    err = capsys.readouterr().err
    assert "none shipped for rig 'mine' / input 'rgb'" in err and "segipm (RGB images, any calibrated rig)" in err
    assert "segmenter 'auto' (not 'none')" in err and "bev-train --method bimapper --rig random" in err
