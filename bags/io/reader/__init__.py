"""Reading bev_mapper bags: :class:`BagReader` (the rig, the grid, synchronized frames), the
:class:`BagFrame` and :class:`BagMessage` it hands out and :data:`DEFAULT_SYNC`.

Modules: :mod:`~bags.io.reader.bag_reader` (the reader), :mod:`~bags.io.reader.assembly` (the
frames of one pass), :mod:`~bags.io.reader.frame` (what is handed out).
"""

from .bag_reader import BagReader
from .frame import DEFAULT_SYNC, MS, BagFrame, BagMessage

__all__ = ["DEFAULT_SYNC", "MS", "BagFrame", "BagMessage", "BagReader"]
