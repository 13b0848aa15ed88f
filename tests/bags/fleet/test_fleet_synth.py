"""``bev-bag synth-many``: drives rendered as Ray tasks on a real local Ray runtime, output
byte-identical with 1 and 2 workers (and to ``bev-bag synth``'s), reruns skip, bev-train's data loading reads the cache."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("ray")

from bags.cli.main import build_parser, main  # noqa: E402
from bags.cli.synth import SynthBagOptions  # noqa: E402
from bags.cli.synth_many import MAX_SEEDS, options_from_args, parse_seeds  # noqa: E402
from bags.fleet.ray_tasks import RayOptions, TaskFailure, ray_runtime, run_tasks  # noqa: E402
from bev_mapper_core.errors import ConfigError  # noqa: E402
from bev_mapper_core.geometry.grid import BevGrid  # noqa: E402
from bev_mapper_core.geometry.rig import preset_rig  # noqa: E402
from bev_mapper_core.synth.config import SynthConfig  # noqa: E402
from bev_mapper_core.training import data  # noqa: E402
from bev_mapper_core.training.config import TrainConfig  # noqa: E402
from bev_mapper_core.training.sources import DataNeeds, SynthSource  # noqa: E402

TINY_GRID = (-8.0, 8.0, -4.0, 4.0, 0.5)  # 32 x 16 cells
GRID_ARGS = ["--grid-x-min", "-8", "--grid-x-max", "8", "--grid-y-min", "-4", "--grid-y-max", "4", "--grid-res", "0.5"]
#: bev-train's drives of --seed 0 --train-drives 2 and one held-out drive
SEEDS = "0,1,900000000"
CACHE_ARGS = ["--format", "cache", "--rig", "front1", "--frames", "2", "--stride", "2", *GRID_ARGS, "--no-progress"]
BAG_ARGS = ["--rig", "front1", "--frames", "2", "--scale", "0.25", *GRID_ARGS, "--no-progress"]


def files(root: Path) -> dict[str, bytes]:
    """Every file under ``root``: relative path -> bytes."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def stamps(root: Path) -> dict[str, int]:
    return {p.relative_to(root).as_posix(): p.stat().st_mtime_ns for p in root.rglob("*")}


def test_parse_seeds():
    assert parse_seeds("3..5") == (3, 4, 5)  # inclusive
    assert parse_seeds("1,2,5") == (1, 2, 5)
    assert parse_seeds(" 7 , 0..1 ") == (7, 0, 1)
    assert parse_seeds("4..4") == (4,)
    for bad in ("", "a", "1..", "..3", "5..3", "-1", "1,,2", "1..2..3", "1,1", "0..3,2", f"0..{MAX_SEEDS}"):
        with pytest.raises(ConfigError):
            parse_seeds(bad)


def test_bad_arguments_are_errors(tmp_path, capsys):
    assert main(["synth-many", str(tmp_path / "o"), "--seeds", "5..3"]) == 1
    assert "error: bad seeds '5..3'" in capsys.readouterr().err
    assert main(["synth-many", str(tmp_path / "o"), "--seeds", "1", "--format", "cache", "--scale", "0.5"]) == 1
    assert "--scale does not apply to --format cache" in capsys.readouterr().err
    assert main(["synth-many", str(tmp_path / "o"), "--seeds", "1", "--stride", "2"]) == 1
    assert "--stride does not apply to --format bag" in capsys.readouterr().err
    assert main(["synth-many", str(tmp_path / "o"), "--seeds", "1", "--format", "cache", "--rgb", "big"]) == 1
    assert "--rgb must be HxW" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_defaults_come_from_the_dataclasses():
    bag = options_from_args(build_parser().parse_args(["synth-many", "o", "--seeds", "1"]))
    assert bag.drive == SynthBagOptions(out=Path("o")) and bag.ray == RayOptions() and not bag.force
    cache = options_from_args(build_parser().parse_args(["synth-many", "o", "--seeds", "1", "--format", "cache"]))
    t = TrainConfig()
    assert cache.drive == data.drive_spec(preset_rig(t.rig), t.grid, t.class_names, t.frames_per_drive, t.stride)
    rgb = options_from_args(build_parser().parse_args(
        ["synth-many", "o", "--seeds", "1", "--format", "cache", "--rig", "front1", "--rgb", "camera"]))
    assert rgb.drive.rgb == (225, 400) and rgb.drive.style == SynthConfig.style


