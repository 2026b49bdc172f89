#!/bin/bash
# Issue 13's recorded comparison: SG-D3QN + planning (d=1, w=10, learned predictor) at the demo
# budget, seeds given as arguments, one at a time; each tested on 1000 circle and 1000 square
# cases. Rerun to resume a killed run. The without-planning arm: results/demo/runs/egreedy-s*.
cd "$(dirname "$0")/../.."
export WANDB_MODE=offline
for S in "$@"; do
  D=results/planning/runs/plan-s$S
  if [ -f $D/checkpoints/last.pt ] && [ ! -f $D/summary.json ]; then
    .venv/bin/python experiments/train.py resume=$D logger.progress_bar=false >> results/planning/train-s$S.log 2>&1
  elif [ ! -f $D/summary.json ]; then
    .venv/bin/python experiments/train.py preset=demo learner=plain planning.enabled=true seed=$S hydra.run.dir=$D logger=csv \
      logger.progress_bar=false >> results/planning/train-s$S.log 2>&1
  fi
  for E in circle square; do
    [ -f $D/eval-$E/eval.json ] || .venv/bin/python experiments/evaluate.py checkpoint=$D env=$E \
      eval.record_episode=null hydra.run.dir=$D/eval-$E >> results/planning/eval-s$S-$E.log 2>&1
  done
done
