"""Training and evaluation of the learned methods, the same for every method: the one training
loop (:mod:`.trainer`), the plug-in interface a method's ``train.py`` implements and its registry
(:mod:`.method`, read from :data:`bev_mapper_core.methods.METHODS`), the run configuration
(:mod:`.config`), data sources (:mod:`.sources`; synthetic drives in :mod:`.data`), class balance
(:mod:`.class_weights`), data-parallel runs (:mod:`.distributed`) and evaluation of any Mapper
(:mod:`.evaluate`). The ``bev-train`` command is :mod:`bags.cli.train` (it adds the bag data
source). Importing the submodules that train imports torch.
"""
