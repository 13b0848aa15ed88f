"""Issue #38: ground-truth layers of classes this package does not define (another recorder's
``/bev/gt/walkway``) are skipped with a note naming them; the replay scores the rest (it once
aborted with ``unknown BEV class``).
"""

from __future__ import annotations

import pytest
from bag_helpers import replay_ipm, replay_scores, synth_small

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import BagWriter

pytest.importorskip("bev_mapper_core.synth")

FRAMES = 2
NO_OUTPUTS = ("--no-pictures", "--no-report")


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """A small drive, and the same with ``/bev/gt/walkway`` and ``/bev/truth/walkway`` (copies of
    the sidewalk layers).
    """
    root = tmp_path_factory.mktemp("walkway")
    bag = synth_small(root / "drive", frames=FRAMES, seed=3)
    with BagReader(bag) as r, BagWriter(root / "with_walkway") as out:
        for key, value in r.custom_data.items():
            out.set_custom_data(key, value)
        for m in r.messages(raw=True):
            copies = [m.topic] + [m.topic.replace("sidewalk", "walkway")
                                  for t in (T.gt_topic("sidewalk"), T.truth_topic("sidewalk")) if m.topic == t]
            for topic in copies:
                out.add_topic(topic, m.msgtype, latched=m.topic in r.latched_topics)
                out.write_raw(topic, bytes(m.msg), m.log_ns)
    return bag, root / "with_walkway"



def test_the_reader_skips_unknown_gt_layers(drives):
    _, bag = drives
    with BagReader(bag) as r:
        assert T.gt_topic("walkway") in r.topics
        assert "walkway" not in r.gt_classes and "walkway" not in r.truth_classes
        assert r.unknown_gt_classes == ("walkway",)
        frame = next(iter(r.frames(rgb=False)))
        assert frame.gt.shape[0] == len(r.gt_classes) == 7


@pytest.mark.parametrize("classes", [(), ("--classes", "road", "static")], ids=["standard", "other-set"])
def test_replay_notes_the_skipped_layer_and_scores_the_rest(drives, tmp_path, capsys, classes):
    plain, bag = drives
    assert replay_ipm(plain, tmp_path / "plain", *NO_OUTPUTS, *classes) == 0
    capsys.readouterr()
    assert replay_ipm(bag, tmp_path / "walkway", *NO_OUTPUTS, *classes) == 0
    err = capsys.readouterr().err
    assert "note: GT layers of unknown classes skipped (not scored): /bev/gt/walkway" in err
    assert "Traceback" not in err and "error" not in err
    got, want = replay_scores(tmp_path / "walkway"), replay_scores(tmp_path / "plain")
    assert got.pop("skipped_gt_layers") == ["/bev/gt/walkway"] and want.pop("skipped_gt_layers") == []
    assert got == want and got["frames_scored"] == FRAMES


def test_info_lists_the_skipped_layer(drives, capsys):
    _, bag = drives
    assert main(["info", str(bag)]) == 0
    assert "GT layers of unknown classes (skipped by replay): walkway" in capsys.readouterr().out
