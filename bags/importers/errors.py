"""Exception types of the dataset importers (``bev-bag import``).

All derive from :class:`DatasetError`, a :class:`~bags.errors.BagError`: the command line prints
them as ``error: ...`` and exits non-zero.
"""

from __future__ import annotations

from ..errors import BagError


class DatasetError(BagError):
    """A dataset cannot be imported."""


class DatasetLayoutError(DatasetError):
    """A table, map or folder the importer needs is missing or not what it should be."""


class DatasetVersionError(DatasetError):
    """The dataset on disk is another version than the one asked for."""


class SceneNotFoundError(DatasetError):
    """A scene (or log) asked for is not in the dataset."""


class MissingDevkitError(DatasetError):
    """An optional dependency the importer needs for this input is not installed."""


__all__ = ["DatasetError", "DatasetLayoutError", "DatasetVersionError", "MissingDevkitError", "SceneNotFoundError"]
