"""Exception types of the bag tool.

All derive from :class:`BagError` (a :class:`bev_mapper_core.errors.BevMapperError`); the CLI
prints them as ``error: ...`` without a traceback.
"""

from __future__ import annotations

from bev_mapper_core.errors import BevMapperError


class BagError(BevMapperError):
    """A bag cannot be written or read."""


class BagExistsError(BagError):
    """The output path exists and overwriting was not allowed."""


class BagFormatError(BagError):
    """The path is not a bag this tool can open (unknown storage, missing metadata)."""


class BagContentError(BagError):
    """The bag lacks topics or messages the operation needs (no CameraInfo, no /tf_static...)."""


class BagCorruptError(BagError):
    """The bag is truncated or damaged; raised after yielding everything before the damage."""
