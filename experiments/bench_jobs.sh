#!/usr/bin/env bash
# How many train.py runs at a time suit this machine (reproduce.py jobs=K): six 20k-frame demo
# runs (seeds 0-5, one thread each) at K = 1, 2, 3; the wall-clock of each K, as the Markdown table
# of the other benchmarks or, with --json, as {"meta": ..., "rows": [...]} (benchkit.py's format).
#   bash experiments/bench_jobs.sh [--json]
cd "$(dirname "$0")/.."
json=false; [ "$1" = "--json" ] && json=true
run() { WANDB_MODE=offline .venv/bin/python experiments/train.py preset=demo learner=plain planning.enabled=false train.total_frames=20000 train.val_every_frames=10000 train.test_episodes=200 logger=csv logger.render=false logger.progress_bar=false seed=$1 hydra.run.dir="${TMPDIR:-/tmp}"/crowdrl-jobs/$2/s$1 >/dev/null 2>&1; }
rows=()
for K in 1 2 3; do
  rm -rf "${TMPDIR:-/tmp}"/crowdrl-jobs/k$K; start=$(date +%s.%N)
  for s in 0 1 2 3 4 5; do
    run $s k$K &
    while [ $(jobs -rp | wc -l) -ge $K ]; do sleep 0.5; done
  done
  wait
  end=$(date +%s.%N)
  wall=$(printf "%.2f" "$(echo "$end - $start" | bc)")
  echo "K=$K: $wall s for 6 runs" >&2
  rows+=("$K $wall")
done
if $json; then
  printf '{"meta": {"runs": 6, "frames_per_run": 20000, "threads_per_run": 1}, "rows": ['
  sep=""; for r in "${rows[@]}"; do set -- $r; printf '%s{"K": %s, "wall_s": %s}' "$sep" "$1" "$2"; sep=", "; done
  printf ']}\n'
else
  echo "Six 20k-frame demo runs (seeds 0-5, one thread each), K at a time"; echo
  echo "| K | wall s |"; echo "|--:|-------:|"
  for r in "${rows[@]}"; do set -- $r; printf '| %s | %6.1f |\n' "$1" "$2"; done
fi
