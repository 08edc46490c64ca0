#!/usr/bin/env bash
# Issue 65: the judge fine-tuned to rank the shipped planner's candidates (the listwise loss that lifted the fast
# model, docs/dynamics_scale/rounds.md), chosen on tuning seeds and measured once on fresh ones. One host of 4 GPUs,
# in calls of at most 10 minutes that resume on a warm machine (a stage whose output exists is skipped; a stage that
# would not fit before UNTIL waits for the next call):
#   UNTIL=$(( $(date +%s) + 560 )) JUDGE=.judge/ckpt WORK=/tmp/jr bash scripts/gpu_judge_rank.sh     # repeat
# 1. sets: ranking sets planned by the shipped model (studies.ranking build --twin-sigma 0): Gather M&M (EPISODES),
#    Gather almond (EPISODES / 2), Redistribute coffee on ACEHMNSX (EPISODES), seeds 9500, 9520, 9510.
# 2. fine-tune JUDGE (studies.rank_finetune, STEPS steps of 16 states, scored before and after on the committed
#    held-out sets docs/dynamics_scale/sets), one variant a GPU: gath (listwise + position on the Gather sets, lr
#    1e-4), gslow (the same, lr 3e-5), all (listwise + position on all three sets), gpos (position alone on the Gather
#    sets: the control).
# 3. tune: evaluate --methods 50 judge for JUDGE and each variant, TUNE episodes of M&M Gather (seed 7000) and of
#    Redistribute on JTULYZRKW (seed 6000). The rule, fixed before any run: the judge with the most successes over
#    both tasks, ties to the lower mean final distance; $WORK/chosen. CHOSEN=NAME skips this stage (a variant
#    chosen beforehand; VARIANTS="NAME" then fine-tunes that one alone).
# 4. fresh (once, never tuned on): the chosen judge against the model, 256 paired episodes of M&M Gather (seed 91000)
#    and of Redistribute on 345689 (characters nobody has used, seed 91500), 64 of each other kind (seed 92000).
# Results: $WORK/results.tar.gz (logs, tables, summaries) and $WORK/judges.tar.gz (the module-only
# checkpoint of the chosen variant), copied to $OUT where set. Env: WORK, UNTIL, JUDGE, VARIANTS, CHOSEN, EPISODES
# (64), STEPS (1500), TUNE (64), FRESH (256), KINDS_EPISODES (64; 0: none), FRESH_SECONDS (420), BUILD_FLAGS,
# FT_FLAGS, EVAL_FLAGS. CPU dry run: GPUS=1 EPISODES=2 STEPS=2 TUNE=1 FRESH=1 KINDS_EPISODES=1
# BUILD_FLAGS="--capture 0 --samples 4 --adam-steps 2 --pieces 30" FT_FLAGS="--batch 2"
# EVAL_FLAGS="--quick --mpc-steps 1 --samples 4 --adam-steps 2 --pieces 40 --best-omega 10".
set -uo pipefail
WORK=${WORK:-/tmp/jr}; JUDGE=$(realpath "${JUDGE:-.judge/ckpt}"); EPISODES=${EPISODES:-64}; STEPS=${STEPS:-1500}
TUNE=${TUNE:-64}; FRESH=${FRESH:-256}; KINDS_EPISODES=${KINDS_EPISODES:-64}; VARIANTS=${VARIANTS:-"gath gslow all gpos"}
UNTIL=${UNTIL:-$(( $(date +%s) + 3600 ))}
read -ra build_flags <<< "${BUILD_FLAGS:-}"; read -ra ft_flags <<< "${FT_FLAGS:-}"
read -ra eval_flags <<< "${EVAL_FLAGS:-}"
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$PWD  # several processes a GPU
cores=$(nproc)
fits() { [ $(( UNTIL - $(date +%s) )) -ge "$1" ] || { log "$2 waits for the next call"; pack_all; exit 0; }; }
pack_all() {
  pack --exclude='*/ckpt' --exclude='*/positions*'
  local v; v=$(cat "$WORK/chosen" 2>/dev/null)
  [ -d "$WORK/runs/ft_$v/ckpt" ] && tar -czf "$WORK/judges.tmp" -C "$WORK/runs" "ft_$v/ckpt" &&
    mv "$WORK/judges.tmp" "$WORK/judges.tar.gz"
  [ -n "${OUT:-}" ] && cp "$WORK"/results.tar.gz "$WORK"/judges.tar.gz "$OUT"/ 2>/dev/null
  return 0
}
log "call: $gpus GPUs, $cores cores, $(( UNTIL - $(date +%s) )) s to go"

build() {  # GPU NAME TASK KIND SEED EPISODES [FLAGS...]
  local g=$1 name=$2 task=$3 kind=$4 seed=$5 episodes=$6; shift 6
  [ -f "$WORK/sets/$name/ranking_set.npz" ] && return
  rm -rf "$WORK/sets/$name"; on "$g"
  python -m studies.ranking build --out "$WORK/sets/$name" --task "$task" --kind "$kind" --episodes "$episodes" \
    --capture 0 3 6 9 --seed "$seed" --twin-sigma 0 --workers $(( cores / 3 )) "${build_flags[@]}" "$@" \
    > "$WORK/logs/build_$name.log" 2>&1
  log "set $name: $(tail -1 "$WORK/logs/build_$name.log")"
}
if [ ! -f "$WORK/sets/done" ]; then
  fits 300 sets
  build 0 gather_mnm gather mnm 9500 "$EPISODES" &
  build 1 redistribute redistribute coffee 9510 "$EPISODES" --letters ACEHMNSX &
  build 2 gather_almond gather almond 9520 $(( EPISODES / 2 > 0 ? EPISODES / 2 : 1 )) &
  wait
  [ "$(ls "$WORK"/sets/*/ranking_set.npz 2>/dev/null | wc -l)" = 3 ] && touch "$WORK/sets/done"
