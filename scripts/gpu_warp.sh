#!/usr/bin/env bash
# Issue 36's MuJoCo Warp engine on one GPU machine (docs/warp), about 25 minutes on one H100 and 16 host cores:
#   WORK=/root/warp bash scripts/gpu_warp.sh
# 1. studies.warp_engine --first-call: each kind's first call in a fresh process; the first of them is the machine's
#    first Warp call (kernels compiled from nothing, as on a fresh machine). Then, while the data is made, its
#    agreement check (256 worlds a kind, one push from C-settled piles, Warp against C).
# 2. Transfer: data sets W (--backend warp) and C (--backend mujoco, C_WORKERS processes), the same DataConfig
#    (seed 11, EPISODES episodes of 10 pushes, shards of 128 worlds) but the engine; models w and c on them
#    (--recipe shipped, STEPS steps each, both at once).
# 3. experiments.benchmark warp alone on the machine: whole pushes/s against C MuJoCo on every host core.
# 4. Closed-loop Gather in the C scene with w and with c (scripts/gpu_ladder.sh: ω = 50, 50 x 100, seeds from 5000):
#    M&M COUNT episodes and almond 64, paired (episode i is the same pile and goal for both models).
# 5. mix (issue 50, not in the default STAGES): the same DataConfig (seed 12, EPISODES episodes) end to end, start-up
#    and compiles included, by C workers on every host core alone, then by Warp with C workers on the other cores.
# 6. gpus (issue 50 item 4, not in the default STAGES): data on 1, 2 and 4 GPUs of the host, one process a GPU (a
#    jax.distributed job, scripts/gpu_job.sh, each process with its share of the host cores as C workers), the same
#    DataConfig (seed 13, EPISODES episodes in shards of GPU_WORLDS worlds, default 256), end to end. GPU_FLAGS picks
#    the data (default "--backend warp": Warp alone); on-policy data on C workers: GPU_FLAGS="--backend mujoco
#    --planned 0.5" with at least six shards a process, so each process plans at every ω of on_policy.OMEGAS.
#    GPU_COUNTS (default "1 2 4") picks the runs, those of more GPUs than the host has skipped.
# 7. planned (issue 50 item 3, not in the default STAGES): on-policy data (--planned 0.5, the shipped policy) as made
#    today (C workers, shards of 64 worlds: 27 frames/s in docs/model_at_scale) and by Warp in shards of PLANNED_WORLDS
#    (default 2048) worlds, each decision batched over the whole shard; PLANNED_EPISODES (2048) episodes each.
# 8. scenes (issue 50 item 1, not in the default STAGES): Warp data alone (seed 15, EPISODES episodes in shards of
#    GPU_WORLDS worlds) with a scene per shard (--scenes 0) and with one scene for the run (--scenes 1), end to end,
#    each with Warp's kernel cache empty.
# 9. profile (issue 50 item 3, not in the default STAGES): where an on-policy shard's time goes
#    (scripts/profile_on_policy.py, PLANNED_WORLDS worlds, 3 pushes, two rounds of the same shard), Warp and C workers;
#    on a host of two GPUs side by side, each on one GPU and half the cores, else one after the other.
# Stages run in the order engine, data, train, loop, mix, gpus, planned, scenes, profile, bench (the benchmark last).
# $WORK/results.tar.gz (logs, runs: the study, the benchmark, the models, closed-loop folders) after every stage;
# $WORK/done at the end; a stage whose output exists is skipped. Env: WORK, EPISODES (1024), STEPS (14000), COUNT
# (256), C_WORKERS (6), BENCH_FLAGS (--worlds 2048 8192 --graph-modes WARP JAX), DATA_FLAGS, STAGES (engine data
# train bench loop). A CPU dry run with warp-lang installed: EPISODES=8 STEPS=20 COUNT=1 C_WORKERS=1 DATA_FLAGS="--kinds
# coffee --pieces 20 20 --two-kinds 0 --image-size 64 --worlds 4" ENGINE_FLAGS="--kinds candy --worlds 2"
# BENCH_FLAGS=--quick FLAGS="--quick --samples 4 --adam-steps 2 --mpc-steps 1".
set -uo pipefail
WORK=${WORK:-/root/warp}; EPISODES=${EPISODES:-1024}; STEPS=${STEPS:-14000}; COUNT=${COUNT:-256}
C_WORKERS=${C_WORKERS:-6}; STAGES=${STAGES:-"engine data train bench loop"}
BENCH_FLAGS=${BENCH_FLAGS:-"--worlds 2048 8192 --graph-modes WARP JAX"}
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # the study, two data runs and two trainings share the GPU
# shellcheck source=scripts/gpu_lib.sh
source "$(dirname "$0")/gpu_lib.sh"
stage() { [[ " $STAGES " == *" $1 "* ]]; }

