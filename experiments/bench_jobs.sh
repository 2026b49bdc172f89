#!/usr/bin/env bash
# How many train.py runs at a time suit this machine (reproduce.py jobs=K): six 20k-frame demo
# runs (seeds 0-5, one thread each) at K = 1, 2, 3; prints the wall-clock of each K.
#   bash experiments/bench_jobs.sh
cd "$(dirname "$0")/.."
run() { WANDB_MODE=offline .venv/bin/python experiments/train.py preset=demo planning.enabled=false train.total_frames=20000 train.val_every_frames=10000 train.test_episodes=200 logger=csv logger.render=false logger.progress_bar=false seed=$1 hydra.run.dir="${TMPDIR:-/tmp}"/crowdrl-jobs/$2/s$1 >/dev/null 2>&1; }
for K in 1 2 3; do
  rm -rf "${TMPDIR:-/tmp}"/crowdrl-jobs/k$K; start=$(date +%s.%N)

  for s in 0 1 2 3 4 5; do
    run $s k$K &
    while [ $(jobs -rp | wc -l) -ge $K ]; do sleep 0.5; done
  done
  wait
  end=$(date +%s.%N)
  echo "K=$K wall $(echo "$end - $start" | bc) s for 6 runs" 
done
