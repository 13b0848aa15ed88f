"""Argoverse 2 sensor logs into bags: ``bev-bag import av2 LOGDIR --out DIR`` (:mod:`.log`).

Argoverse 2 is CC BY-NC-SA 4.0: the bags are derived data under the same terms, nothing of it is
shipped. Its tables are Apache Arrow Feather files, read with pyarrow (``pip install
'bev_mapper_ros[av2]'``); the vector map is JSON, read directly.
"""

from .log import LICENSE, RING_CAMERAS, import_av2_log

__all__ = ["LICENSE", "RING_CAMERAS", "import_av2_log"]
