#!/bin/bash
# the 5-20-human runs of the crowd-size generalisation table, one at a time (rerun to resume)
cd "$(dirname "$0")/../.."
for s in 1 2; do
  d=results/crowd_range/runs/range-s$s
  if [ -f $d/status.json ] && grep -q '"completed"' $d/status.json; then continue; fi
  if [ -f $d/config.yaml ]; then extra="resume=$d"; else extra=""; fi
  .venv/bin/python experiments/train.py preset=demo learner=plain planning.enabled=false env.min_humans=5 env.max_humans=20 seed=$s logger=csv \
    logger.progress_bar=false hydra.run.dir=$d $extra >> results/crowd_range/range-s$s.log 2>&1
done
