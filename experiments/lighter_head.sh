#!/usr/bin/env bash
# issue #15: the lighter decoder head ablation (docs/RESULTS.md) at equal budget (sk_lvgv recipe), CPU, 1 thread each
set -x
cd "$(dirname "$0")/.."
R="--rig surround6 --input labels --epochs 10 --frames-per-epoch 240 --batch 4 --lr 1e-3 --lr-step-epoch 8 --seed 0 --val-frames 40 --cache data/cache --threads 1 --ipm-skip --pos-weight none --no-asl --mutual none"
.venv/bin/python -m bev_mapper_core.training.data --rig surround6 --classes standard --cache data/cache --train-drives 40 --val-drives 6 --frames 20 --stride 3
(.venv/bin/python -m bags.cli.train $R --out runs/lh_base $RESUME > runs/lh_base.log 2>&1) &
(.venv/bin/python -m bags.cli.train $R --decoder-min-channels 8 --out runs/lh_min8 $RESUME > runs/lh_min8.log 2>&1) &
wait
T="950000010,950000011,950000012,950000013,950000014,950000015,950000016,950000017,950000018,950000019"
for r in lh_base lh_min8; do
  .venv/bin/python -m bags.cli.train eval --rig surround6 --method bimapper --weights runs/$r/last.safetensors --val-seeds $T --cache data/cache --threads 1 --json runs/eval_$r.json --name $r > runs/eval_$r.log 2>&1
done
echo done
