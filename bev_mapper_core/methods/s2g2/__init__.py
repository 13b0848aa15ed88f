"""S2G2 (Gao, Wang & Sun, RA-L 2022), semi-supervised monocular BEV: the network (:mod:`.model`),
its dual-attention view transformation blocks (:mod:`.blocks`), objective and EMA
(:mod:`.losses`), weights file (:mod:`.weights`), Mapper (:mod:`.mapper`) and training plug-in
(:mod:`.train`).
"""
