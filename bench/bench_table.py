"""The speed table of docs/SPEED.md, generated: runs the benchmarks one after another on this machine,
each printing ours next to its reference measured in the same run, and collects their rows.

    .venv/bin/python bench/bench_table.py            # print the table (a few minutes)
    .venv/bin/python bench/bench_table.py --write    # ... and write it into docs/SPEED.md

Rows: IPM against its earlier algorithm (``bench_ipm.py``); Bi-Mapper by inference backend
against torch eager, and by thread count with a competing process (``bench_backends.py
--competitor``); the node at 10 and 20 Hz with reliable publishers and at 10 Hz with
best-effort ones, and with ``backend:=torch`` against the default ``auto`` (``bench_node_rate.py``);
replay against reading in turn (``bench_replay.py``) and its marginal rate against real time, ours
scored in the replay's own process, the reading and writing before #28's second part and
everything before #28 (``bench_replay_rate.py``); the node's start to its first grid per
method, cold and warm export cache (``bench_node_startup.py --methods``);
1600 x 900 cameras against 400 x 225 ones on RGB (``bench_full_resolution.py``).
Run it on a quiet machine: every figure is a wall-clock time (on a shared one, only the ratios
of a row hold).
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import subprocess
import sys
import tempfile

from bench_rows import machine

BENCH = pathlib.Path(__file__).resolve().parent
TARGET = BENCH.parent / "docs" / "SPEED.md"
START, END = "<!-- bench-table:start -->", "<!-- bench-table:end -->"

#: (script, arguments) in the order the table shows them
RUNS = (
    ("bench_ipm.py", []),
    ("bench_backends.py", ["--competitor", "--frames", "6"]),
    ("bench_node_rate.py", ["--hz", "10", "--seconds", "15"]),
    ("bench_node_rate.py", ["--hz", "20", "--seconds", "15"]),
    ("bench_node_rate.py", ["--hz", "10", "--seconds", "15", "--publishers", "best_effort"]),
    ("bench_node_rate.py", ["--hz", "10", "--seconds", "15", "--node-arg", "backend:=torch"]),
    ("bench_replay.py", []),
    ("bench_replay_rate.py", []),
    ("bench_replay_e2e.py", ["--repeat", "2", "--loads", "0", "1", "--settings", "auto", "off"]),
    ("bench_node_startup.py", ["--methods", "--runs", "1"]),
    ("bench_full_resolution.py", []),
)


def run_all(log) -> list[dict]:
    """Run every benchmark of :data:`RUNS`; their rows, in order."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_table_") as tmp:
        for k, (script, args) in enumerate(RUNS):
            out = pathlib.Path(tmp) / f"{k}.json"
            cmd = [sys.executable, str(BENCH / script), *args, "--json", str(out)]
            log(f"$ {' '.join(['.venv/bin/python', f'bench/{script}', *args])}")
            proc = subprocess.run(cmd, cwd=BENCH.parent, capture_output=True, text=True)
            log(proc.stdout.rstrip())
            if proc.returncode != 0 or not out.exists():
                raise SystemExit(f"error: bench/{script} failed (status {proc.returncode}):\n{proc.stderr[-2000:]}")
            for r in json.loads(out.read_text())["rows"]:
                rows.append({**r, "command": f"bench/{script} {' '.join(args)}".strip()})
    return rows


def markdown(rows: list[dict]) -> str:
    """The table, with the machine, the date and the command that made it."""
    lines = [f"Measured by `.venv/bin/python bench/bench_table.py --write` on {machine()}, "
             f"{datetime.date.today().isoformat()}. Ratio: the reference's time over ours (above 1: ours is "
             "faster); for the node, sets mapped over sets published; for replay, the pipeline's speed over one thread; "
             "for replay's marginal rate, ours over ours scored in the replay's own process, over the reading and "
             "writing before #28's second part and over everything before #28; for the start-up, torch's over the "
             "warm export cache's. The machine was shared with other jobs: a row's two figures come from the same "
             "run, interleaved where the row says so, and only their ratio carries over.",
             "",
             "| path | ours | reference, same run | ratio | note | command |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        ratio = "" if r["ratio"] is None else f"{r['ratio']:.2f}"
        lines.append(f"| {r['path']} | {r['ours']} | {r['reference']} | {ratio} | {r['note']} | `{r['command']}` |")
    return "\n".join(lines)


def write_table(table: str) -> None:
    """Replace the text between the table markers of :data:`TARGET`."""
    text = TARGET.read_text()
    if START not in text or END not in text:
        raise SystemExit(f"error: {TARGET} has no {START} ... {END} block")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    TARGET.write_text(f"{head}{START}\n{table}\n{END}{tail}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="write the table into docs/SPEED.md")
    args = ap.parse_args()
    table = markdown(run_all(lambda s: print(s, file=sys.stderr, flush=True)))
    print(table)
    if args.write:
        write_table(table)


if __name__ == "__main__":
    main()
