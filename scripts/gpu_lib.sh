# Shared by the GPU run scripts (source it): stage log, results tarball, data sets and models under $WORK.
# Sets gpus (GPUS overrides) and on N. Env: WORK, EPISODES (episodes a data set), STEPS (Adam steps a model), BOX
# (minutes, each training's safety stop), DATA_FLAGS (more generate_data flags).
mkdir -p "$WORK/runs" "$WORK/logs"
gpus=${GPUS:-$(n=$(nvidia-smi -L 2>/dev/null | grep -c "^GPU"); echo $(( n > 0 ? n : 1 )))}  # GPUS: override
on() { CUDA_VISIBLE_DEVICES=$(( $1 % gpus )); export CUDA_VISIBLE_DEVICES; }  # N: what runs next uses GPU N mod gpus
log() { echo "$(date +%T) $*" | tee -a "$WORK/logs/stages.log"; }
now() { date +%s.%N; }
since() { python -c "print(round($(now) - $1, 1))"; }  # T0 (from now): seconds since, one decimal
summary() { python -c "import json; s = json.load(open('$1/summary.json')); print($2)"; }  # DIR EXPR of s, its summary

pack() {  # [TAR FLAGS...]: logs and runs (no data) into $WORK/results.tar.gz, atomically
  tar -czf "$WORK/results.tmp" "$@" -C "$WORK" logs runs 2>/dev/null
  mv "$WORK/results.tmp" "$WORK/results.tar.gz"
}

gen() {  # NAME SEED WORLDS WORKERS [FLAGS...]: EPISODES episodes of 10 pushes into $WORK/data/NAME
  local name=$1 seed=$2 worlds=$3 workers=$4; shift 4
  # shellcheck disable=SC2086
  python -m experiments.generate_data --out "$WORK/data/$name" \
    --episodes "$EPISODES" --pushes 10 --worlds "$worlds" --seed "$seed" --workers "$workers" --no-progress \
    ${DATA_FLAGS:-} "$@" \
    > "$WORK/logs/data_$name.log" 2>&1 && log "data $name: $(grep -o '"frames": [0-9]*' "$WORK/logs/data_$name.log")"
}

timed() {  # NAME SEED WORLDS WORKERS WHAT [FLAGS...]: gen, unless NAME is made, then log its seconds end to end
  local name=$1 seed=$2 worlds=$3 workers=$4 what=$5 t0  # WHAT: an expression of its summary s (``summary``)
  shift 5
  [ -f "$WORK/data/$name/summary.json" ] && return
  t0=$(now)
  gen "$name" "$seed" "$worlds" "$workers" "$@"
  log "$name: $(since "$t0") s end to end, $(summary "$WORK/data/$name" "$what")"
}

train() {  # NAME DATA... [-- FLAGS...]: --recipe shipped on $WORK/data/DATA..., STEPS steps, into $WORK/runs/NAME
  local name=$1; shift
  local folders=() flags=()
  while [ $# -gt 0 ] && [ "$1" != -- ]; do folders+=("$WORK/data/$1"); shift; done
  [ $# -gt 0 ] && shift && flags=("$@")
  [ -f "$WORK/runs/$name/done" ] && return
  log "train $name on ${folders[*]##*/} ${flags[*]}"
  python -m experiments.train_dynamics --recipe shipped --data "${folders[@]}" \
    --out "$WORK/runs/$name" --steps "$STEPS" --eval-every 2000 --max-minutes "${BOX:-11}" --quiet "${flags[@]}" \
    > "$WORK/logs/train_$name.log" 2>&1 && touch "$WORK/runs/$name/done"
  log "train $name: $(tail -1 "$WORK/runs/$name/metrics.jsonl")"
}
