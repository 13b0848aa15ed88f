#!/usr/bin/env bash
# Issue #38: the default RGB map (segmenter, then Bi-Mapper's weights for any rig) against segipm
# on rigs no training drive used, on the test drives 950000010-12 (100 frames each; never used for
# training or any choice). Usage: bash experiments/anyrig_eval.sh METHOD RIG [INPUT]
set -euo pipefail
cd "$(dirname "$0")/.."
method=$1 rig=$2 input=${3:-rgb}
mkdir -p out/anyrig
exec .venv/bin/bev-train eval --rig "$rig" --input "$input" --method "$method" \
  --val-seeds 950000010,950000011,950000012 --frames-per-drive 100 --threads 1 \
  --json "out/anyrig/${rig}_${input}_${method}.json" --name "$method $rig $input"
