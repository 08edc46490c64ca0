#!/usr/bin/env bash
# The wheel as a user installs it (CI runs this): build it, install it in a fresh virtual environment, run a one-step
# Gather from a folder outside the checkout and check that it planned with the shipped learned model (package data),
# not the sweep heuristic, at the checkout's step (a stale build/ folder once packed an older step beside it).
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
step=$(find dynres_jax/checkpoints/dynamics -mindepth 1 -maxdepth 1 -name '[0-9]*' -printf '%f\n' | sort -n | tail -1)
python3 -m pip wheel -q --no-deps . -w "$work/dist"
python3 -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$work"/dist/*.whl
cd "$work"
"$work/venv/bin/dynres" gather --mpc-steps 1 --samples 4 --adam-steps 2 --out "$work/out"
"$work/venv/bin/python" - "$work/out/metrics.json" "$step" <<'PY'
import json, re, sys
dynamics = json.load(open(sys.argv[1]))["dynamics"]
assert dynamics.startswith("learned (") and "site-packages" in dynamics, f"the wheel did not plan with its model: {dynamics}"
assert re.search(rf"\bstep {sys.argv[2]}\b", dynamics), f"the wheel planned with another step than the checkout's {sys.argv[2]}: {dynamics}"
print(f"wheel test passed: {dynamics}")
PY
rm -rf "$work"
