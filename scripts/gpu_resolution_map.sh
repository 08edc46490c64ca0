#!/usr/bin/env bash
# Issue 51 item 4: the map of where ω matters, on every GPU of one host. One anytime surface (tradeoff --surface: c*
# for ω in 10-100 and N in 1-200 Adam steps, SCENES scenes of each of two kinds, fresh seed SEED) for each planner of
# PLANNERS and sample count of SAMPLES, all at once, one process each on GPU i mod the GPU count, each with its share
# of the host's cores; then scripts/resolution_map.py prices every surface at budgets of 0.03-2 s and writes the map.
#   OUT=/root/map bash scripts/gpu_resolution_map.sh
# Env: OUT, SCENES (128), SEED (63000: fresh), SAMPLES ("20 50 200"), PLANNERS ("ours reference"; also
# reference-starts, reference-lr, reference-pricing: the authors' planner with that one option ours, for the
# attribution), FLAGS (more tradeoff flags). The attribution (issue 51), 4 surfaces at M = 50 on fresh scenes:
#   OUT=/root/attr SAMPLES=50 SEED=65000 PLANNERS="reference reference-starts reference-lr reference-pricing" \
#     bash scripts/gpu_resolution_map.sh
# A CPU dry run: GPUS=1 SCENES=quick SAMPLES=4 (tradeoff's --quick sizes). A finished surface is kept on a rerun.
# $OUT/results.tar.gz after every surface.
set -uo pipefail
OUT=${OUT:-/root/map}; SCENES=${SCENES:-128}; SEED=${SEED:-63000}; SAMPLES=${SAMPLES:-"20 50 200"}
PLANNERS=${PLANNERS:-"ours reference"}
gpus=${GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c "^GPU" || true)}
read -ra samples <<< "$SAMPLES"; read -ra planners <<< "$PLANNERS"
n=$(( ${#samples[@]} * ${#planners[@]} )); workers=$(( $(nproc) / n )); [ "$workers" -ge 1 ] || workers=1
fraction=$(python -c "print(round(0.9 / -(-$n // $gpus), 2))")
mkdir -p "$OUT"
pack() { tar -czf "$OUT/results.tmp" -C "$OUT" --exclude results.tar.gz --exclude results.tmp . 2>/dev/null
         mv "$OUT/results.tmp" "$OUT/results.tar.gz"; }
i=0; pids=(); runs=()
for planner in "${planners[@]}"; do
  for m in "${samples[@]}"; do
    name=${planner}_M${m}; runs+=("$OUT/$name")
    flags="--scenes $SCENES --samples $m"; [ "$SCENES" = quick ] && flags="--quick"
    case $planner in  # each reverted option takes our planner's value (planner_args.PLANNER_OPTIONS)
      ours) ;;
      reference) flags="$flags --reference-planner --resamples 1" ;;
      reference-starts) flags="$flags --reference-planner --resamples 1 --starts pile" ;;
      reference-lr) flags="$flags --reference-planner --resamples 1 --lr 0.02" ;;
      reference-pricing) flags="$flags --reference-planner --resamples 1 --pricing measured --buckets 16 32 64 100" ;;
      *) echo "unknown planner $planner"; exit 2 ;;
    esac
    echo "$(date +%T) $name on GPU $((i % gpus)), $workers workers"
    # shellcheck disable=SC2086
    ( CUDA_VISIBLE_DEVICES=$((i % gpus)) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction python -m experiments.tradeoff \
        --surface --seed "$SEED" --workers "$workers" --out "$OUT/$name" $flags \
        ${FLAGS:-} > "$OUT/$name.log" 2>&1; echo "$(date +%T) $name: $(tail -1 "$OUT/$name.log" | cut -c1-100)"; pack ) &
    pids+=($!); i=$((i + 1))
  done
done
for p in "${pids[@]}"; do wait "$p"; done
done_runs=(); for r in "${runs[@]}"; do [ -f "$r/surface.json" ] && done_runs+=("$r"); done
[ "${#done_runs[@]}" -gt 0 ] || { echo "no surface finished: see $OUT/*.log"; exit 1; }
python "$(dirname "$0")/resolution_map.py" "${done_runs[@]}" --out "$OUT/map" > "$OUT/map.log" 2>&1
echo "$(date +%T) map: $(grep -c '^## ' "$OUT/map/map.md" 2>/dev/null) runs"; pack; touch "$OUT/done"
