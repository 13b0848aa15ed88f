"""Geometry (numpy, REP 103/105): the one BEV grid (:mod:`.grid`), camera models with ROS
distortion (:mod:`.camera`), rigs of cameras with ``ego_from_cam`` extrinsics and their presets
(:mod:`.rig`), rigid transforms (:mod:`.transforms`), projection tables from 3-D points to camera
pixels (:mod:`.projection`), BEV layers moved between ego poses (:mod:`.bev_warp`) and ego poses
looked up at an image stamp (:mod:`.pose_buffer`).
"""