fi
pack_all
[ -f "$WORK/sets/done" ] || { log "sets incomplete"; exit 1; }

gath=("$WORK/sets/gather_mnm/ranking_set.npz" "$WORK/sets/gather_almond/ranking_set.npz")
finetune() {  # GPU NAME FLAGS... (train sets first: --train ...)
  local g=$1 name=$2; shift 2
  [ -d "$WORK/runs/ft_$name/ckpt" ] && return
  rm -rf "$WORK/runs/ft_$name"; on "$g"
  python -m studies.rank_finetune --test docs/dynamics_scale/sets/*.npz --ckpt "$JUDGE" --out "$WORK/runs/ft_$name" \
    --steps "$STEPS" --batch 16 --save "$WORK/runs/ft_$name/ckpt" "${ft_flags[@]}" "$@" \
    > "$WORK/logs/finetune_$name.log" 2>&1
  log "fine-tune $name: $(tail -2 "$WORK/logs/finetune_$name.log" | tr '\n' ' ')"
}
fits 240 fine-tune
i=0
for v in $VARIANTS; do
  case $v in
    gath) finetune $(( i % gpus )) gath --train "${gath[@]}" --lr 1e-4 & ;;
    gslow) finetune $(( i % gpus )) gslow --train "${gath[@]}" --lr 3e-5 & ;;
    all) finetune $(( i % gpus )) all --train "$WORK"/sets/*/ranking_set.npz --lr 1e-4 & ;;
    gpos) finetune $(( i % gpus )) gpos --train "${gath[@]}" --lr 1e-4 --rank-weight 0 & ;;
    *) log "no variant $v"; exit 1 ;;
  esac
  i=$(( i + 1 ))
done
wait
pack_all

loop() {  # GPU NAME CKPT SEED EPISODES TASK-FLAGS...: evaluate --methods 50 judge into $WORK/runs/NAME
  local g=$1 name=$2 judge=$3 seed=$4 episodes=$5; shift 5
  [ -f "$WORK/runs/$name/summary.json" ] && return
  on "$g"
  python -m experiments.evaluate --methods 50 judge --judge "$judge" --episodes "$episodes" --seed "$seed" \
    --samples 50 --workers "$LOOP_WORKERS" --out "$WORK/runs/$name" "$@" "${eval_flags[@]}" \
    > "$WORK/logs/$name.log" 2>&1
  log "$name: $(grep -E '^ *(50|judge)[: -]' "$WORK/logs/$name.log" | tr '\n' ' ' || tail -3 "$WORK/logs/$name.log")"
}
judges=(base $VARIANTS)
path() { [ "$1" = base ] && echo "$JUDGE" || echo "$WORK/runs/ft_$1/ckpt"; }
[ -n "${CHOSEN:-}" ] && [ ! -f "$WORK/chosen" ] && echo "$CHOSEN" > "$WORK/chosen" && log "chosen beforehand: $CHOSEN"
if [ ! -f "$WORK/chosen" ]; then
  fits 480 tune  # ten closed loops at once ran past 320 s on 4 H200s: the call that lost a host had started at 318
  LOOP_WORKERS=$(( cores / (2 * $(wc -w <<< "${judges[*]}")) + 1 ))
  i=0
  for j in "${judges[@]}"; do
    loop $(( i % gpus )) "tune_mnm_$j" "$(path "$j")" 7000 "$TUNE" --task gather --kind mnm &
    loop $(( (i + 1) % gpus )) "tune_red_$j" "$(path "$j")" 6000 "$TUNE" --task redistribute --letters JTULYZRKW &
    i=$(( i + 2 ))
  done
  wait
  if ! python - "$WORK" "${judges[@]}" > "$WORK/chosen" 2> "$WORK/logs/tune_table.log" <<'PY'
import json, sys
work, names = sys.argv[1], sys.argv[2:]
def rows(name):
    s = [json.load(open(f"{work}/runs/tune_{t}_{name}/summary.json")) for t in ("mnm", "red")]
    return [m for x in s for m in [x["methods"]["judge"]]], [x["methods"]["50"] for x in s]
score = {}
for n in names:
    judge, model = rows(n)
    score[n] = (sum(m["success_share"] for m in judge), -sum(m["final_distance"] for m in judge))
    print(f"{n}: success {[m['success_share'] for m in judge]} (model {[m['success_share'] for m in model]})",
          file=sys.stderr)
print(max(names, key=lambda n: score[n]))
PY
  then log "tune incomplete"; rm -f "$WORK/chosen"; pack_all; exit 1; fi
  log "chosen on tuning seeds: $(cat "$WORK/chosen")"
fi
pack_all

chosen=$(path "$(cat "$WORK/chosen")")
fits "${FRESH_SECONDS:-420}" fresh
LOOP_WORKERS=$(( cores / 4 + 1 ))
loop 0 fresh_mnm "$chosen" 91000 "$FRESH" --task gather --kind mnm &
loop 1 fresh_red "$chosen" 91500 "$FRESH" --task redistribute --letters 345689 &
i=2
if [ "$KINDS_EPISODES" -gt 0 ]; then
  for k in coffee almond rice granola candy; do
    loop $(( i % gpus )) "fresh_$k" "$chosen" 92000 "$KINDS_EPISODES" --task gather --kind "$k" & i=$(( i + 1 ))
  done
fi
wait
pack_all
touch "$WORK/done"; log "done"
