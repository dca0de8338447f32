#!/usr/bin/env bash
# The GPU checks in one run: the test suite and the README's GPU figures, on a machine with
# an NVIDIA GPU and JAX's CUDA wheels (`pip install -e ".[test,cuda]"`).
#
#     scripts/gpu_check.sh OUTDIR [SECONDS]
#
# Each step has its own time limit (the whole run stays within SECONDS, default 560) and a
# failed step does not stop the next. Logs and JSON go to OUTDIR; the end of the output
# is a summary. Steps: the device; the test suite (pytest-xdist, processes sharing the
# card); `bench.py` forward frames and the fit benchmark (cold, warm, steady; deterministic
# GPU ops, as the CLI runs); `profile_render.py`: render's parts and host steps, and the
# fit's steps and the frame with and without deterministic ops (with deterministic ops,
# traced: the kernels that take the device's time); last, where time is left,
# the cold fit benchmark under XLA flags that may cut GPU compilation.
set -u
out=${1:?usage: scripts/gpu_check.sh OUTDIR [SECONDS]}
total=${2:-560}
mkdir -p "$out"
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
det="--xla_gpu_deterministic_ops=true"
left() { echo $(( total - SECONDS - ${1:-0} )); }
step() {  # step NAME LIMIT CMD...: run CMD with a time limit, log to OUTDIR/NAME.log
  local name=$1 limit=$2; shift 2
  (( limit > $(left) )) && limit=$(left)
  if (( limit < 20 )); then echo "== $name: skipped (no time left)"; return; fi
  echo "== $name (limit ${limit}s): $*"
  local t0=$SECONDS
  timeout "$limit" "$@" >"$out/$name.log" 2>&1
  echo "== $name: rc $? in $(( SECONDS - t0 ))s"
}

{ nvidia-smi -L; python -c "import sys, jax; print(sys.version.split()[0], jax.__version__,
jax.devices())"; } 2>&1 | tee "$out/device.log"

step tests 320 python -m pytest -v -n 14 -p no:benchmark -p no:cacheprovider \
  --durations=15 --junitxml "$out/junit.xml"
step bench 150 env XLA_FLAGS="$det" python scripts/bench.py --no-mitsuba --no-cli \
  --parts forward,fit --budget 6 --repeats 10 --out "$out/bench"
step profile 90 env XLA_FLAGS="$det" python scripts/profile_render.py --host --fit --trace \
  --repeats 20 --out "$out/profile"
step fit_nondeterministic 25 python scripts/profile_render.py --scenes "" --fit \
  --out "$out/profile"
step frame_nondeterministic 40 python scripts/profile_render.py --repeats 20 \
  --out "$out/profile"
for flags in "--xla_gpu_autotune_level=0" "--xla_gpu_enable_command_buffer="; do
  step "fit_${flags//[^a-z0-9]/_}" "$(left 5)" env XLA_FLAGS="$det $flags" \
    python scripts/bench.py --no-mitsuba --no-cli --parts fit --budget 3 --out "$out/flags"
done

echo "=== summary"
tail -n 30 "$out/bench.log"
grep -h '^{' "$out/profile.log" "$out/fit_nondeterministic.log" \
  "$out/frame_nondeterministic.log"
for f in "$out"/fit__*.log; do echo "$f"; grep '^| jaxnm' "$f"; done
grep -E "^(FAILED|ERROR)|passed|failed" "$out/tests.log" | grep -v '^\[gw' | tail -n 25
