#!/usr/bin/env bash
# The main job on the bundled default: generate the demo drive if it is not there, replay it
# through the default method, print the metrics table, write the output bag, metrics.json and
# pictures of prediction vs ground truth under out/demo/.
#   bash scripts/demo.sh [extra bev-bag replay flags, e.g. --method ipm]
# Outputs of another method or input than the default go to their own folder (out/demo_ipm,
# out/demo_rgb, out/demo_segipm_rgb, ...), so they never overwrite the default's.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
method=""
input=""
prev=""
for a in "$@"; do
  case "$a" in --method=*) method=${a#--method=} ;; --input=*) input=${a#--input=} ;; esac
  [ "$prev" = "--method" ] && method=$a
  [ "$prev" = "--input" ] && input=$a
  prev=$a
done
default=$(.venv/bin/python -c "from bev_mapper_core.mapper import MapperConfig; print(MapperConfig.method)")
[ "$method" = "$default" ] && method=""
[ "$input" = "labels" ] && input=""
BAG=${BEV_DEMO_BAG:-data/demo_drive}
OUT=${BEV_DEMO_OUT:-out/demo${method:+_$method}${input:+_$input}}
if [ ! -f "$BAG/metadata.yaml" ]; then
  # Seeds from 950,000,000 up are the test split: never used for training or validation.
  echo "generating the demo drive $BAG (surround6, 50 frames, test seed 950000008; 10-30 s)" >&2
  .venv/bin/bev-bag synth "$BAG" --rig surround6 --frames 50 --seed 950000008 --storage mcap
fi
exec .venv/bin/bev-bag replay "$BAG" --out "$OUT" --force "$@"
