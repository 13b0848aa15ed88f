"""Exception types of the core library.

Every error the core raises on bad input derives from :class:`BevMapperError`, so callers
(the ROS node, the bag tool) can catch one type, log it and keep going.
"""


class BevMapperError(Exception):
    """Base class of all errors raised by ``bev_mapper_core``."""


class GridError(BevMapperError, ValueError):
    """A BEV grid definition is invalid (non-positive resolution, empty extent, ...)."""


class CalibrationError(BevMapperError, ValueError):
    """A camera model or rig calibration is invalid (zero focal length, non-finite values, ...)."""


class InputError(BevMapperError, ValueError):
    """Input data (images, label maps, layers) does not match what the method expects."""


class ConfigError(BevMapperError, ValueError):
    """A configuration value is out of range or names something unknown."""
