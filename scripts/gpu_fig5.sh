#!/usr/bin/env bash
# Fig. 5 on the shipped dynamics model (issue 37, docs/resolution), one GPU machine, about 30 minutes on an H200:
#   OUT=/root/fig5 bash scripts/gpu_fig5.sh
# Gather and Redistribute, EPISODES paired episodes from seed SEED under the 2-core CPU's 0.25 s budget
# (docs/budget/timing_cpu.json): every fixed ω of FIXED and adaptive ω (the shipped regressor g; and G_NEW, a
# regressor trained on the new model's labels, when given), then the probe (no labels); both tasks again without a
# budget (NOBUDGET methods, 100 Adam steps each). $OUT/results.tar.gz after every stage; a stage whose summary exists
# is skipped. Env: OUT, EPISODES (256), SEED (7400), FIXED ("10 25 50 75 100"), NOBUDGET ("25 50 100 adaptive"),
# G_NEW (a regressor folder), STAGES ("budget gnew probe nobudget"), FLAGS (more evaluate flags, e.g. "--mpc-steps 1"
# with EPISODES=2 for a CPU dry run).
set -uo pipefail
OUT=${OUT:-/root/fig5}; EPISODES=${EPISODES:-256}; SEED=${SEED:-7400}; FIXED=${FIXED:-"10 25 50 75 100"}
NOBUDGET=${NOBUDGET:-"25 50 100 adaptive"}; G_NEW=${G_NEW:-}; STAGES=${STAGES:-"budget gnew probe nobudget"}
BUDGET="--time-budget 0.25 --timing docs/budget/timing_cpu.json"
mkdir -p "$OUT"
stage() { [[ " $STAGES " == *" $1 "* ]]; }
pack() { tar -czf "$OUT/results.tmp" -C "$OUT" --exclude results.tar.gz --exclude results.tmp . 2>/dev/null
         mv "$OUT/results.tmp" "$OUT/results.tar.gz"; }
evaluate() {  # NAME TASK METHODS [FLAGS...]
  local name=$1 task=$2 methods=$3; shift 3
  [ -f "$OUT/$name/summary.json" ] && return
  # shellcheck disable=SC2086
  python -m experiments.evaluate --task "$task" --episodes "$EPISODES" --samples 50 --seed "$SEED" --methods $methods \
    --out "$OUT/$name" ${FLAGS:-} "$@" > "$OUT/$name.log" 2>&1
  echo "$(date +%T) $name: $(grep -c 'final d' "$OUT/$name.log") methods"; pack
}
for task in gather redistribute; do
  # shellcheck disable=SC2086
  stage budget && evaluate "${task}_budget" "$task" "$FIXED adaptive" $BUDGET
  # shellcheck disable=SC2086
  stage gnew && [ -n "$G_NEW" ] && evaluate "${task}_budget_gnew" "$task" adaptive --regressor "$G_NEW" $BUDGET
  # shellcheck disable=SC2086
  stage probe && evaluate "${task}_budget_probe" "$task" probe $BUDGET
done
for task in gather redistribute; do
  stage nobudget && evaluate "${task}_nobudget" "$task" "$NOBUDGET" --adam-steps 100
done
echo "$(date +%T) done"; touch "$OUT/done"
