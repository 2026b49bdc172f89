#!/bin/bash
# Issue 26's arms of the intrinsic-reward study at the demo budget (planning on, the plain learner, as results/demo-planning),
# run one after another: `bash results/intrinsic/chain.sh ARM:SEED [ARM:SEED ...]`. A killed run resumes
# from its last checkpoint when rerun; finished runs are skipped. Arms are compared on validation
# (experiments/compare_runs.py --split val); the 1000 circle test cases each run ends with are for the table.
cd "$(dirname "$0")/../.."
export WANDB_MODE=offline
STABLE="exploration.reward_norm=batch exploration.reward_center=true exploration.reward_clip=5 exploration.obs_norm=true"
DECAY="exploration.beta_schedule=exp exploration.beta_decay=1e-5"
EPS="exploration.eps_start=0.5 exploration.eps_end=0.1"  # ε-greedy's schedule (the demo preset: over 100k frames)
arm() {
  case $1 in
    icm-stable) echo "exploration=icm $STABLE exploration.icm_feature_norm=layernorm $DECAY" ;;
    re3-stable) echo "exploration=re3 $STABLE $DECAY" ;;
    icm-stable-eps) echo "exploration=icm $STABLE exploration.icm_feature_norm=layernorm $DECAY $EPS" ;;
    re3-stable-eps) echo "exploration=re3 $STABLE $DECAY $EPS" ;;
    # one lever at a time on the published RE3 (exploration=re3_published)
    re3-center) echo "exploration=re3_published exploration.reward_norm=batch exploration.reward_center=true" ;;
    re3-decay)  echo "exploration=re3_published $DECAY" ;;
    re3-terminal) echo "exploration=re3_published exploration.terminal_value=true" ;;
    greedy)     echo "exploration=re3 exploration.beta=0" ;;  # the control: ε = 0, planning, no bonus
    *) echo "unknown arm $1" >&2; exit 2 ;;
  esac
}
for item in "$@"; do
  A=${item%%:*}; S=${item##*:}
  D=results/intrinsic/runs/$A-s$S
  LOG=results/intrinsic/logs/$A-s$S.log
  mkdir -p results/intrinsic/logs
  OVR=$(arm "$A") || exit 2
  if [ -f $D/summary.json ]; then continue; fi
  if [ -f $D/checkpoints/last.pt ]; then
    .venv/bin/python experiments/train.py resume=$D logger.progress_bar=false >> $LOG 2>&1
  else
    .venv/bin/python experiments/train.py preset=demo learner=plain seed=$S $OVR logger=csv logger.progress_bar=false \
      logger.render=false hydra.run.dir=$D >> $LOG 2>&1
  fi
done
