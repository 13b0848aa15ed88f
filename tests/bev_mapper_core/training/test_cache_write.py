"""The drive cache's atomic write (``training.data._write_cache``): an exception raised anywhere in
it, as SIGTERM's is raised by ``bev-train``'s handler, comes out as itself and leaves no file."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from bev_mapper_core.training.data import _write_cache


class Interrupted(BaseException):
    """Stands for the command line's ``Terminated`` (a BaseException raised by a signal handler)."""


def _arrays() -> dict[str, np.ndarray]:
    return {"labels": np.arange(24, dtype=np.uint8).reshape(2, 3, 4), "stamps": np.arange(2, dtype=np.int64)}


def test_written_file_reads_back_and_is_the_same_bytes_every_time(tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    _write_cache(a, _arrays())
    _write_cache(b, _arrays())
    assert a.read_bytes() == b.read_bytes()  # fixed member dates: the bytes depend on the arrays only
    with np.load(a) as z:
        assert all(np.array_equal(z[k], v) for k, v in _arrays().items())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]


@pytest.mark.parametrize("where", ["opening a member", "writing a member"])
def test_an_interruption_comes_out_as_itself_and_leaves_no_file(tmp_path, monkeypatch, where):
    """Raised while zipfile opens a member, zipfile's own close used to replace it with "Can't
    close the ZIP file while there is an open writing handle" (bev-train exited 1 with a
    traceback on SIGTERM instead of 143)."""
    if where == "opening a member":
        def interrupt(*args, **kwargs):
            raise Interrupted()

        monkeypatch.setattr(zipfile, "_get_compressor", interrupt)
    else:
        calls = []

        def interrupt(*args, **kwargs):
            calls.append(1)
            if len(calls) == 2:  # the second member: the first is complete in the file
                raise Interrupted()
            return real(*args, **kwargs)

        real = np.lib.format.write_array
        monkeypatch.setattr(np.lib.format, "write_array", interrupt)
    with pytest.raises(Interrupted):
        _write_cache(tmp_path / "drive.npz", _arrays())
    assert list(tmp_path.iterdir()) == []  # neither the drive nor its temporary file
