"""Integrity checks of bag storage files, run when a bag is opened (:mod:`bags.io.sources`).

* MCAP: the footer's summary CRC and the DataEnd record's data section CRC are verified when
  the file carries them (:mod:`bags.mcap_checksums`, where the results are remembered per file).
  Chunk CRCs are verified by the readers whenever a chunk is read, unless the data section CRC
  was verified (:func:`data_crc_verified`; :mod:`bags.io.raw.mcap_index`).
* sqlite3: messages whose ``topic_id`` is not in the ``topics`` table (their topic, hence
  their type, is unknown: rosbags skips them silently).

Each check returns ``None`` for a file that passed (or carries nothing to verify) and a
sentence describing the damage otherwise; they never raise for a damaged file.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

# the MCAP checks live in a module that imports nothing else of the package, so that the command
# line can start them before it loads the rest (bags/cli/main.py)
from ..mcap_checksums import check_mcap, data_crc_verified  # noqa: E402,F401 - re-exported


def check_sqlite(path: Path) -> str | None:
    """Messages of a rosbag2 sqlite3 file whose ``topic_id`` is not in its ``topics`` table."""
    uri = f"{Path(path).resolve().as_uri()}?mode=ro&immutable=1"
    try:
        con = sqlite3.connect(uri, uri=True)
    except sqlite3.Error:
        return None  # unreadable: rosbags reports it
    try:
        rows = con.execute(
            "SELECT topic_id, COUNT(*) FROM messages "
            "WHERE topic_id NOT IN (SELECT id FROM topics) GROUP BY topic_id"
        ).fetchall()
    except sqlite3.Error as exc:
        return f"{Path(path).name}: sqlite3 database is damaged: {exc}"
    finally:
        con.close()
    if not rows:
        return None
    n = sum(count for _, count in rows)
    ids = sorted(tid for tid, _ in rows)
    return (f"{Path(path).name}: {n} message(s) reference topic id(s) {ids[:10]} missing from "
            "the topics table (their topic and type are unknown; they cannot be read)")
