"""The per-camera 2-D segmenter, RGB -> this package's pixel labels: the network (:mod:`.model`),
its weights file (:mod:`.weights`), its use in front of label models (:mod:`.stage`) and its
training plug-in (:mod:`.train`, ``bev-train --method segmenter``).
"""