log "start: $(nvidia-smi -L 2>/dev/null | head -1), $(nproc) cores"
if stage engine && [ ! -f "$WORK/runs/engine/warp_engine.md" ]; then
  # shellcheck disable=SC2086
  python -m studies.warp_engine --out "$WORK/runs/engine" --first-call --workers 8 ${ENGINE_FLAGS:-} \
    > "$WORK/logs/engine.log" 2>&1 &
  engine=$!
  # the first calls run alone (a fresh kernel cache), then the agreement check shares the machine with the data
  while kill -0 "$engine" 2>/dev/null && ! grep -q "^first call candy" "$WORK/logs/engine.log"; do sleep 5; done
  log "first calls: $(grep -c 'ok=True' "$WORK/logs/engine.log") of 6 ok"
fi
if stage data; then
  [ -f "$WORK/data/W/summary.json" ] || gen W 11 128 1 --backend warp &
  [ -f "$WORK/data/C/summary.json" ] || gen C 11 128 "$C_WORKERS" --backend mujoco
  wait
  pack
fi
stage train && { train w W & train c C & wait; pack; }
if stage loop; then
  jobs=$WORK/loop.jobs
  printf '%s\n' "0 gather mnm 50 $COUNT $WORK/runs/c/ckpt" "1 gather mnm 50 $COUNT $WORK/runs/w/ckpt" \
    "2 gather almond 50 64 $WORK/runs/c/ckpt" "3 gather almond 50 64 $WORK/runs/w/ckpt" > "$jobs"
  OUT=$WORK/runs/loop WORK=$WORK/ladder JOBS=$jobs bash scripts/gpu_ladder.sh > "$WORK/logs/loop.log" 2>&1
  log "closed loop: $(grep -c done "$WORK/logs/loop.log") jobs done"
  pack
fi
if stage mix; then
  timed Calone 12 128 "$(nproc)" "s['shards_by_engine']" --backend mujoco
  timed WC 12 128 1 "s['shards_by_engine']" --backend warp --cpu-workers $(($(nproc) - 1))
  pack
fi
if stage gpus; then
  for g in ${GPU_COUNTS:-1 2 4}; do
    [ "$g" -le "$(nvidia-smi -L 2>/dev/null | grep -c '^GPU')" ] && [ ! -f "$WORK/data/G$g/summary.json" ] || continue
    t0=$(now)
    # shellcheck disable=SC2086
    ( GPUS=$g PER_GPU=1; . "$(dirname "$0")/gpu_job.sh"
      job "$WORK/logs/data_G$g.log" python -m experiments.generate_data --out "$WORK/data/G$g" --episodes "$EPISODES" \
        --pushes 10 --worlds "${GPU_WORLDS:-256}" --seed 13 --no-progress ${GPU_FLAGS:---backend warp} \
        $(case "${GPU_FLAGS:-}" in *mujoco*) echo --workers "$workers";; esac) ${DATA_FLAGS:-} )
    log "gpus $g: $(since "$t0") s end to end"
  done
  pack
fi
if stage planned; then
  rate="s['frames'], 'frames,', round(s['samples_per_s'], 1), 'frames/s'"
  EPISODES=${PLANNED_EPISODES:-2048} timed Pc 14 64 "$(nproc)" "$rate" --backend mujoco --planned 0.5
  EPISODES=${PLANNED_EPISODES:-2048} timed Pw 14 "${PLANNED_WORLDS:-2048}" 1 "$rate" --backend warp --planned 0.5
  pack
fi
if stage scenes; then
  for s in 0 1; do  # each with Warp's kernel cache empty, as on a fresh machine
    ( export WARP_CACHE_PATH=$WORK/kernels_S$s
      timed "S$s" 15 "${GPU_WORLDS:-256}" 1 "s['shards'], 'shards'" --backend warp --scenes "$s" )
  done
  pack
fi
if stage profile; then
  gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU'); cores=$(nproc); [ "$gpus" -ge 2 ] && cores=$((cores / 2))
  for b in warp mujoco; do
    [ -f "$WORK/runs/profile_$b.json" ] && continue
    g=$([ "$gpus" -ge 2 ] && [ "$b" = mujoco ] && echo 1 || echo 0); first=$((g * cores))
    CUDA_VISIBLE_DEVICES=$g taskset -c "$first-$((first + cores - 1))" python scripts/profile_on_policy.py --backend "$b" \
      --worlds "${PLANNED_WORLDS:-1024}" --workers $((cores - 1)) --json "$WORK/runs/profile_$b.json" \
      > "$WORK/logs/profile_$b.log" 2>&1 &
    [ "$gpus" -ge 2 ] || wait
  done
  wait
  log "profile: $(cat "$WORK"/logs/profile_*.log | grep -c '^{') rounds"
  pack
fi
if stage bench && [ ! -f "$WORK/runs/bench_warp.json" ]; then
  log "benchmark"
  # shellcheck disable=SC2086
  python -m experiments.benchmark warp $BENCH_FLAGS --json "$WORK/runs/bench_warp.json" \
    > "$WORK/logs/bench.log" 2>&1
  log "benchmark: $(grep -o 'Warp / C MuJoCo.*' "$WORK/logs/bench.log")"
  pack
fi
log "done"
touch "$WORK/done"
