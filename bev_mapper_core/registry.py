"""Lazy ``"module:attr"`` references, as the method registries of the mapper and the trainer use
them: a method's module (and torch with it) is imported only when the method is used.
"""

from __future__ import annotations

import importlib
from typing import Any


def resolve(target: Any) -> Any:
    """``target`` itself, or the attribute a ``"package.module:attr"`` string names (imported now)."""
    if isinstance(target, str):
        module, _, attr = target.partition(":")
        return getattr(importlib.import_module(module), attr)
    return target
