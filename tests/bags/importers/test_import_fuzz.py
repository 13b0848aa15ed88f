"""Issue #41: ``bev-bag import nuscenes`` on damaged copies of the miniature dataset, and an
import killed with SIGKILL.

Each case of :data:`DAMAGE` breaks one thing the importer follows (a token link to a record that
does not exist, a table that is not a list of records, a record without a field, a map expansion
that is not JSON): the import must end with status 1 and an ``error:`` line naming the table or
file, and leave nothing under the scene's name. (Missing tables, missing or corrupt JPEGs and an
absent map expansion: tests/bags/importers/nuscenes/test_nuscenes_import.py.)

A SIGKILL mid-import leaves no bag under the final name (the bag is written under a hidden
temporary name and renamed when complete) and the next import succeeds and removes the killed
one's temporary.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from nuscenes_helpers import write_nuscenes

from bags.cli.main import main
from bags.io.reader import BagReader

SCENE = "scene-0061"


def _rows(root: Path, table: str) -> list:
    return json.loads((root / "v1.0-mini" / f"{table}.json").read_text())


def _put(root: Path, table: str, rows) -> None:
    (root / "v1.0-mini" / f"{table}.json").write_text(json.dumps(rows))


def _link(table: str, row: int, field: str):
    def damage(root: Path) -> None:
        rows = _rows(root, table)
        rows[row][field] = "no-such-token"
        _put(root, table, rows)
    return damage


def _drop_field(root: Path) -> None:
    rows = _rows(root, "sample_data")
    del rows[0]["timestamp"]
    _put(root, "sample_data", rows)


def _map_not_json(root: Path) -> None:
    for p in (root / "maps").rglob("*.json"):
        p.write_text("{")


#: name -> (damage(dataset root), words of the error)
DAMAGE = {
    "sample_data -> missing ego_pose": (_link("sample_data", 3, "ego_pose_token"), "ego_pose.json has no record"),
    "sample_data -> missing calibrated_sensor": (_link("sample_data", 3, "calibrated_sensor_token"),
                                                 "calibrated_sensor.json has no record"),
    "scene -> missing first sample": (_link("scene", 0, "first_sample_token"), "sample.json has no record"),
    "sample -> missing next": (_link("sample", 1, "next"), "sample.json has no record"),
    "annotation -> missing instance": (_link("sample_annotation", 0, "instance_token"),
                                       "instance.json has no record"),
    "scene -> missing log": (_link("scene", 0, "log_token"), "log.json has no record"),
    "table not a list": (lambda root: _put(root, "sample", {"a": 1}), "not a JSON list of records"),
    "record without a field": (_drop_field, "lacks the field 'timestamp'"),
    "map expansion not JSON": (_map_not_json, "boston-seaport.json: not valid JSON"),
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_nuscenes(tmp_path_factory.mktemp("nus"))


def _import(data: Path, out: Path) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main(["import", "nuscenes", str(data), "--version", "v1.0-mini", "--scene", SCENE, "--out", str(out)])
    assert "Traceback" not in err.getvalue()
    return rc, err.getvalue()


@pytest.mark.parametrize("name", list(DAMAGE))
def test_damaged_dataset(dataset, tmp_path, name):
    damage, said = DAMAGE[name]
    data = tmp_path / "nus"
    shutil.copytree(dataset, data)
    damage(data)
    rc, err = _import(data, tmp_path / "out")
    assert rc == 1 and "error: " in err and said in err, err
    assert not (tmp_path / "out" / SCENE).exists()
    assert not list((tmp_path / "out").glob(".*partial*")) if (tmp_path / "out").exists() else True


@pytest.mark.slow
def test_sigkill_mid_import_leaves_no_bag_and_a_rerun_succeeds(tmp_path):
    data = write_nuscenes(tmp_path / "nus", samples=40, scenes=1)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "bags.cli.main", "import", "nuscenes", str(data), "--version", "v1.0-mini",
           "--scene", SCENE, "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob(f".{SCENE}.partial-*/*/*.mcap")) and proc.poll() is None:
            assert time.monotonic() < deadline, "the import never started writing"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == -signal.SIGKILL, "the import ended before the kill: make the dataset larger"
    assert not (out / SCENE).exists()  # nothing half-written under the final name
    left = list(out.glob(f".{SCENE}.partial-{proc.pid}"))
    assert left  # the killed process's temporary (it could not clean up)
    rc, err = _import(data, out)
    assert rc == 0, err
    assert not list(out.glob(".*partial*")), "the rerun left the killed import's temporary"
    with BagReader(out / SCENE) as r:
        assert sum(1 for _ in r.frames(gt=False)) > 0
