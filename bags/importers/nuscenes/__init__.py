"""nuScenes into bags: ``bev-bag import nuscenes DATAROOT --version V --scene NAME|--split SPLIT --out DIR``.

Reads the JSON tables (:mod:`.tables`), the map expansion (:mod:`.maps`) and the annotation
boxes (:mod:`.objects`) itself, so the devkit is not needed; :mod:`.scene` assembles a scene,
:mod:`.importer` writes its bag. nuScenes is CC BY-NC-SA 4.0: the bags are derived data under the
same terms, and nothing of the dataset is shipped with the package.
"""

from .importer import NuScenesImportOptions, SceneResult, import_nuscenes
from .objects import BoxFilter
from .scene import CAMERAS, LICENSE, SceneOptions

__all__ = ["CAMERAS", "LICENSE", "BoxFilter", "NuScenesImportOptions", "SceneOptions", "SceneResult", "import_nuscenes"]
