"""bev_mapper_core: framework-free BEV mapping library (geometry, methods, metrics, synth).

Imports no ROS package; the ROS layers (``msg_adapters``, ``bev_mapper_ros``, ``bags``) build on it.
"""

from .errors import BevMapperError, CalibrationError, ConfigError, GridError, InputError
from .geometry.grid import BevGrid

__all__ = ["BevGrid", "BevMapperError", "CalibrationError", "ConfigError", "GridError", "InputError"]
__version__ = "0.1.0"
