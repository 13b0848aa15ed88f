"""What the benchmarks hand to ``bench/bench_table.py``: rows of "ours next to its reference,
measured in the same run", written as JSON with ``--json PATH``.

A row: ``{"path": what runs, "ours": figure, "reference": figure, "ratio": reference / ours or
None, "note": ...}``; figures are strings with their unit, as printed.
"""

from __future__ import annotations

import json
import os
import platform
from pathlib import Path


def machine() -> str:
    """The CPU model and the CPUs this process may use, e.g. ``AMD EPYC 7B13, 2 CPUs``."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{model}, {cpus} CPUs"


def row(path: str, ours: str, reference: str, ratio: float | None, note: str = "") -> dict:
    """One row (see the module docstring)."""
    return {"path": path, "ours": ours, "reference": reference,
            "ratio": None if ratio is None else round(float(ratio), 2), "note": note}


def write_rows(path: str | os.PathLike | None, bench: str, rows: list[dict]) -> None:
    """Write ``rows`` of benchmark ``bench`` to ``path`` (nothing when ``path`` is None)."""
    if path:
        Path(path).write_text(json.dumps({"bench": bench, "machine": machine(), "rows": rows}, indent=1) + "\n")
