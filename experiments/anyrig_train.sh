#!/usr/bin/env bash
# The rig-free Bi-Mapper (issue #38): LV stream + IPM skip + visibility head, 40 drives of 40 random rigs.
cd "$(dirname "$0")/.."
exec .venv/bin/bev-train --config experiments/anyrig_config.yaml --method bimapper --rig random --input labels \
  --streams lv --ipm-skip --visibility-head --visibility-weight 1 --batch 4 --lr 1e-3 --seed 0 \
  --epochs 10 --frames-per-epoch 320 --lr-step-epoch 8 --val-frames 40 --cache data/cache --threads 1 \
  --pos-weight none --no-asl --mutual none --time-budget 40 --no-progress --out runs/anyrig/run "$@"
