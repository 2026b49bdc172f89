#!/bin/bash
# The validation table the defaults were chosen by (results/intrinsic/val/table.md): each arm's runs
# compared on the validations their training logged (last 5), never on test cases.
cd "$(dirname "$0")/../.."
R=results/intrinsic/runs P=results/demo-planning/runs
runs() { local out=""; for s in 0 1 2; do [ -f $1-s$s/summary.json ] && out="$out,$1-s$s"; done; echo "${out#,}"; }
.venv/bin/python experiments/compare_runs.py --split val --last 5 --out results/intrinsic/val \
  --group "ε-greedy=$(runs $P/egreedy)" \
  --group "greedy control (ε 0, no bonus)=$(runs $R/greedy)" \
  --group "ICM published=$(runs $P/icm)" \
  --group "RE3 published=$(runs $P/re3)" \
  --group "RE3 + centring only=$(runs $R/re3-center)" \
  --group "RE3 + exp decay only [exploration re3]=$(runs $R/re3-decay)" \
  --group "ICM stable [exploration icm]=$(runs $R/icm-stable)" \
  --group "ICM stable + ε-greedy's ε=$(runs $R/icm-stable-eps)" \
  --group "RE3 stable=$(runs $R/re3-stable)" "$@"
