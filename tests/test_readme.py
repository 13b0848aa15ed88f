"""README.md as a front page, and the docs it links to: its generated tables equal what the code
renders, the figures it quotes are checked, every relative link resolves.

- the parameter and diagnostics tables equal :mod:`bev_mapper_ros.reference`'s rendering
  (``python -m bev_mapper_ros.reference --write`` rewrites them);
- the demo-drive results table equals fresh replays of the demo drive
  (``experiments/demo_figures.py --readme`` rewrites it; slow: three replays of 50 frames);
- each held-out figure of the README is found in the docs/RESULTS.md section its row links to;
- every relative link (and ``#anchor`` into a markdown file) of README.md, docs/*.md and
  experiments/README.md resolves.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = [README, *sorted((REPO / "docs").glob("*.md")), REPO / "experiments" / "README.md"]


def _demo_figures():
    spec = importlib.util.spec_from_file_location("demo_figures", REPO / "experiments" / "demo_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _without_code(text: str) -> str:
    """``text`` without fenced code blocks and inline code (links there are not links)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading.strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M)
    for m in re.finditer(r"^#{1,6} +(.+?) *#*$", text, re.M):
        slug = _slug(m.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def _links(path: Path) -> list[str]:
    return re.findall(r"\]\(([^)\s]+)\)", _without_code(path.read_text()))


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(doc):
    bad = []
    for link in _links(doc):
        if re.match(r"[a-z]+:", link):  # https:, mailto:
            continue
        target, _, anchor = link.partition("#")
        path = (doc.parent / target).resolve() if target else doc
        if not path.exists():
            bad.append(f"{link}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
            bad.append(f"{link}: no heading #{anchor} in {path.relative_to(REPO)}")
    assert not bad, f"{doc.relative_to(REPO)}:\n" + "\n".join(bad)


def test_setup_commands_within_the_first_60_lines():
    lines = README.read_text().splitlines()[:60]
    for command in ("bash scripts/demo.sh    # main job", "bash scripts/test.sh    # the whole test suite"):
        assert any(line.startswith(command) for line in lines), command


def _block(name: str) -> str:
    text = README.read_text()
    m = re.search(rf"<!-- {name}:begin[^>]*-->\n(.*?)\n?<!-- {name}:end -->", text, re.S)
    assert m, f"README.md has no {name} block"
    return m.group(1).strip("\n")


@pytest.mark.ros  # bev_mapper_ros.params imports rclpy
@pytest.mark.parametrize("name", ["params", "diagnostics"])
def test_reference_tables_are_generated(name):
    from bev_mapper_ros.reference import TABLES

    assert _block(name) == TABLES[name](), f"run: .venv/bin/python -m bev_mapper_ros.reference --write ({name})"


@pytest.mark.ros
def test_every_diagnostics_key_of_the_node_is_described():
    from bev_mapper_ros.reference import NODE_DIAGNOSTIC_KEYS, diagnostic_keys

    source = (REPO / "bev_mapper_ros" / "mapper_node.py").read_text()
    added = set(re.findall(r"values\[\"(\w+)\"\] *=", source))
    assert added <= set(NODE_DIAGNOSTIC_KEYS), added - set(NODE_DIAGNOSTIC_KEYS)
    assert {"rate_hz", "latency_ms", "drop_ratio", "temporal_note", "use_sim_time"} <= set(diagnostic_keys())


def _section(doc: Path, anchor: str) -> str:
    """The text of the section of ``doc`` under the heading ``#anchor`` (to the next heading of its level or above)."""
    lines = doc.read_text().splitlines()
    for i, line in enumerate(lines):
        m = re.match(r"^(#{1,6}) +(.+)$", line)
        if m and _slug(m.group(2)) == anchor:
            level = len(m.group(1))
            end = next((j for j in range(i + 1, len(lines))
                        if re.match(rf"^#{{1,{level}}} ", lines[j])), len(lines))
            return "\n".join(lines[i:end])
    raise AssertionError(f"no heading #{anchor} in {doc}")


def test_held_out_figures_are_in_the_linked_results():
    rows = [r for r in _block("held-out").splitlines() if r.startswith("| ") and "](" in r]
    assert len(rows) >= 5
    for row in rows:
        link = re.search(r"\]\(([^)#]+)#([^)]+)\)", row)
        section = _section(REPO / link.group(1), link.group(2))
        cells = row.split(" | ")
        figures = re.findall(r"\d+\.\d", cells[2] + " " + cells[3])
        assert len(figures) == 2, row
        for figure in figures:
            assert re.search(rf"(?<![\d.]){re.escape(figure)}(?![\d])", section), f"{figure} not in {link.group(0)}: {row}"


def test_speed_table_markers_are_where_bench_table_writes():
    source = (REPO / "bench" / "bench_table.py").read_text()
    assert 'TARGET = BENCH.parent / "docs" / "SPEED.md"' in source
    text = (REPO / "docs" / "SPEED.md").read_text()
    assert "<!-- bench-table:start -->" in text and "<!-- bench-table:end -->" in text


def test_demo_block_renders_every_row():
    figures = _demo_figures()
    table = _block("demo-figures").splitlines()
    assert table[0] == figures.HEADER.splitlines()[0]
    assert len(table) == 2 + len(figures.ROWS)


@pytest.mark.slow
def test_demo_figures_equal_a_replay_of_the_demo_drive():
    """The README's demo-drive table equals fresh replays of the demo drive (as ``bash scripts/demo.sh``)."""
    figures = _demo_figures()
    assert _block("demo-figures") == figures.table(figures.measure()), \
        "run: .venv/bin/python experiments/demo_figures.py --readme"
