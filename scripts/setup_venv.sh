#!/usr/bin/env bash
# Create (or refresh) the project's virtual environment in .venv and install everything it needs:
# the CPU build of torch, the package itself (editable) with the ROS 2 Jazzy wheels and test tools.
# Idempotent: a second run with nothing changed only re-checks the installed set.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.bev_mapper_installed
want=$(cat setup.py scripts/setup_venv.sh | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
# The CPU wheel first, pinned: a looser requirement would pull several GB of CUDA packages.
.venv/bin/python -m pip install -q "torch==2.13.0" 2>&1 | grep -v "is ignored: it is neither" || true
.venv/bin/python -m pip install -q -e ".[ros,test]" 2>&1 | grep -v "is ignored: it is neither a file nor a directory" || true
.venv/bin/python -c "import torch, cv2, rosbags, rclpy" 
echo "$want" > "$stamp"
