"""The node's ``label_map`` parameter naming a hostile file (issue #29): a nested-list bomb, exotic
digits, hex ids, a FIFO, a directory, a link to /dev/zero. ``main()`` exits 2 with one short
``error:`` line naming the file, without a traceback and without reading forever."""

from __future__ import annotations

import os

import pytest
from test_node import run_main_in_process

CASES = {
    "nested_lists": "labels: " + "[" * 50_000 + "]" * 50_000 + "\n",
    "nested_maps": "labels: " + "{a: " * 30_000 + "1" + "}" * 30_000 + "\n",
    "superscript": "labels: {'\u00b2': road}\n",
    "arabic_digit": "labels: {\u0663: road}\n",
    "hex_id": "labels: {0x10: road}\n",
    "huge_name": "labels: {1: " + "x" * 1_000_000 + "}\n",
    "fifo": None,
    "directory": None,
    "dev_zero": None,
}


@pytest.mark.parametrize("case", list(CASES))
def test_hostile_label_map_parameter_is_one_error_line(case, tmp_path, ros_domain, monkeypatch, capsys):
    path = tmp_path / "map.yaml"
    if case == "fifo":
        os.mkfifo(path)
    elif case == "directory":
        path.mkdir()
    elif case == "dev_zero":
        path.symlink_to("/dev/zero")
    else:
        path.write_text(CASES[case], encoding="utf-8")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    code, err = run_main_in_process(["-p", "method:=ipm", "-p", f"label_map:={path}"], capsys)
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert code == 2 and len(lines) == 1, err[:2000]
    assert str(path) in lines[0] and len(lines[0]) < 500 and "Traceback" not in err, lines[0][:600]
