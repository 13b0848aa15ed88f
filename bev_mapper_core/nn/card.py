"""Model cards: what a shipped weights file was trained on, under which licenses, what that means
for the file, its input, its classes, its measured scores and how it was trained.

A card is the ``card`` object of a weights file's metadata document (the JSON document under
``bev_mapper`` in the safetensors header, :mod:`bev_mapper_core.nn.weights`), beside the format's
own keys; every weights reader accepts a document with or without one, and refuses a malformed
card (:func:`check_card`, called by :func:`~bev_mapper_core.nn.weights.read_document`).
``docs/MODELS.md`` is generated from the shipped files' cards
(:mod:`bev_mapper_core.methods.cards`). A card::

    {"card_version": 1,
     "summary": "what the file is and what uses it",
     "input": "input size and kind, e.g. 'RGB, resized to 320 px wide (320x180 for 400x225)'",
     "classes": ["road", ...],                  # the output classes, in layer order
     "training_data": [{"name": "...", "kind": "synthetic" | "real",
                        "description": "seeds, styles, splits, frame counts",
                        "license": "Apache-2.0 ...", "source": "where it comes from"}, ...],
     "license": {"weights": "the terms the file itself is under",
                 "use": "what that means for a user of the file, said plainly"},
     "training": {"command": "the command(s) that trained it", "details": "recipe, device, choice"},
     "scores": [{"data": "held-out data", "metric": "pooled pixel IoU %, ...",
                 "values": {"name": number, ...}, "command": "the command that measured it",
                 "note": "optional"}, ...]}

Keys beyond these are kept and ignored (a later card version may add some).
"""

from __future__ import annotations

import math

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import Label, bev_class

CARD_KEY = "card"
CARD_VERSION = 1
#: longest text field, in characters (a card is read before any tensor; keep it bounded)
MAX_TEXT = 8000
#: most items of a list (training data sets, scores, classes) or score values
MAX_ITEMS = 64
DATA_KINDS = ("synthetic", "real")

_TOP = {"card_version": int, "summary": str, "input": str, "classes": list, "training_data": list,
        "license": dict, "training": dict, "scores": list}
_DATA = {"name": str, "kind": str, "description": str, "license": str, "source": str}
_LICENSE = {"weights": str, "use": str}
_TRAINING = {"command": str, "details": str}
_SCORE = {"data": str, "metric": str, "values": dict, "command": str}
_SCORE_OPTIONAL = {"note": str}


class CardError(ValueError):
    """A malformed model card; the message names the field."""


def _text(value, where: str) -> None:
    if not isinstance(value, str) or not value.strip():
        raise CardError(f"{where} must be a non-empty string, got {value!r:.80}")
    if len(value) > MAX_TEXT:
        raise CardError(f"{where} is longer than {MAX_TEXT} characters")


def _fields(obj, spec: dict, where: str, optional: dict | None = None) -> None:
    if not isinstance(obj, dict):
        raise CardError(f"{where} must be an object, got {type(obj).__name__}")
    missing = sorted(set(spec) - set(obj))
    if missing:
        raise CardError(f"{where} lacks {missing}")
    for key, typ in {**spec, **{k: t for k, t in (optional or {}).items() if k in obj}}.items():
        value = obj[key]
        if typ is str:
            _text(value, f"{where}.{key}")
        elif typ is list:
            if not isinstance(value, list) or not value or len(value) > MAX_ITEMS:
                raise CardError(f"{where}.{key} must be a list of 1..{MAX_ITEMS} items")
        elif typ is dict:
            if not isinstance(value, dict):
                raise CardError(f"{where}.{key} must be an object")
        elif typ is int and (isinstance(value, bool) or not isinstance(value, int)):
            raise CardError(f"{where}.{key} must be an integer, got {value!r:.80}")


def check_card(card) -> dict:
    """``card`` if it is a well-formed model card (see the module docstring).

    Raises:
        CardError: naming the first malformed field.
    """
    _fields(card, _TOP, "card")
    if card["card_version"] != CARD_VERSION:
        raise CardError(f"card.card_version is {card['card_version']}, this code reads {CARD_VERSION}")
    for i, name in enumerate(card["classes"]):
        _text(name, f"card.classes[{i}]")
    for i, data in enumerate(card["training_data"]):
        where = f"card.training_data[{i}]"
        _fields(data, _DATA, where)
        if data["kind"] not in DATA_KINDS:
            raise CardError(f"{where}.kind must be one of {DATA_KINDS}, got {data['kind']!r:.80}")
    _fields(card["license"], _LICENSE, "card.license")
    _fields(card["training"], _TRAINING, "card.training")
    for i, score in enumerate(card["scores"]):
        where = f"card.scores[{i}]"
        _fields(score, _SCORE, where, _SCORE_OPTIONAL)
        values = score["values"]
        if not values or len(values) > MAX_ITEMS:
            raise CardError(f"{where}.values must hold 1..{MAX_ITEMS} named numbers")
        for name, v in values.items():
            _text(name, f"{where}.values key")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise CardError(f"{where}.values[{name!r}] must be a finite number, got {v!r:.80}")
    return card


def document_classes(meta: dict) -> list | None:
    """The output classes a weights document stores (``classes``, or a segmenter's
    ``config.labels``), None when it names none.
    """
    if isinstance(meta.get("classes"), list):
        return meta["classes"]
    config = meta.get("config")
    if isinstance(config, dict) and isinstance(config.get("labels"), list):
        return config["labels"]
    return None


def _known_class(name: str) -> bool:
    """A BEV class (any class set) or a pixel label name."""
    if name.upper() in Label.__members__:
        return True
    try:
        bev_class(name)
    except ConfigError:
        return False
    return True


def check_card_fits(card: dict, meta: dict) -> None:
    """A card against the document it is stored in: the same classes, in the same order.

    Raises:
        CardError: the classes differ.
    """
    stored = document_classes(meta)
    if stored is None or not all(isinstance(c, str) and _known_class(c) for c in stored):
        return  # the document's own check refuses unknown classes, with its own message
    if list(card["classes"]) != list(stored):
        raise CardError(f"card.classes {card['classes']} differ from the weights' classes {stored}")


__all__ = ["CARD_KEY", "CARD_VERSION", "CardError", "check_card", "check_card_fits", "document_classes"]
