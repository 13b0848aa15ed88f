"""Benchmark: the mapper node's overhead per synchronized surround6 set, method excluded.

Runs the real :class:`~bev_mapper_ros.mapper_node.MapperNode` in this process with a trivial
registered method (``null``: an all-zero, all-known prediction, so the mapping itself costs
~nothing) and times, per set of six full-size label images (400x225 mono8):

* ``deserialize``: CDR -> rclpy Image for the six images (what rclpy does before a callback);
* ``callbacks+sync``: the node's image callbacks feeding the synchronizer until the set is out;
* ``process``: the node's worker path (decode six images, map with ``null``, build and publish
  the class OccupancyGrids and the rgb8 picture), with a breakdown of its parts.

Nothing is spun and no subscriber is matched, so publishing costs the rclpy conversion and the
rmw write. DDS stays on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` by default);
pick a private ``ROS_DOMAIN_ID``.

    ROS_DOMAIN_ID=142 .venv/bin/python bench/bench_node_overhead.py [--sets 50]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from bev_mapper_core.geometry.grid import BevGrid  # noqa: E402
from bev_mapper_core.geometry.rig import preset_rig  # noqa: E402
from bev_mapper_core.geometry.transforms import rot_to_quat  # noqa: E402
from bev_mapper_core.labels.classes import bev_picture  # noqa: E402
from bev_mapper_core.mapper import BevPrediction, Mapper, register_method  # noqa: E402
from bev_mapper_core.synth import SynthConfig, generate_drive  # noqa: E402
from msg_adapters import RclpyFactory, image_to_labels, make_camera_info, make_image, make_occupancy_grid  # noqa: E402


class NullMapper(Mapper):
    """A method that costs nothing: every cell known, every class absent."""

    name = "null"

    def map(self, images, ego_pose=None, stamp_ns=None) -> BevPrediction:
        """All-zero probabilities, all cells known."""
        self.check_images(images)
        return BevPrediction(self.class_names, self._probs, self._known)

    def set_rig(self, rig) -> None:
        """No tables; allocate the constant prediction once."""
        super().set_rig(rig)
        self._probs = np.zeros((len(self.classes), *self.grid.shape), np.float32)
        self._known = np.ones(self.grid.shape, bool)


def _subscribe_all(listener, node, pubs) -> None:
    """Subscribe ``listener`` to the outputs and wait until every publisher is matched."""
    from nav_msgs.msg import OccupancyGrid  # noqa: PLC0415

    for p in pubs:
        listener.create_subscription(OccupancyGrid, p.topic_name, lambda m: None, 2)
    listener.create_subscription(Image, node._image_pub.topic_name, lambda m: None, 2)
    end = time.monotonic() + 20.0
    while time.monotonic() < end and not all(
            p.get_subscription_count() for p in [*pubs, node._image_pub]):
        time.sleep(0.05)


def _ms(samples: list[float]) -> str:
    return f"{statistics.median(samples):7.2f} ms (p95 {np.percentile(samples, 95):6.2f})"


def _params(rig) -> list[Parameter]:
    out = [Parameter("rig", value="surround6"), Parameter("cameras", value=list(rig.names)),
           Parameter("method", value="null"), Parameter("use_tf", value=False),
           Parameter("diagnostics_period_s", value=10.0)]
    for cam in rig.cameras:
        T = cam.ego_from_cam_array
        q = rot_to_quat(T[:3, :3])
        out.append(Parameter(f"extrinsics.{cam.name}", value=[*map(float, T[:3, 3]), *map(float, q)]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=50)
    ap.add_argument("--subscribe", action="store_true",
                    help="match a subscriber (another node in this process, not spun) to every "
                         "output topic, so that publishing really delivers")
    args = ap.parse_args()
    register_method("null", NullMapper)
    rig, grid = preset_rig("surround6"), BevGrid()
    frames = list(generate_drive(rig, grid, SynthConfig(frames=3, seed=1)))
    fac = RclpyFactory()
    rclpy.init()
    from bev_mapper_ros.mapper_node import MapperNode  # noqa: PLC0415

    rclpy.logging.set_logger_level("mapper_node", rclpy.logging.LoggingSeverity.WARN)
    node = MapperNode(parameter_overrides=_params(rig))
    node.worker.stop()  # run the worker path synchronously here
    listener = rclpy.create_node("bench_listener") if args.subscribe else None
    sets = []
    node.sync.callback = sets.append
    for cam in rig.cameras:  # calibration via the node's own CameraInfo callbacks
        node._info_cb(cam.name)(make_camera_info(fac, cam.model, 0, cam.frame_id))
    period = 100_000_000
    t_deser, t_cb, t_proc, t_dec, t_grid, t_pic, t_pub = ([] for _ in range(7))
    pubs = None
    for i in range(args.sets + 3):
        f = frames[i % len(frames)]
        stamp = 1_700_000_000_000_000_000 + i * period
        wire = {c: serialize_message(make_image(fac, f.cameras[c].labels, "mono8", stamp,
                                                rig[c].frame_id)) for c in rig.names}
        t0 = time.perf_counter()
        msgs = {c: deserialize_message(b, Image) for c, b in wire.items()}
        t1 = time.perf_counter()
        for c, m in msgs.items():
            node._image_cb(c)(m)
        t2 = time.perf_counter()
        assert len(sets) == 1, "the synchronizer did not emit exactly one set"
        synced = sets.pop()
        node._process(synced)
        t3 = time.perf_counter()
        # breakdown of the worker path, redone step by step
        s0 = time.perf_counter()
        imgs = {c: image_to_labels(synced.messages[c]) for c in synced.valid_names}
        s1 = time.perf_counter()
        pred = node.mapper.map(imgs)
        grids = [make_occupancy_grid(fac, grid, pred.probs[k], pred.known, stamp, "base_link")
                 for k in range(len(node.classes))]
        s2 = time.perf_counter()
        pic = make_image(fac, bev_picture(grid, pred.probs, node.classes, pred.known), "rgb8",
                         stamp, "base_link")
        s3 = time.perf_counter()
        if pubs is None:
            pubs = [node._grid_pubs[c.name] for c in node.classes]
            if listener is not None:
                _subscribe_all(listener, node, pubs)
        for p, g in zip(pubs, grids):
            p.publish(g)
        node._image_pub.publish(pic)
        s4 = time.perf_counter()
        if i >= 3:  # warm-up
            t_deser.append((t1 - t0) * 1e3)
            t_cb.append((t2 - t1) * 1e3)
            t_proc.append((t3 - t2) * 1e3)
            t_dec.append((s1 - s0) * 1e3)
            t_grid.append((s2 - s1) * 1e3)
            t_pic.append((s3 - s2) * 1e3)
            t_pub.append((s4 - s3) * 1e3)
    w, h = rig.cameras[0].model.image_size
    print(f"subscribers matched: {'yes (not spun)' if listener else 'no'}")
    print(f"surround6: 6 x {w}x{h} mono8 labels per set -> {len(node.classes)} OccupancyGrids "
          f"{grid.width}x{grid.height} + rgb8 picture; {args.sets} sets, median (p95)")
    print(f"deserialize (rclpy, 6 images) : {_ms(t_deser)}")
    print(f"callbacks + synchronizer      : {_ms(t_cb)}")
    print(f"worker path with 'null' method: {_ms(t_proc)}")
    print(f"  decode 6 label images       : {_ms(t_dec)}")
    print(f"  {f'build {len(node.classes)} OccupancyGrids':<28}: {_ms(t_grid)}")
    print(f"  build the rgb8 picture      : {_ms(t_pic)}")
    print(f"  publish grids + picture     : {_ms(t_pub)}")
    total = [a + b + c for a, b, c in zip(t_deser, t_cb, t_proc)]
    print(f"node overhead per set (total) : {_ms(total)}")
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