@pytest.mark.slow
def test_cache_identical_with_1_and_2_workers_and_bev_train_reads_it(tmp_path, capsys, monkeypatch):
    one, two = tmp_path / "w1", tmp_path / "w2"
    assert main(["synth-many", str(one), "--seeds", SEEDS, "--workers", "1", *CACHE_ARGS]) == 0
    assert main(["synth-many", str(two), "--seeds", "900000000,1,0", "--workers", "2", *CACHE_ARGS]) == 0
    assert "3 drives rendered" in capsys.readouterr().out
    a = files(one)
    assert len([k for k in a if k.endswith(".npz")]) == 3 and any(k.endswith("/spec.json") for k in a)
    assert a == files(two)  # byte-identical, whatever the worker count and completion order

    # a rerun skips what is there (no Ray started, nothing rewritten)
    before = stamps(one)
    assert main(["synth-many", str(one), "--seeds", SEEDS, "--workers", "2", *CACHE_ARGS]) == 0
    assert "0 drives rendered, 3 already there" in capsys.readouterr().out
    assert stamps(one) == before

    # bev-train's data loading (SynthSource, as `bev-train --cache w1`) finds every drive there
    def no_render(*a, **k):
        raise AssertionError("a drive was rendered instead of read from the cache")

    monkeypatch.setattr(data, "render_drive", no_render)
    cfg = TrainConfig.from_dict(dict(rig="front1", seed=0, train_drives=2, val_seeds=[900000000], frames_per_drive=2,
                                     stride=2, cache=str(one), grid=list(TINY_GRID), progress=False))
    rig, grid = SynthSource().rig_grid(cfg)
    assert grid == BevGrid(*TINY_GRID)
    got = SynthSource().load(cfg, rig, grid, DataNeeds(), log=lambda m: None)
    assert (len(got.train), len(got.val)) == (4, 2)
    assert got.train.labels.shape == (4, 1, 225, 400) and got.train.target.shape == (4, 7, 16, 32)
    assert stamps(one) == before


@pytest.mark.slow
def test_bags_identical_to_bev_bag_synth_with_2_workers_and_failures_listed(tmp_path, capsys):
    """The drives of 2 workers, finishing in any order, are byte for byte the bags ``bev-bag
    synth`` writes for those seeds one after the other (1 worker against 2: the cache test)."""
    one, two = tmp_path / "w1", tmp_path / "w2"
    for s in (5, 6, 7):
        assert main(["synth", str(one / f"drive_{s}"), "--seed", str(s), *BAG_ARGS[:-1]]) == 0
    a = files(one)
    assert sorted(a) == [f"drive_{s}/{f}" for s in (5, 6, 7) for f in (f"drive_{s}.mcap", "metadata.yaml")]
    capsys.readouterr()

    # 2 workers; one drive cannot be placed (--force never replaces what is not a bag): the others complete
    two.mkdir()
    (two / "drive_6").write_text("not a bag")
    assert main(["synth-many", str(two), "--seeds", "5..7", "--workers", "2", "--force", *BAG_ARGS]) == 1
    out, err = capsys.readouterr()
    assert "2 drives rendered, 0 already there, 1 failed" in out
    assert "error: seed 6: refusing to overwrite" in err
    assert (two / "drive_6").read_text() == "not a bag"
    # byte-identical to the drives 1 worker wrote: bags hold no wall-clock time
    assert {k: v for k, v in files(two).items() if k != "drive_6"} == \
        {k: v for k, v in a.items() if not k.startswith("drive_6/")}
    assert not [p for p in two.iterdir() if ".partial-" in p.name]


def _descendants(pid: int) -> set[int]:
    """Live processes below ``pid`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), ()):
            out.add(c)
            todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
def test_sigterm_cancels_the_tasks_and_stops_ray(tmp_path):
    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "bags.cli.main", "synth-many", str(out), "--seeds", "0..200", "--workers", "2",
           *CACHE_ARGS]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120  # Ray's start on a busy machine
        while not list(out.glob("*/drive_*.npz")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        assert list(out.glob("*/drive_*.npz")), "no drive written"
        ray_procs = _descendants(proc.pid)
        assert ray_procs  # the local runtime's processes
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 143 and "error: terminated (SIGTERM)" in err, err
    written = list(out.glob("*/drive_*.npz"))
    assert 0 < len(written) < 201
    assert not [p for p in out.rglob("*") if "tmp" in p.name or "partial" in p.name]
    deadline = time.monotonic() + 15
    while any(_alive(p) for p in ray_procs) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [p for p in ray_procs if _alive(p)], "Ray processes outlived the command"


@pytest.mark.slow
def test_run_tasks_reports_failures_per_item():
    def fails_on_two(item: int) -> int:  # nested: shipped by value (the workers cannot import tests/)
        if item == 2:
            raise ValueError("two is broken")
        return item * 10

    with ray_runtime(RayOptions(workers=2)) as ray:
        assert ray.is_initialized() and ray.cluster_resources()["CPU"] == 2
        got = dict(run_tasks(ray, fails_on_two, [1, 2, 3]))
        assert got[1] == 10 and got[3] == 30
        assert got[2] == TaskFailure("ValueError: two is broken")
        # the workers import this checkout
        assert ray.get(ray.remote(lambda: os.environ["PYTHONPATH"]).remote()).split(os.pathsep)[0] == \
            str(Path(__file__).resolve().parents[3])
    assert not ray.is_initialized()
