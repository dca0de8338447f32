#!/usr/bin/env bash
# The GPU checks in one run: the test suite and the README's GPU figures, on a machine with
# an NVIDIA GPU and JAX's CUDA wheels (`pip install -e ".[test,cuda]"`).
#
#     scripts/gpu_check.sh OUTDIR [SECONDS] [all|timing|tests]
#
# Each step has its own time limit (the whole run stays within SECONDS, default 560) and a
# failed step does not stop the next. Logs and JSON go to OUTDIR; the end of the output
# is a summary. Steps ("timing"): the device; `bench.py` forward frames and the fit
# benchmark (cold, warm, steady; deterministic GPU ops, as the CLI runs);
# `profile_render.py`: render's parts, its host steps and the fit's steps with
# deterministic ops (traced: the kernels that take the device's time), the same with
# loops and conditionals in CUDA graphs (`jaxnm.runtime.use_gpu_graphs`), and the fit's
# steps without deterministic ops; the fit's steps each time with scatter-adds and with
# fixed-order texel sums (`FitOptions.texel_sums`), and whether two runs agree bit for bit; ("tests") the test suite (pytest-xdist, processes
# sharing the card). "all" runs both, timing first.
set -u
out=${1:?usage: scripts/gpu_check.sh OUTDIR [SECONDS] [all|timing|tests]}
total=${2:-560}
part=${3:-all}
mkdir -p "$out"
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
py=$(command -v python3 || command -v python)
det="--xla_gpu_deterministic_ops=true"
# jaxnm.runtime.GRAPHS_FLAG: loops and conditionals in CUDA graphs
cb=$("$py" -c "from jaxnm.runtime import GRAPHS_FLAG; print(GRAPHS_FLAG)")
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

{ nvidia-smi -L; "$py" -c "import sys, jax; print(sys.version.split()[0], jax.__version__,
jax.devices())"; } 2>&1 | tee "$out/device.log"

if [[ $part != tests ]]; then
  step bench 150 env XLA_FLAGS="$det" "$py" scripts/bench.py --no-mitsuba --no-cli \
    --parts forward,fit --budget 6 --repeats 10 --out "$out/bench"
  step profile 100 env XLA_FLAGS="$det" "$py" scripts/profile_render.py --host --fit --trace \
    --texel-sums scatter,tables --repeats 20 --out "$out/profile"
  step profile_graphs 80 env XLA_FLAGS="$det $cb" "$py" scripts/profile_render.py --fit \
    --texel-sums scatter,tables --repeats 20 --out "$out/profile"
  step fit_nondeterministic 45 "$py" scripts/profile_render.py --scenes "" --fit \
    --texel-sums scatter,tables --out "$out/profile"
  echo "=== summary (timing)"
  tail -n 30 "$out/bench.log"
  for f in profile profile_graphs fit_nondeterministic; do
    echo "-- $f"; grep -h '^{' "$out/$f.log" | cut -c1-1500
  done
fi
if [[ $part != timing ]]; then
  step tests 330 "$py" -m pytest -v -n 14 -p no:benchmark -p no:cacheprovider \
    --durations=15 --junitxml "$out/junit.xml"
  echo "=== summary (tests)"
  grep -E "^(FAILED|ERROR)|passed|failed" "$out/tests.log" | grep -v '^\[gw' | tail -n 25
fi
