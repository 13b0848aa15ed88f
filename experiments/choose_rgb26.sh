#!/usr/bin/env bash
# Model choice for issue #26 on the VALIDATION drives only (the trainer's held-out seeds
# 900000000.., never the test seeds): whether end-to-end RGB Bi-Mapper replaces the chained one
# as surround6's RGB default. Writes runs/eval26/val_<row>.json.
#   bash experiments/choose_rgb26.sh [WEIGHTS_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
W=${1:-runs/gpu26}
OUT=runs/eval26; mkdir -p $OUT
ev() {  # row args...
  local row=$1; shift
  [ -f $OUT/val_${row}.json ] && return 0
  .venv/bin/bev-train eval --threads 1 --cache data/cache --json $OUT/val_${row}.json --name "$row (validation)" "$@" 2>&1 | tail -1
}
C="--rig surround6 --input rgb --style mixed"
ev s6_chained $C --method bimapper
ev s6_bimapper_rgb $C --method bimapper --weights $W/gpu_bimapper_rgb.safetensors
ev s6_segipm $C --method segipm
