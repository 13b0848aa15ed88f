"""Issue #28: replay's faster reading and writing give every output they gave before.

The reference is the reading and writing the replay did before (``bench/replay_reference.py``'s
``reference_io``, also a reference of ``bench/bench_replay_rate.py``): every message read and
deserialized by rosbags, every GT layer decoded by ``occupancy_grid_to_layer``, every grid and
CameraInfo of the output bag serialized by rosbags. Replays of small drives (MCAP, through the
file's indexes, and sqlite3, through rosbags) must give the same output bag byte for byte, the
same ``metrics.json`` (all but the timings), the same pictures and the same report.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from bag_helpers import replay_ipm, replay_outputs, synth_small

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
from replay_reference import reference_io  # noqa: E402 - bench/ is no package

pytest.importorskip("bev_mapper_core.synth")


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_replay_outputs_equal_the_rosbags_reading_and_writing(tmp_path, storage):
    bag = synth_small(tmp_path / "drive", frames=5, seed=31, storage=storage)
    assert replay_ipm(bag, tmp_path / "fast", "--frames-every", "2") == 0
    with reference_io():
        assert replay_ipm(bag, tmp_path / "reference", "--frames-every", "2") == 0
    fast, ref = replay_outputs(tmp_path / "fast"), replay_outputs(tmp_path / "reference")
    assert fast[0]["frames_scored"] == 5 and fast[0]["output_bag"]["messages"]["/bev/drivable"] == 5
    assert fast[0] == ref[0]
    assert fast[1] == ref[1] and len(fast[1]) == 3
    assert fast[2].keys() == ref[2].keys() and len(fast[2]) == 2
    for name in fast[2]:
        assert fast[2][name] == ref[2][name], name
    assert fast[3] == ref[3]
