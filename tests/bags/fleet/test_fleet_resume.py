"""``bev-bag evaluate --resume`` notices change (issue #29): a bag replaced since the first run is
replayed again, a damaged record (missing key, hand-edited counts, not JSON) is a redo with a
note, never a traceback; Ray starts without its token-authentication warning."""

from __future__ import annotations

import json
import shutil

from bag_damage import GRID_ARGS
from test_fleet_evaluate import _one_scorer

from bags.cli.main import main
from bags.fleet.evaluate import RECORD_FILE, SUMMARY_FILE
from bags.fleet.records import bag_identity, read_record, seal
from bags.replay import METRICS_FILE

FAST = ["--method", "ipm", "--no-pictures", "--no-report", "--quiet"]


def _synth(path, frames: int, seed: int) -> None:
    assert main(["synth", str(path), "--rig", "front1", "--scale", "0.25", "--frames", str(frames), "--seed",
                 str(seed), *GRID_ARGS]) == 0


def test_resume_replays_changed_bags_and_redoes_damaged_records(tmp_path, capsys):
    bags = tmp_path / "bags"
    names = "abcdef"
    for k, name in enumerate(names):
        _synth(bags / name, 3, 11 + k)
    out = tmp_path / "eval"
    argv = ["evaluate", str(bags), "--out", str(out), "--workers", "2", *FAST]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "Token authentication" not in err and "Traceback" not in err
    first = json.loads((out / SUMMARY_FILE).read_text())
    rec = {n: json.loads((out / "bags" / n / RECORD_FILE).read_text()) for n in names}
    assert rec["a"]["bag_identity"] == bag_identity(bags / "a") and isinstance(read_record(out / "bags/a" /
                                                                                           RECORD_FILE), dict)
    stamps = {n: (out / "bags" / n / METRICS_FILE).stat().st_mtime_ns for n in names}

    # a: replaced by another drive (same name, same frame count)
    shutil.rmtree(bags / "a")
    _synth(bags / "a", 3, 99)
    # b: a count edited by hand (the record's own hash no longer matches)
    r = rec["b"]
    r["metrics"]["frames"] += 5
    (out / "bags" / "b" / RECORD_FILE).write_text(json.dumps(r))
    # c: a key missing (was a KeyError traceback)
    r = {k: v for k, v in rec["c"].items() if k != "scoring"}
    (out / "bags" / "c" / RECORD_FILE).write_text(json.dumps(seal({k: v for k, v in r.items()
                                                                    if k != "record_sha256"})))
    # d: a truncated record; e: a directory in its place
    (out / "bags" / "d" / RECORD_FILE).write_text((out / "bags" / "d" / RECORD_FILE).read_text()[:50])
    (out / "bags" / "e" / RECORD_FILE).unlink()
    (out / "bags" / "e" / RECORD_FILE).mkdir()
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    s = json.loads((out / SUMMARY_FILE).read_text())
    assert s["bags"]["resumed"] == 1 and s["complete"]  # f only
    redone = {r["name"]: r["reason"] for r in s["redone"]}
    assert set(redone) == set("abcde")
    assert "changed since" in redone["a"] and "record_sha256" in redone["b"] and "'scoring'" in redone["c"]
    for n in "abcde":
        assert f"note: {n} replayed again" in err
        assert (out / "bags" / n / METRICS_FILE).stat().st_mtime_ns != stamps[n]
    assert (out / "bags" / "f" / METRICS_FILE).stat().st_mtime_ns == stamps["f"]
    assert list(out.rglob("*partial*")) == []
    # the aggregate is that of the bags as they are now (every frame through one scorer, as
    # test_fleet_evaluate checks a fresh evaluation against)
    want = _one_scorer([bags / n for n in names])
    got = s["aggregate"]
    assert abs(got["miou"] - want["miou"]) <= 1e-9 and got["frames_scored"] == want["frames"] == 3 * len(names)
    assert first["aggregate"]["miou"] != got["miou"]  # bag a's new drive is in it
