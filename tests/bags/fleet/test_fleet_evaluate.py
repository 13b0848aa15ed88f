"""bev-bag evaluate: bags replayed as tasks of a real local Ray runtime (2 CPUs), the exact
aggregate, damaged bags failing alone, --resume; and the exact merge of the accumulators."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from bag_damage import GRID_ARGS, make_base

from bags.cli.main import build_parser, main
from bags.fleet.evaluate import RECORD_FILE, SUMMARY_FILE
from bags.fleet.replay_tasks import bag_names
from bags.io.reader import BagReader
from bags.replay import METRICS_FILE, ReplayScorer, percentiles
from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.label_maps import label_map
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.metrics import MetricAccumulator, WholeGridAccumulator

pytest.importorskip("ray")
TOL = 1e-9
FAST = ["--method", "ipm", "--no-pictures", "--no-report", "--quiet"]


# ------------------------------------------------------------------ exact merge (fast)
def _frames(grid, n, seed):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield (rng.random((2,) + grid.shape), rng.random((2,) + grid.shape) > 0.6,
               rng.random(grid.shape) > 0.2, rng.random(grid.shape) > 0.1)


@pytest.mark.parametrize("reduction", ["frame", "pixel"])
def test_merged_accumulators_equal_one_accumulator(reduction):
    grid = BevGrid(-5.0, 5.0, -5.0, 5.0, 0.5)
    names = ["drivable", "vehicle"]
    one = MetricAccumulator(grid, names, chamfer_reduction=reduction)
    parts = [MetricAccumulator(grid, names, chamfer_reduction=reduction) for _ in range(3)]
    w_one, w_parts = WholeGridAccumulator(grid, names), [WholeGridAccumulator(grid, names) for _ in range(3)]
    for i, (p, gt, vis, known) in enumerate(_frames(grid, 9, 3)):
        one.update(p, gt, vis, known)
        parts[i % 3].update(p, gt, vis, known)
        w_one.update(p, known, vis, gt)
        w_parts[i % 3].update(p, known, vis, gt)
    # through JSON, as the states travel between processes and to disk
    merged = MetricAccumulator.from_state(json.loads(json.dumps(parts[0].state())))
    merged.merge(parts[1])
    merged.merge_state(json.loads(json.dumps(parts[2].state())))
    w = WholeGridAccumulator.from_state(w_parts[0].state())
    w.merge(w_parts[1])
    w.merge(w_parts[2])
    assert merged.frames == one.frames == 9
    np.testing.assert_array_equal(merged._inter, one._inter)  # counts: exact
    np.testing.assert_array_equal(merged._band_union, one._band_union)
    _assert_close(merged.result(), one.result())
    _assert_close(w.result(), w_one.result())


def test_merge_refuses_other_definitions():
    grid = BevGrid(-5.0, 5.0, -5.0, 5.0, 0.5)
    acc = MetricAccumulator(grid, ["drivable"])
    for other in (MetricAccumulator(grid, ["vehicle"]), MetricAccumulator(grid, ["drivable"], threshold=0.4),
                  MetricAccumulator(BevGrid(-5.0, 5.0, -5.0, 5.0, 0.25), ["drivable"]),
                  WholeGridAccumulator(grid, ["drivable"])):
        with pytest.raises(ConfigError):
            acc.merge(other)
    bad = acc.state()
    bad["counts"]["_inter"] = [1, 2]
    with pytest.raises(ConfigError, match="shape"):
        acc.merge_state(bad)
    assert acc.frames == 0 and acc._inter.tolist() == [0]  # nothing added on refusal


def _assert_close(a, b, path="") -> None:
    """Equal JSON-like values, floats within TOL."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            _assert_close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert abs(a - b) <= TOL * max(1.0, abs(b)), (path, a, b)
    else:
        assert a == b, (path, a, b)


