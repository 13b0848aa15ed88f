"""Label spaces: a dataset's classes as sets of this package's fine labels (numpy; the torch loss
that trains across them is :mod:`bev_mapper_core.nn.label_space`).

Synthetic frames carry the package's fine :class:`~bev_mapper_core.labels.classes.Label` ids (lane
divider, crossing, curb ...). A real dataset carries coarser classes: CamVid's ``Road`` includes
the markings and crossings, its ``Pavement`` the curb. A :class:`LabelSpace` writes each of a
dataset's classes as the SET of fine labels it covers, and the loss of a coarse label is the
**marginal (partial-label) negative log-likelihood**

    loss = -log( sum_{j in cover(c)} softmax(z)_j )

so a pixel labelled ``Road`` asks for "road or lane divider or crossing" and never teaches "not
lane divider" on a marking (the gradient on every covered logit is <= 0; see
:func:`marginal_nll`). With singleton covers the loss is the ordinary cross-entropy, so synthetic
frames (the :data:`FINE` space) and real frames train through the same function, also in one
mixed batch (:func:`joint_cover`).

Mapping predictions back for evaluation (:meth:`LabelSpace.coarse_of_fine`): **fine argmax,
then map** each fine label to its *home* class, the covering class with the smallest cover
(first listed on ties). Summed probabilities per class are not used, because covers may overlap
(CamVid ``Bicyclist`` = pedestrian or vehicle also contains ``Pedestrian``'s and ``Car``'s
labels): the broader class would win every pixel where its parts do.

CamVid (SegNet tutorial version, 11 classes + Unlabelled) decisions, see :data:`CAMVID`:

* Sky -> UNLABELED (the synthetic frames label their sky UNLABELED; there is no sky label).
* Road -> ROAD, LANE_DIVIDER, PED_CROSSING (CamVid merges its marking classes into Road).
* Pavement -> SIDEWALK, ROAD_BOUNDARY (CamVid has no curb class; the kerb stone is labelled
  with the pavement it belongs to).
* Tree -> TERRAIN (the package's vegetation label: the Cityscapes preset maps vegetation and
  terrain to TERRAIN, and the synthetic verges are TERRAIN).
* Pole, SignSymbol, Fence -> OBSTACLE (as the Cityscapes preset). At evaluation OBSTACLE's home
  is Pole (the first of the three), so those three CamVid classes are not separable.
* Car -> VEHICLE; Pedestrian -> PEDESTRIAN; Building -> BUILDING.
* Bicyclist -> PEDESTRIAN or VEHICLE (Cityscapes maps rider to PEDESTRIAN and bicycle to
  VEHICLE; CamVid's class holds both).
* Unlabelled (11) -> ignored (:data:`IGNORE`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .classes import NUM_LABELS, Label

#: Target id that is ignored by the loss and the scores.
IGNORE = 255


@dataclass(frozen=True)
class LabelSpace:
    """A dataset's classes, each a set of fine :class:`Label` ids.

    Args:
        name: the dataset's name (messages, logs).
        classes: class names, in the dataset's id order (id ``i`` = ``classes[i]``).
        covers: per class, the fine label ids it covers (non-empty).

    Raises:
        ConfigError: lengths differ, an empty cover, or an id that is no Label.
    """

    name: str
    classes: tuple[str, ...]
    covers: tuple[frozenset[int], ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))
        object.__setattr__(self, "covers", tuple(frozenset(int(j) for j in c) for c in self.covers))
        if len(self.classes) != len(self.covers) or not self.classes:
            raise ConfigError(f"label space {self.name!r}: one cover per class needed "
                              f"({len(self.classes)} classes, {len(self.covers)} covers)")
        if len(self.classes) >= IGNORE:
            raise ConfigError(f"label space {self.name!r}: at most {IGNORE - 1} classes")
        for name, cover in zip(self.classes, self.covers):
            if not cover or any(not 0 <= j < NUM_LABELS for j in cover):
                raise ConfigError(f"label space {self.name!r}: class {name!r} must cover label ids in "
                                  f"0..{NUM_LABELS - 1}, got {sorted(cover)}")

    @property
    def num_classes(self) -> int:
        """Number of classes ``K``."""
        return len(self.classes)

    def cover_matrix(self) -> np.ndarray:
        """``(K, NUM_LABELS)`` bool: ``m[k, j]`` is True if class ``k`` covers fine label ``j``."""
        m = np.zeros((self.num_classes, NUM_LABELS), bool)
        for k, cover in enumerate(self.covers):
            m[k, sorted(cover)] = True
        return m

    def coarse_of_fine(self) -> np.ndarray:
        """``(NUM_LABELS,)`` uint8: each fine label's home class (the covering class with the
        smallest cover, the first listed on ties), :data:`IGNORE` where no class covers it.
        """
        home = np.full(NUM_LABELS, IGNORE, np.uint8)
        size = np.full(NUM_LABELS, NUM_LABELS + 1)
        for k, cover in enumerate(self.covers):
            for j in cover:
                if len(cover) < size[j]:
                    home[j], size[j] = k, len(cover)
        return home


#: The package's own labels (synthetic frames): every class covers itself (ordinary CE).
FINE = LabelSpace("fine", tuple(m.name.lower() for m in Label), tuple(frozenset({int(m)}) for m in Label))


_L = Label


#: CamVid, SegNet tutorial version (ids 0..10; 11 Unlabelled is ignored by the readers).
CAMVID = LabelSpace(
    "camvid",
    ("Sky", "Building", "Pole", "Road", "Pavement", "Tree", "SignSymbol", "Fence", "Car", "Pedestrian",
     "Bicyclist"),
    (
        {_L.UNLABELED}, {_L.BUILDING}, {_L.OBSTACLE}, {_L.ROAD, _L.LANE_DIVIDER, _L.PED_CROSSING},
        {_L.SIDEWALK, _L.ROAD_BOUNDARY}, {_L.TERRAIN}, {_L.OBSTACLE}, {_L.OBSTACLE}, {_L.VEHICLE},
        {_L.PEDESTRIAN}, {_L.PEDESTRIAN, _L.VEHICLE},
    ),
)


#: The five classes every space is compared on: name -> CamVid class.
COMMON_CAMVID: dict[str, str] = {"road": "Road", "sidewalk": "Pavement", "vehicle": "Car",
                                 "pedestrian": "Pedestrian", "building": "Building"}


#: Finer labels a fine label's class silently contains when a dataset never labels them itself.
IMPLIED_PARTS: dict[int, tuple[int, ...]] = {
    int(_L.ROAD): (int(_L.LANE_DIVIDER), int(_L.PED_CROSSING)),
    int(_L.SIDEWALK): (int(_L.ROAD_BOUNDARY),),
}


def space_from_labels(name: str, produced: Iterable[int]) -> LabelSpace:
    """The label space of a dataset labelled in fine :class:`Label` ids through a label map
    (the generic folder layout): class ``i`` is Label ``i``. A produced label covers its
    :data:`IMPLIED_PARTS` the dataset never produces (a Cityscapes ``road`` includes the
    markings, so it covers LANE_DIVIDER and PED_CROSSING; ``sidewalk`` covers the curb).
    """
    produced = {int(j) for j in produced}
    covers = []
    for m in Label:
        cover = {int(m)}
        if int(m) in produced:
            cover |= {p for p in IMPLIED_PARTS.get(int(m), ()) if p not in produced}
        covers.append(frozenset(cover))
    return LabelSpace(name, FINE.classes, tuple(covers))


__all__ = ["CAMVID", "COMMON_CAMVID", "FINE", "IGNORE", "IMPLIED_PARTS", "LabelSpace", "space_from_labels"]
