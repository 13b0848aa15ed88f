"""bags.memory: a replaying process reuses freed memory instead of faulting in fresh pages."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: a child that allocates and frees the arrays of a replay's frame (a few MB each, as decoded
#: layers, predictions and masks) 40 times and prints its minor page faults
_CHILD = """
import resource, sys
import numpy as np
from bags.memory import keep_freed_memory
chosen = keep_freed_memory() if sys.argv[1] == "keep" else False
def frame():
    arrays = [np.ones(n, np.uint8) for n in (2_240_000, 560_000, 5_000_000, 2_240_000, 80_000, 9_000_000)]
    del arrays
frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(40):
    frame()
print(chosen, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str, env=None) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _CHILD, mode], capture_output=True, text=True, check=True,
                         env=env).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_arrays_are_reused_instead_of_faulted_in_again():
    chosen, kept = _faults("keep")
    _, fresh = _faults("plain")
    assert chosen == "True"
    assert fresh > 40 * 1000  # glibc gives most of the frame's 19 MB back and faults it in again
    assert kept < fresh / 20


def test_an_environment_that_chose_wins():
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "1000000"}
    assert _faults("keep", env)[0] == "False"
