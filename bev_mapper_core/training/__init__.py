"""Training and evaluation of the learned methods (Bi-Mapper): synthetic-drive data
(:mod:`.data`), the training loop (:mod:`.trainer`), evaluation of any Mapper (:mod:`.evaluate`)
and the ``bev-train`` command (:mod:`.cli`). Importing the submodules that train imports torch."""
