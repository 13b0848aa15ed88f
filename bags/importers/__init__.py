"""Importers of public driving datasets into the package's bags (``bev-bag import``).

Each dataset has a subpackage (:mod:`bags.importers.nuscenes`, :mod:`bags.importers.av2`) that reads
the dataset's own files (JSON tables, map files) without its devkit, and writes one rosbag2 (MCAP)
per scene or log through :mod:`bags.importers.drive`: the camera JPEGs as
``sensor_msgs/CompressedImage`` (the bytes copied, not re-encoded), CameraInfo, ``/tf_static``,
``/tf`` and ``/odom``, and ground-truth layers ``/bev/gt/<class>`` on the package's grid
(:mod:`bags.importers.raster`). A class the dataset has no source for gets no topic, so it is left
unscored rather than scored as empty. Nothing of a dataset is shipped with the package.
"""
