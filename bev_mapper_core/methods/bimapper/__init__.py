"""Bi-Mapper (Li et al., RA-L 2023): the network (:mod:`.model`: the global-cross view stream
:mod:`.gv`, the local-self view stream :mod:`.lv`, their calibration tables :mod:`.geometry`),
its architecture (:mod:`.config`), losses (:mod:`.losses`: BCE, Across-Space Loss, asynchronous
mutual learning), weights file (:mod:`.weights`), Mapper (:mod:`.mapper`), training plug-in
(:mod:`.train`) and per-class temperature calibration (:mod:`.calibrate`).
"""
