"""IPM, the classical training-free baseline: :mod:`.mapper` (lookup tables per calibration, the
per-frame gather, :class:`~.mapper.LineOfSight`) and :mod:`.occlusion` (cells hidden behind an
object's near edge become unknown). Numpy and OpenCV only: no torch.
"""
