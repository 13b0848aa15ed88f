"""``segipm``, the two-stage RGB baseline: the 2-D segmenter per camera, then IPM (:mod:`.mapper`)."""
