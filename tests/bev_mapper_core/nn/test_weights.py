"""Weights paths that are no regular file are named for what they are (issue #41): a directory,
a FIFO (never opened, so never waited on) or a link to a device, never "does not exist".
"""

from __future__ import annotations

import os
import threading

import pytest

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.mapper import MapperConfig, preflight
from bev_mapper_core.nn.weights import weights_file_problem


def _make(tmp_path, kind: str):
    path = tmp_path / "weights.safetensors"
    if kind == "directory":
        path.mkdir()
    elif kind == "FIFO":
        os.mkfifo(path)  # no writer: opening it for reading would block
    elif kind == "device":
        path.symlink_to("/dev/zero")  # endless: never to be read
    elif kind == "broken link":
        path.symlink_to(tmp_path / "gone")
    return path


EXPECTED = {
    "directory": "is a directory, not a weights file",
    "FIFO": "is a FIFO, not a regular file",
    "device": "is a device (a link to /dev/zero), not a regular file",
    "missing": "does not exist",
    "broken link": "does not exist (a broken link)",
}


@pytest.mark.parametrize("kind", list(EXPECTED))
def test_weights_file_problem_names_what_the_path_is(tmp_path, kind):
    assert weights_file_problem(_make(tmp_path, kind)) == EXPECTED[kind]


def test_a_regular_file_or_a_link_to_one_has_no_problem(tmp_path):
    (tmp_path / "w.safetensors").write_bytes(b"x")
    (tmp_path / "link.safetensors").symlink_to(tmp_path / "w.safetensors")
    assert weights_file_problem(tmp_path / "w.safetensors") is None
    assert weights_file_problem(tmp_path / "link.safetensors") is None


@pytest.mark.parametrize("method, rig, input_kind", [("bimapper", "surround6", "labels"), ("s2g2", "front1", "rgb"),
                                                      ("focusbev", "front1", "rgb")])
@pytest.mark.parametrize("kind", ["directory", "FIFO", "device"])
def test_every_learned_method_says_what_its_weights_path_is(tmp_path, method, rig, input_kind, kind):
    path = _make(tmp_path, kind)
    result: list = []

    def check():
        try:
            preflight(MapperConfig(method=method, weights=str(path), input_kind=input_kind), rig)
        except BevMapperError as exc:
            result.append(str(exc))

    t = threading.Thread(target=check, daemon=True)  # a reader blocked on the FIFO would hang here
    t.start()
    t.join(30)
    assert not t.is_alive(), "reading the weights blocked"
    assert len(result) == 1
    assert f"{path} {EXPECTED[kind]}" in result[0]
    assert "does not exist" not in result[0]
