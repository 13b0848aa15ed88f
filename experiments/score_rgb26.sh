#!/usr/bin/env bash
# Score issue #26's GPU-trained RGB weights on CPU on the test drives (never used for training or
# model choice), beside the baselines in the same run. Writes runs/eval26/<row>_<style>.json.
#   bash experiments/score_rgb26.sh [WEIGHTS_DIR]      (default runs/gpu26: gpu_<run>.safetensors)
set -euo pipefail
cd "$(dirname "$0")/.."
W=${1:-runs/gpu26}
OUT=runs/eval26; mkdir -p $OUT
F1=950000010,950000011,950000012,950000013,950000014,950000015,950000016,950000017,950000018,950000019
S6=950000010,950000011,950000012
ev() {  # row style args...
  local row=$1 style=$2; shift 2
  [ -f $OUT/${row}_${style}.json ] && return 0
  .venv/bin/bev-train eval --style $style --threads 1 --cache data/cache --json $OUT/${row}_${style}.json --name "$row ($style)" "$@" \
    2>&1 | tail -3
}
for st in mixed dusk; do
  C="--rig front1 --grid ahead --val-seeds $F1 --input rgb"
  ev f1_segipm $st $C --method segipm
  ev f1_s2g2_shipped $st $C --method s2g2
  ev f1_focusbev_shipped $st $C --method focusbev
  for r in s2g2 s2g2_clip s2g2_semi s2g2_semi_clip s2g2_semi_synth_clip s2g2_384_clip; do
    ev f1_$r $st $C --method s2g2 --weights $W/gpu_$r.safetensors
  done
  for r in focusbev focusbev_mlp focusbev_w1; do
    ev f1_$r $st $C --method focusbev --weights $W/gpu_$r.safetensors
  done
  C="--rig surround6 --val-seeds $S6 --input rgb"
  ev s6_segipm $st $C --method segipm
  ev s6_chained $st $C --method bimapper
  ev s6_bimapper_rgb $st $C --method bimapper --weights $W/gpu_bimapper_rgb.safetensors
done
