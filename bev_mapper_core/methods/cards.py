"""The model cards of the shipped weights files, and ``docs/MODELS.md`` made from them.

Each file named in a method's ``weights`` (:data:`~bev_mapper_core.methods.METHODS`) carries its
card in its metadata document (:mod:`bev_mapper_core.nn.card`). ``docs/MODELS.md`` is generated
from the files, never edited by hand; a test checks that it equals what the files say.

::

    python -m bev_mapper_core.methods.cards write            # docs/MODELS.md from the shipped files
    python -m bev_mapper_core.methods.cards check            # exit 1 if docs/MODELS.md is stale
    python -m bev_mapper_core.methods.cards show FILE        # a file's card as JSON
    python -m bev_mapper_core.methods.cards set FILE CARD.json   # store a card in FILE

``set`` rewrites the header only: the tensors are loaded with safetensors and saved again with
the new document, and the new file's tensor section is checked to be byte for byte the old
one's before it replaces the file (:func:`set_card`). Reading a card or rendering the page
parses safetensors headers only (no torch).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import struct
import sys
from pathlib import Path

from bev_mapper_core.nn.card import CARD_KEY, CardError, check_card, check_card_fits

from . import METHODS, WEIGHTS_DIR

#: the page generated from the cards
MODELS_MD = Path(__file__).resolve().parents[2] / "docs" / "MODELS.md"
META_KEY = "bev_mapper"  # = bev_mapper_core.nn.weights.META_KEY (that module imports torch)
#: largest safetensors header read here (the shipped files' are under 64 KiB)
MAX_HEADER = 16 * 1024 * 1024
_BN_STATS = ("running_mean", "running_var", "num_batches_tracked")


def shipped_files() -> dict[str, list[str]]:
    """Every shipped weights file (name in :data:`WEIGHTS_DIR`) -> the methods that read it, in
    the order of :data:`METHODS`.
    """
    files: dict[str, list[str]] = {}
    for method, spec in METHODS.items():
        for name in spec.weights:
            files.setdefault(name, []).append(method)
    return files


def read_header(path: str | os.PathLike) -> tuple[dict, dict, int]:
    """``(tensor entries, metadata document, header length)`` of a safetensors file, from its
    header alone: tensor name -> ``{"dtype", "shape", "data_offsets"}``; the document is the
    JSON under ``bev_mapper`` ({} if absent).

    Raises:
        CardError: not a safetensors file, or a document that is not a JSON object.
    """
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) != 8:
            raise CardError(f"{path}: not a safetensors file (shorter than 8 bytes)")
        n = struct.unpack("<Q", head)[0]
        if n > MAX_HEADER:
            raise CardError(f"{path}: header of {n} bytes, more than {MAX_HEADER}")
        raw = f.read(n)
    try:
        header = json.loads(raw)
        meta = json.loads((header.pop("__metadata__", None) or {}).get(META_KEY, "{}"))
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError) as e:
        raise CardError(f"{path}: unreadable safetensors header ({e})") from None
    if not isinstance(meta, dict):
        raise CardError(f"{path}: the {META_KEY!r} metadata is not a JSON object")
    return header, meta, n


def read_card(path: str | os.PathLike) -> dict | None:
    """The checked card of a weights file, None if it has none.

    Raises:
        CardError: an unreadable header or a malformed card.
    """
    _, meta, _ = read_header(path)
    if CARD_KEY not in meta:
        return None
    try:
        check_card_fits(check_card(meta[CARD_KEY]), meta)
    except CardError as e:
        raise CardError(f"{path}: {e}") from None
    return meta[CARD_KEY]


def set_card(path: str | os.PathLike, card: dict, out: str | os.PathLike | None = None) -> dict:
    """Store ``card`` in the metadata document of the weights file ``path`` (written to ``out``,
    default: ``path`` itself, replaced atomically). Every other key of the document is kept.

    The tensors are loaded with safetensors and saved again with the new document; before the
    new file replaces anything, its tensor entries (names, dtypes, shapes, offsets) and its
    whole tensor section are compared byte for byte with the old file's, and the tensors read
    back are compared bit for bit. Returns ``{"tensors": n, "tensor_bytes": bytes}``.

    Raises:
        CardError: a malformed card, classes that differ from the file's, a file without a
            ``bev_mapper`` document, or tensors that would change (nothing is then written).
    """
    import torch
    from safetensors.torch import load_file, save_file

    path = Path(path)
    out = Path(out) if out is not None else path
    entries, meta, n = read_header(path)
    if not meta:
        raise CardError(f"{path}: no {META_KEY!r} metadata document; not a bev_mapper weights file")
    check_card_fits(check_card(card), meta)
    doc = {**meta, CARD_KEY: card}
    tensors = load_file(str(path))
    tmp = out.with_name(out.name + ".card.tmp")
    try:
        # the document's keys keep their order (not sorted): a card's score values read in the order written
        save_file(tensors, str(tmp), metadata={META_KEY: json.dumps(doc, ensure_ascii=False)})
        new_entries, new_meta, new_n = read_header(tmp)
        if new_entries != entries or new_meta != doc:
            raise CardError(f"{path}: the rewritten header's tensor entries differ from the old ones")
        old_data, new_data = path.read_bytes()[8 + n:], tmp.read_bytes()[8 + new_n:]
        if old_data != new_data:
            raise CardError(f"{path}: the rewritten file's tensor bytes differ from the old ones")
        back = load_file(str(tmp))
        if set(back) != set(tensors) or not all(
                back[k].dtype == t.dtype and back[k].shape == t.shape
                and torch.equal(back[k].reshape(-1).view(torch.uint8), t.reshape(-1).view(torch.uint8))
                for k, t in tensors.items()):
            raise CardError(f"{path}: the tensors read back differ from the old ones")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return {"tensors": len(tensors), "tensor_bytes": len(old_data)}


# ------------------------------------------------------------------------------------ the page
def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _number(v) -> str:
    return str(v)  # as stored: 90.7, 0.0, 0.01


def render_file(name: str, methods: list[str], path: Path) -> str:
    """One file's section of ``docs/MODELS.md``.

    Raises:
        CardError: the file has no card, or a malformed one.
    """
    entries, meta, _ = read_header(path)
    card = read_card(path)
    if card is None:
        raise CardError(f"{path}: no model card (every shipped weights file needs one)")
    params = sum(math.prod(e["shape"]) for k, e in entries.items() if not k.endswith(_BN_STATS))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    lines = [f"## `{name}`", "", card["summary"], "",
             f"* **File**: `bev_mapper_core/weights/{name}`, {path.stat().st_size:,} bytes, sha256 `{digest}`",
             f"* **Read by**: {', '.join(f'`{m}`' for m in methods)}; format `{meta.get('format')}` "
             f"version {meta.get('version')}" + (f", rig `{meta['rig']}`" if meta.get("rig") else ""),
             f"* **Parameters**: {params:,} (BatchNorm statistics not counted)",
             f"* **Input**: {card['input']}",
             f"* **Classes** ({len(card['classes'])}): {', '.join(card['classes'])}",
             "", "### Training data", "",
             "| data | kind | what | license | source |", "|---|---|---|---|---|"]
    lines += [f"| {_cell(d['name'])} | {d['kind']} | {_cell(d['description'])} | {_cell(d['license'])} | "
              f"{_cell(d['source'])} |" for d in card["training_data"]]
    lines += ["", "### License of this file", "", f"**{card['license']['weights']}**", "", card["license"]["use"],
              "", "### Scores", ""]
    for s in card["scores"]:
        lines += [f"**{s['data']}**: {s['metric']}", "",
                  "| " + " | ".join(_cell(k) for k in s["values"]) + " |",
                  "|" + "---|" * len(s["values"]),
                  "| " + " | ".join(_number(v) for v in s["values"].values()) + " |", ""]
        if s.get("note"):
            lines += [s["note"], ""]
        lines += ["```sh", s["command"], "```", ""]
    lines += ["### Training", "", card["training"]["details"], "", "```sh", card["training"]["command"], "```", ""]
    return "\n".join(lines)


def render_models_md(weights_dir: Path = WEIGHTS_DIR) -> str:
    """``docs/MODELS.md``: a section per shipped weights file, from the files' cards.

    Raises:
        CardError: a shipped file without a card, or with a malformed one.
    """
    files = shipped_files()
    head = ["# Model cards of the shipped weights", "",
            "<!-- generated by `python -m bev_mapper_core.methods.cards write` from the cards in the files' "
            "metadata; do not edit by hand -->", "",
            "Every weights file the package ships carries its model card in its safetensors metadata (the "
            "`card` object of the `bev_mapper` document; `python -m bev_mapper_core.methods.cards show FILE` "
            "prints it). This page is generated from those cards. The package's code is Apache-2.0; a weights "
            "file is under the terms its card names, which follow from its training data.", "",
            "| file | read by | training data | license of the file |", "|---|---|---|---|"]
    sections = []
    for name, methods in files.items():
        path = weights_dir / name
        card = read_card(path)
        if card is None:
            raise CardError(f"{path}: no model card (every shipped weights file needs one)")
        head.append(f"| `{name}` | {', '.join(methods)} | "
                    f"{_cell('; '.join(d['name'] for d in card['training_data']))} | {_cell(card['license']['weights'])} |")
        sections.append(render_file(name, methods, path))
    return "\n".join(head) + "\n\n" + "\n".join(sections).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    """Command line entry (see the module docstring); 0 done, 1 stale page or no card, 2 error."""
    ap = argparse.ArgumentParser(prog="python -m bev_mapper_core.methods.cards", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write", help="write docs/MODELS.md from the shipped files' cards")
    w.add_argument("--out", default=str(MODELS_MD))
    c = sub.add_parser("check", help="exit 1 if docs/MODELS.md differs from the shipped files' cards")
    c.add_argument("--page", default=str(MODELS_MD))
    s = sub.add_parser("show", help="print a weights file's card as JSON")
    s.add_argument("file")
    t = sub.add_parser("set", help="store a card (a JSON file) in a weights file; its tensors stay byte for byte")
    t.add_argument("file")
    t.add_argument("card")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "write":
            Path(args.out).write_text(render_models_md())
            print(f"wrote {args.out}")
        elif args.cmd == "check":
            page = Path(args.page)
            if not page.is_file() or page.read_text() != render_models_md():
                print(f"error: {page} differs from the shipped files' cards; run "
                      "python -m bev_mapper_core.methods.cards write", file=sys.stderr)
                return 1
            print(f"{page} matches the shipped files' cards")
        elif args.cmd == "show":
            card = read_card(args.file)
            if card is None:
                print(f"error: {args.file} has no model card", file=sys.stderr)
                return 1
            print(json.dumps(card, indent=1, ensure_ascii=False))
        else:
            try:
                card = json.loads(Path(args.card).read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise CardError(f"{args.card}: {e}") from None
            done = set_card(args.file, card)
            print(f"{args.file}: card stored; {done['tensors']} tensors ({done['tensor_bytes']:,} bytes) unchanged")
    except (CardError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
