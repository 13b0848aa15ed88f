"""Bag I/O: rosbag2 bags (MCAP or SQLite 3) read and written with ``rosbags``, no ROS install needed.

Public names:

* :class:`BagReader` (with :class:`BagFrame`, :class:`BagMessage`, :data:`DEFAULT_SYNC`): a bag's
  topics, rig, grid and synchronized frames, damage reported as
  :class:`~bags.errors.BagCorruptError` after everything before it;
* :class:`BagWriter`, :func:`write_drive` (with :class:`DriveSummary`), :func:`check_output`,
  :data:`STORAGES`: writing bags atomically;
* :mod:`~bags.io.topics`: the topic names and message types of bev_mapper bags;
* :data:`BAG_SUFFIXES`, :class:`MetadataError`.

Also here, imported on their own: :mod:`~bags.io.train_data` (bags as training data for
``bev-train``; it imports the core's training package), :mod:`~bags.io.input_checks`,
:mod:`~bags.io.integrity`, :mod:`~bags.io.metadata`, :mod:`~bags.io.mcap_storage`,
:mod:`~bags.io.sources` (the readers' storage back ends) and :mod:`~bags.io.raw` (messages read
through an MCAP file's indexes, Images and OccupancyGrids decoded as views of their bytes).
"""

from . import topics
from .metadata import MetadataError
from .reader import DEFAULT_SYNC, BagFrame, BagMessage, BagReader
from .sources import BAG_SUFFIXES
from .writer import STORAGES, BagWriter, DriveSummary, check_output, write_drive

__all__ = ["BAG_SUFFIXES", "DEFAULT_SYNC", "STORAGES", "BagFrame", "BagMessage", "BagReader", "BagWriter",
           "DriveSummary", "MetadataError", "check_output", "topics", "write_drive"]
