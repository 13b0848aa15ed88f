"""Training and evaluation of the learned methods: the one training loop (:mod:`.trainer`), the
method plug-in interface and registry (:mod:`.method`; Bi-Mapper's plug-in in
:mod:`.bimapper_method`), the run configuration (:mod:`.config`), data sources (:mod:`.sources`;
synthetic drives in :mod:`.data`) and evaluation of any Mapper (:mod:`.evaluate`). The
``bev-train`` command is :mod:`bags.cli.train` (it adds the bag data source). Importing the
submodules that train imports torch.
"""
