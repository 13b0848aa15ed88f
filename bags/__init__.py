"""The bag tool: rosbag2 bags in and out of bev_mapper, offline (no ROS graph needed).

Subpackages, by role (each ``__init__`` names its public names):

* :mod:`bags.io`: reading and writing bags (:class:`~bags.io.reader.BagReader`,
  :class:`~bags.io.writer.BagWriter`, topic names, integrity and input checks, the training
  data source);
* :mod:`bags.replay`: mapping a bag's frames offline and scoring them (:func:`~bags.replay.replay`);
* :mod:`bags.report`: pictures, ``report.html`` and the reliability diagram of a replay;
* :mod:`bags.fleet`: many bags or drives as Ray tasks (``bev-bag evaluate`` / ``synth-many``);
* :mod:`bags.cli`: the ``bev-bag`` and ``bev-train`` command lines.

Beside them, :mod:`bags.errors` (the exception types), :mod:`bags.files` (atomic writes),
:mod:`bags.memory` (the allocator's settings) and :mod:`bags.mcap_checksums` (the MCAP checks,
importing nothing else of the package so that ``bev-bag`` starts them before loading the rest).
Importing ``bags`` imports none of them.
"""
