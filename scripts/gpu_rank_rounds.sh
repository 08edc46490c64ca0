#!/usr/bin/env bash
# Issue 48 item 4 on one GPU machine: one round of on-policy candidates. The model POLICY plans the closed loop; the
# states it visits, each with the planner's candidate pushes pushed in C MuJoCo, become ranking sets
# (studies.ranking build --twin-sigma 0); POLICY is fine-tuned on them once per variant (studies.rank_finetune: the
# position loss alone, and with the listwise loss); every model is scored on the committed held-out ranking sets
# (docs/dynamics_scale/sets) and in closed loop on tuning seeds (scripts/gpu_ladder.sh: Gather M&M and Redistribute
# JTULY, COUNT episodes each from seed 6000), the fine-tuned ones paired with POLICY.
#   setsid nohup bash scripts/gpu_rank_rounds.sh > /tmp/rr.log 2>&1 &
# The next round: POLICY=a fine-tuned checkpoint of this one, ROUND=2 (new seeds for the sets).
# Results: $WORK/results/ (logs, sets' sizes, ranking tables, lanes, closed_loop.md, each model's ckpt); $WORK/done.
# Env: WORK (/tmp/rr), POLICY (the shipped checkpoint), ROUND (1), EPISODES (64 a set), CAPTURE ("0 3 6 9"),
# COUNT (64), STEPS (1000), BATCH (16 states a step), LR (1e-4), VARIANTS ("pos --rank-weight 0;list --rank-weight 1":
# NAME and rank_finetune's flags), LETTERS_TRAIN (ACEHMNSX: letters never used for tuning or testing), LETTERS (the
# closed loop's, JTULY), BUILD_FLAGS, FLAGS (more evaluate flags).
# A CPU dry run: EPISODES=2 CAPTURE=0 COUNT=1 STEPS=2 BUILD_FLAGS="--samples 4 --adam-steps 2 --pieces 30"
# FLAGS="--quick --samples 4 --adam-steps 2 --mpc-steps 1".
set -uo pipefail
WORK=${WORK:-/tmp/rr}; POLICY=$(realpath "${POLICY:-dynres_jax/checkpoints/dynamics}"); ROUND=${ROUND:-1}
EPISODES=${EPISODES:-64}; CAPTURE=${CAPTURE:-"0 3 6 9"}; COUNT=${COUNT:-64}; STEPS=${STEPS:-1000}
BATCH=${BATCH:-16}; LR=${LR:-1e-4}; LETTERS_TRAIN=${LETTERS_TRAIN:-ACEHMNSX}
VARIANTS=${VARIANTS:-"pos --rank-weight 0;list --rank-weight 1"}
cores=$(nproc); R=$WORK/results; mkdir -p "$R/logs" "$WORK/sets" "$WORK/runs"
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD  # builds and lanes share the GPU
log() { echo "$(date +%T) $*" | tee -a "$R/logs/stages.log"; }

build() {  # NAME TASK KIND SEED EPISODES [FLAGS...]: a training set planned by POLICY
  local name=$1 task=$2 kind=$3 seed=$4 episodes=$5; shift 5
  [ -f "$WORK/sets/$name/ranking_set.npz" ] && return
  # shellcheck disable=SC2086
  python -m studies.ranking build --out "$WORK/sets/$name" --task "$task" --kind "$kind" --episodes "$episodes" \
    --capture $CAPTURE --seed "$seed" --policy "$POLICY" --twin-sigma 0 --workers $((cores / 3)) ${BUILD_FLAGS:-} \
    "$@" > "$R/logs/build_$name.log" 2>&1
  log "set $name: $(tail -1 "$R/logs/build_$name.log")"
}

log "start: round $ROUND, policy $POLICY, $cores cores"
s=$((9000 + 100 * ROUND))
build "gather_mnm_$ROUND" gather mnm $s "$EPISODES" &
build "redistribute_$ROUND" redistribute coffee $((s + 10)) "$EPISODES" --letters "$LETTERS_TRAIN" &
build "gather_almond_$ROUND" gather almond $((s + 20)) $((EPISODES / 2 > 0 ? EPISODES / 2 : 1)) &
wait
sets=$(ls "$WORK"/sets/*/ranking_set.npz)  # this round's and any earlier round's on this machine (aggregated)
tests=$(ls docs/dynamics_scale/sets/*.npz)

IFS=';' read -ra specs <<< "$VARIANTS"
ckpts=()
for spec in "${specs[@]}"; do
  read -r name flags <<< "$spec"
  name="r${ROUND}$name"; ckpts+=("$WORK/runs/$name/ckpt")  # [a-z0-9]: the ladder table's model names
  [ -d "$WORK/runs/$name/ckpt" ] && continue
  # shellcheck disable=SC2086
  python -m studies.rank_finetune --train $sets --test $tests --ckpt "$POLICY" --out "$WORK/runs/$name" \
    --steps "$STEPS" --batch "$BATCH" --lr "$LR" $flags --save "$WORK/runs/$name/ckpt" \
    > "$R/logs/finetune_$name.log" 2>&1
  log "fine-tune $name: $(tail -2 "$R/logs/finetune_$name.log" | tr '\n' ' ')"
  mkdir -p "$R/runs"
  for f in "$WORK/runs/$name"/rank_finetune.*; do cp "$f" "$R/runs/${name}_$(basename "$f")"; done
  tar -czf "$R/runs/$name.ckpt.tar.gz" -C "$WORK/runs/$name" ckpt
done

jobs=$WORK/closed_loop.jobs; : > "$jobs"
policy_col=""; [ "$POLICY" != "$(realpath dynres_jax/checkpoints/dynamics)" ] && policy_col=$POLICY
lane=0
for c in "$policy_col" "${ckpts[@]}"; do
  echo "$lane gather mnm 50 $COUNT $c" >> "$jobs"; echo "$((lane + 1)) redistribute coffee 50 $COUNT $c" >> "$jobs"
  lane=$((lane + 2))
done
OUT=$R/lanes WORK=$WORK/ladder JOBS=$jobs SEED=6000 LETTERS=${LETTERS:-JTULY} bash scripts/gpu_ladder.sh > "$R/logs/ladder.log" 2>&1
log "closed loop: $(grep -c done "$R/logs/ladder.log") jobs done"
mkdir -p "$WORK/unpacked"
for t in "$R"/lanes/*.tar.gz; do tar -xzf "$t" -C "$WORK/unpacked"; done
base=50; [ -n "$policy_col" ] && base="50@$(basename "$(dirname "$policy_col")")"
python scripts/model_table.py --runs "$WORK/unpacked" --base "$base" --out "$R" > "$R/logs/table.log" 2>&1
log "table: $(cat "$R/closed_loop.md" 2>/dev/null | tr '\n' ' ' | head -c 2000)"
touch "$WORK/done"
