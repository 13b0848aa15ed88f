"""Reading a bag's messages fast: raw messages of indexed MCAP files through their indexes
(:mod:`~bags.io.raw.mcap_index`) and Images and OccupancyGrids decoded as views of their CDR bytes
(:mod:`~bags.io.raw.cdr`). :mod:`bags.io.sources` uses both; what they cannot read is left to
``rosbags``.
"""

from .cdr import fast_deserializer
from .mcap_index import IndexedMcap, McapIndexError

__all__ = ["IndexedMcap", "McapIndexError", "fast_deserializer"]
