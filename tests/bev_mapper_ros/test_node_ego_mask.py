"""The node's ``ego_mask.<camera>`` parameters: read from parameters, attached to the live rig;
an unusable mask leaves its camera out (counted and said), the other cameras keep their images."""

import cv2
import numpy as np
import rclpy
from rclpy.parameter import Parameter

from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_ros.config import node_config_from_params, unknown_parameter_messages
from bev_mapper_ros.mapper_node import MapperNode


def test_ego_mask_parameters_map_onto_the_config():
    cfg = node_config_from_params({"rig": "surround6", "ego_mask.front": "/m/front.png", "ego_mask.back": ""})
    assert cfg.ego_masks == (("front", "/m/front.png"),)
    warned = unknown_parameter_messages({"ego_mask.roof", "ego_mask.front"}, ("front", "back"))
    assert len(warned) == 1 and "'roof' is not one of the cameras" in warned[0]


def test_node_leaves_out_cameras_whose_mask_is_unusable(tmp_path):
    rig = preset_rig("surround6")
    w, h = rig["back"].model.image_size
    good = np.zeros((h, w), np.uint8)
    good[-10:] = 255
    cv2.imwrite(str(tmp_path / "back.png"), good)
    cv2.imwrite(str(tmp_path / "small.png"), good[:10, :10])
    rclpy.init()
    try:
        node = MapperNode(parameter_overrides=[
            Parameter("rig", value="surround6"), Parameter("method", value="ipm"), Parameter("use_tf", value=False),
            Parameter("ego_mask.front", value=str(tmp_path / "missing.png")),
            Parameter("ego_mask.back", value=str(tmp_path / "back.png")),
            Parameter("ego_mask.front_left", value=str(tmp_path / "small.png")),
        ])
        try:
            masked = node._masked(rig)
            assert masked["back"].ego_mask is not None and masked["front"].ego_mask is None
            assert set(node.mask_problems) == {"front", "front_left"}
            assert "no such file" in node.mask_problems["front"] and "10x10" in node.mask_problems["front_left"]
            assert node._decode("front", object()) is None  # left out before decoding
            assert node.stats.bad_input == 1
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown()