# ------------------------------------------------------------------ the command (slow)
@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Three intact bags (two of them named ``a`` in other directories), one truncated bag
    (damaged after its first frames) and one that is no mcap at all; evaluated once.
    """
    root = tmp_path_factory.mktemp("fleet")
    base = make_base(root / "base")  # 12 frames, small chunks
    good = [base.mcap]
    for i, d in enumerate(("drives", "more")):
        argv = ["synth", str(root / d / "a"), "--rig", "front1", "--scale", "0.25", "--frames",
                str(3 + i), "--seed", str(11 + i), *GRID_ARGS]
        assert main(argv) == 0
        good.append(root / d / "a")
    data = base.mcap_file.read_bytes()
    (root / "cut.mcap").write_bytes(data[: int(len(data) * 0.6)])
    (root / "junk.mcap").write_bytes(b"no mcap" * 20)
    inputs = [base.mcap, root / "drives", root / "more", root / "cut.mcap", root / "junk.mcap"]
    out = root / "eval"
    rc = main(["evaluate", *map(str, inputs), "--out", str(out), "--workers", "2", *FAST])
    summary = json.loads((out / SUMMARY_FILE).read_text())
    return {"root": root, "good": good, "inputs": inputs, "out": out, "rc": rc, "summary": summary}


def _one_scorer(bags: list[Path]) -> dict:
    """Every frame of ``bags`` mapped with IPM (as the replay calls it) into ONE scorer."""
    scorer = None
    for bag in bags:
        with BagReader(bag) as r:
            grid = r.grid()
            mapper = create_mapper(r.rig(), grid, MapperConfig(method="ipm"))
            if scorer is None:
                scorer = ReplayScorer(grid, mapper.class_names, r.gt_classes, ground=False)
            frames = r.frames(rgb=False, labels=True, label_map=label_map(MapperConfig.label_map))
            for f in frames:
                pose = f.odom.world_from_ego if f.odom is not None else None
                scorer.update(f, mapper.map(f.labels, ego_pose=pose, stamp_ns=f.stamp_ns))
    return scorer.result()


@pytest.mark.slow
def test_aggregate_equals_all_frames_through_one_scorer(fleet):
    s = fleet["summary"]
    agg = s["aggregate"]
    assert agg["bags"] == 3 and agg["excluded"] == []
    want = _one_scorer(fleet["good"])
    assert agg["frames_scored"] == want["frames"] == 12 + 3 + 4
    for key in ("classes", "miou", "map", "iou_by_range", "occlusion", "calibration"):
        _assert_close(agg[key], want[key], key)
    # not a mean of per-bag means
    per_bag = [e["miou"] for e in s["per_bag"] if e["status"] == "ok"]
    assert abs(agg["miou"] - float(np.mean(per_bag))) > 1e-6
    # latency percentiles over all frames of the complete bags
    names = [e["name"] for e in s["per_bag"] if e["status"] == "ok"]
    lat = [v for n in names for v in json.loads((fleet["out"] / "bags" / n / RECORD_FILE).read_text())["latencies_ms"]]
    assert len(lat) == agg["frames"] == 19
    assert agg["latency_ms"] == percentiles(lat)


@pytest.mark.slow
def test_each_bag_is_what_replay_writes(fleet, tmp_path):
    """The per-bag metrics.json equal those of ``bev-bag replay`` (the same code)."""
    s = fleet["summary"]
    entry = next(e for e in s["per_bag"] if e["bag"] == str(fleet["good"][1].resolve()))
    assert main(["replay", str(fleet["good"][1]), "--out", str(tmp_path / "r"), *FAST]) == 0
    mine = json.loads((fleet["out"] / entry["out"] / METRICS_FILE).read_text())
    theirs = json.loads((tmp_path / "r" / METRICS_FILE).read_text())
    for m in (mine, theirs):
        del m["latency_ms"], m["score_process"]
    assert mine == theirs


@pytest.mark.slow
def test_damaged_bags_fail_alone(fleet, capsys):
    s = fleet["summary"]
    assert fleet["rc"] == 1 and s["complete"] is False
    assert s["bags"] == {"total": 5, "ok": 3, "damaged": 1, "failed": 1, "resumed": 0}
    by_name = {e["name"]: e for e in s["per_bag"]}
    assert by_name["cut"]["status"] == "damaged" and "damaged" in by_name["cut"]["error"]
    assert 1 <= by_name["cut"]["frames"] < 12  # replayed up to the damage, outputs completed
    assert (fleet["out"] / "bags" / "cut" / METRICS_FILE).exists()
    assert by_name["junk"]["status"] == "failed" and "not an mcap" in by_name["junk"]["error"]
    # same-named bags in different directories get their own outputs
    a_names = [n for n in by_name if n.startswith("a-")]
    assert len(a_names) == 2 and all(by_name[n]["status"] == "ok" for n in a_names)
    assert list(fleet["out"].rglob("*partial*")) == []


@pytest.mark.slow
def test_resume_skips_finished_bags(fleet, capsys, monkeypatch):
    out = fleet["out"]
    ok = [e["out"] for e in fleet["summary"]["per_bag"] if e["status"] == "ok"]
    stamps = {n: (out / n / METRICS_FILE).stat().st_mtime_ns for n in ok}
    argv = ["evaluate", *map(str, fleet["inputs"]), "--out", str(out), "--workers", "2", *FAST]
    assert main(argv) == 1  # an earlier evaluation is there
    assert "--resume" in capsys.readouterr().err
    (out / "bags" / "cut" / ".bev_bag.partial-99999").mkdir()  # as a killed worker leaves it
    argv.remove("--quiet")  # with the progress bars (through the progress actor)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main([*argv, "--resume"]) == 1  # the damaged bags are tried again and fail again
    cap = capsys.readouterr()
    assert "frames" in cap.err and "bags" in cap.err and "Traceback" not in cap.err
    s = json.loads((out / SUMMARY_FILE).read_text())
    assert s["bags"] == {"total": 5, "ok": 3, "damaged": 1, "failed": 1, "resumed": 3}
    assert {n: (out / n / METRICS_FILE).stat().st_mtime_ns for n in ok} == stamps
    assert s["aggregate"] == fleet["summary"]["aggregate"]
    assert list(out.rglob("*partial*")) == []
    # resuming with other options is refused, not mixed
    assert main([*argv, "--resume", "--scope", "ground", "--quiet"]) == 1
    assert "other options" in capsys.readouterr().err


@pytest.mark.slow
def test_joining_an_existing_cluster(fleet, tmp_path):
    """--ray-address HOST:PORT: the tasks run on a cluster started beforehand, which stays up."""
    import ray  # noqa: PLC0415
    from ray.cluster_utils import Cluster  # noqa: PLC0415

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2, "include_dashboard": False})
    try:
        out = tmp_path / "eval"
        assert main(["evaluate", *map(str, fleet["inputs"]), "--out", str(out), "--ray-address",
                     cluster.address, *FAST]) == 1
        s = json.loads((out / SUMMARY_FILE).read_text())
        assert s["ray"]["address"] == cluster.address and s["ray"]["workers"] == 2  # the cluster's CPUs
        assert s["ray"]["nodes"] == [cluster.head_node.node_id], s["per_bag"]  # where the tasks ran
        assert {e["node"] for e in s["per_bag"] if e["status"] == "ok"} == {cluster.head_node.node_id}
        same = {k: v for k, v in fleet["summary"]["aggregate"].items() if k != "latency_ms"}
        assert s["bags"]["ok"] == 3 and {k: s["aggregate"][k] for k in same} == same
        assert not ray.is_initialized()  # disconnected ...
        assert cluster.head_node.remaining_processes_alive()  # ... and the cluster is still up
    finally:
        cluster.shutdown()


@pytest.mark.parametrize("extra, message", [
    (["--workers", "0"], "--workers"),
    (["--ray-address", "nowhere"], "--ray-address"),
    (["--resume", "--force"], "--resume"),
])
def test_bad_input_is_an_error(tmp_path, capsys, extra, message):
    (tmp_path / "x.mcap").write_bytes(b"")
    assert main(["evaluate", str(tmp_path / "x.mcap"), "--out", str(tmp_path / "o"), *extra]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and "Traceback" not in err


def test_paths_without_bags_are_errors(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    for path in (tmp_path / "missing", tmp_path / "empty"):
        assert main(["evaluate", str(path), "--out", str(tmp_path / "o")]) == 1
        assert capsys.readouterr().err.startswith("error: ")
    assert not (tmp_path / "o").exists()


def test_unique_names():
    bags = [Path("/d1/a"), Path("/d2/a.mcap"), Path("/d3/b.db3")]
    names = bag_names(bags)
    assert names[2] == "b" and names[0] != names[1] and all(n.startswith("a-") for n in names[:2])
    assert bag_names(bags) == names  # the same in every run (resume finds them)


def test_evaluate_has_the_flags_of_replay():
    """One definition of the per-bag flags: same destinations, defaults and choices."""
    sub = build_parser()._subparsers._group_actions[0].choices
    def flags(name):
        return {a.dest: (a.default, a.choices) for a in sub[name]._actions if a.option_strings}
    replay, evaluate = flags("replay"), flags("evaluate")
    assert {k: v for k, v in evaluate.items() if k in replay} == replay
    assert set(evaluate) - set(replay) == {"ray_address", "workers", "resume"}
