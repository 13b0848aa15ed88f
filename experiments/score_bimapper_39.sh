#!/bin/bash
# Issue #39: score segipm, chained Bi-Mapper (the shipped label weights behind the default segmenter)
# and a new RGB Bi-Mapper file on two disjoint surround6 test sets (A = 950000010-11,
# B = 950000012-13, 100 frames each drive, style mixed, the `surround` grid), once.
#   bash experiments/score_bimapper_39.sh NEW_WEIGHTS OUT_DIR [CACHE]
# writes OUT_DIR/{segipm,chained,new}_{A,B}.json (a row that exists is not scored again)
set -e
new=$1; out=$2; cache=${3:-data/cache}
mkdir -p "$out"
bt() { local json=$1; shift; [ -f "$json" ] && return 0
       ${BEV_TRAIN:-.venv/bin/bev-train} eval --rig surround6 --input rgb --style mixed --frames-per-drive 100 \
       --threads 1 --cache "$cache" --method bimapper --json "$json" "$@"; }
for set in A:950000010,950000011 B:950000012,950000013; do
  name=${set%%:*}; seeds=${set#*:}
  bt "$out/segipm_$name.json" --method segipm --val-seeds "$seeds" --name "segipm $name"
  bt "$out/chained_$name.json" --val-seeds "$seeds" --name "chained Bi-Mapper $name"
  bt "$out/new_$name.json" --weights "$new" --val-seeds "$seeds" --name "Bi-Mapper new $name"
done
