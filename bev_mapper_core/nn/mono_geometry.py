"""Camera checks of the monocular learned methods (S2G2, FocusBEV): one camera, and a new
calibration that keeps the model's input size.
"""

from __future__ import annotations

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.rig import Rig, scaled_camera


def check_one_camera(rig: Rig, title: str, hint: str = "") -> None:
    """Raise ConfigError unless ``rig`` has exactly one camera (monocular method ``title``);
    ``hint``: what runs on the rig instead (:func:`~bev_mapper_core.methods.alternatives`).
    """
    if len(rig.cameras) != 1:
        raise ConfigError(f"{title} is monocular: rig {rig.name!r} has {len(rig.cameras)} cameras "
                          f"{list(rig.names)}; use a one-camera rig (e.g. front1)" + (f"; {hint}" if hint else ""))


def one_camera_input_size(rig: Rig, input_width: int, title: str) -> tuple[int, int]:
    """Model input ``(h, w)`` of a one-camera rig's camera at ``input_width`` (same aspect)."""
    check_one_camera(rig, title)
    w, h = scaled_camera(rig.cameras[0], input_width).model.image_size
    return h, w


def check_same_camera(old: Rig, new: Rig, input_width: int, input_size: tuple[int, int], title: str) -> None:
    """A new calibration ``new`` of a one-camera model built for ``old`` must name the same
    camera and give the same model input size.

    Raises:
        ConfigError: another camera, more than one camera, or another model input size.
    """
    if new.names != old.names:
        raise ConfigError(f"rig cameras {list(new.names)} differ from the model's {list(old.names)}")
    got = one_camera_input_size(new, input_width, title)
    if got != tuple(input_size):
        raise ConfigError(f"new calibration gives input size {got}, the model needs {tuple(input_size)}")
