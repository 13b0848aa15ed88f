#!/bin/bash
# Issue #39: score segipm, a new file of a monocular method (s2g2, the default, or focusbev) and that
# method's shipped file on the two disjoint front1 test sets (A = 950000010-11, B = 950000012-13,
# 100 frames each drive, style mixed, the `ahead` grid), once.
#   bash experiments/score_s2g2_39.sh NEW_WEIGHTS OUT_DIR [CACHE] [METHOD]
# writes OUT_DIR/{segipm,new,shipped}_{A,B}.json
set -e
new=$1; out=$2; cache=${3:-data/cache}; method=${4:-s2g2}
case $method in s2g2) title=S2G2 ;; focusbev) title=FocusBEV ;; *) echo "error: METHOD must be s2g2 or focusbev" >&2; exit 2 ;; esac
mkdir -p "$out"
bt() { ${BEV_TRAIN:-.venv/bin/bev-train} eval --rig front1 --grid ahead --input rgb --style mixed --frames-per-drive 100 \
       --threads 1 --cache "$cache" "$@"; }
for set in A:950000010,950000011 B:950000012,950000013; do
  name=${set%%:*}; seeds=${set#*:}
  bt --method segipm --val-seeds "$seeds" --json "$out/segipm_$name.json" --name "segipm $name"
  bt --method "$method" --weights "$new" --val-seeds "$seeds" --json "$out/new_$name.json" --name "$title new $name"
  bt --method "$method" --val-seeds "$seeds" --json "$out/shipped_$name.json" --name "$title shipped $name"
done
