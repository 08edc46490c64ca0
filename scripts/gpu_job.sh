# A jax.distributed job over every GPU of one host, PER_GPU processes a GPU (source it). Sets gpus (GPUS overrides:
# a CPU dry run), n (processes), workers (host cores a process, for C MuJoCo) and fraction (GPU memory a process);
# job LOG CMD...: CMD in n processes, process i on GPU i mod gpus with the job's flags appended, its output in LOG.i;
# returns when all have ended.
PER_GPU=${PER_GPU:-2}
gpus=${GPUS:-$(nvidia-smi -L 2>/dev/null | grep -c "^GPU" || true)}
n=$((gpus * PER_GPU)); workers=$(( $(nproc) / n )); [ "$workers" -ge 1 ] || workers=1
fraction=$(python -c "print(round(0.9 / $PER_GPU, 2))")
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jax_cache}  # later stages reuse compiles

job() {  # LOG CMD...
  local log=$1 port=$((20000 + RANDOM % 20000)) pids=() i p
  shift
  for ((i = 0; i < n; i++)); do
    CUDA_VISIBLE_DEVICES=$((i % gpus)) XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction "$@" \
      --coordinator "localhost:$port" --num-processes "$n" --process-id "$i" > "$log.$i" 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait "$p"; done
}
