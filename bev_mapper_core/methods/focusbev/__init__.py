"""FocusBEV (Zhao et al.), monocular BEV with a self-calibrated cycle view transformation and
ego-motion temporal fusion: the network (:mod:`.model`), its column-wise transformers, polar
resampling and memory fusion (:mod:`.blocks`), objective (:mod:`.losses`), weights file
(:mod:`.weights`), Mapper with its memory bank (:mod:`.mapper`) and training plug-in (:mod:`.train`).
"""
