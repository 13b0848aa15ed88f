"""Semantic labels: the pixel label ids and BEV classes (:mod:`.classes`), and label images of
other segmenters converted to them (:mod:`.label_maps`).
"""
