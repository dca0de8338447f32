#!/usr/bin/env bash
# Every GPU goal of jaxnm in one run of at most 8 minutes, on a machine with one NVIDIA GPU
# and no network: render frames (the 20k torus at 512^2, the 200k torus at 1024^2, 64 views
# of the 20k torus at 512^2 through jax.vmap), the benchmark fit (its LM step and the time to
# 1 degree, cold and warm: scripts/benchmarks/bench.py --parts fit), then the GPU-relevant
# tests. Prints one JSON object (card, driver, JAX version, date, figures) and writes it and
# the logs under ${OUT:-gpu_check_out}.
#
#     bash scripts/benchmarks/gpu_check.sh [--quick]
#
# (from the repository root; --quick: small sizes, a smoke test of the script that runs on
# the CPU too, JAX_PLATFORMS=cpu; its figures mean nothing).
#
# Packages: the GPU machine has no network. JAX with CUDA must be importable there. If the
# environment carried to it lacks them, put the wheels in a git-ignored folder `gpu_wheels/`
# at the repository root on the machine that has a network (for example
# `pip download "jax[cuda12]==<the jax version here>" -d gpu_wheels`; never commit them) and
# name that folder (and the virtual environment, if it travels) in the device tool's `carry`;
# this script then installs them from there with `pip install --no-index --find-links`.
# XLA's deterministic GPU ops are on, as the command line and the test suite set them.
set -euo pipefail
cd "$(dirname "$0")/../.."
QUICK=""
[[ "${1:-}" == "--quick" ]] && QUICK="--quick"
OUT="${OUT:-gpu_check_out}"
mkdir -p "$OUT"
PY="${PYTHON:-python}"
export XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_deterministic_ops=true"
export XLA_PYTHON_CLIENT_PREALLOCATE=false
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
deadline=$((SECONDS + 470))

if [[ -d gpu_wheels ]] && ! "$PY" -c "import jax; assert jax.default_backend() == 'gpu'" 2>/dev/null; then
  "$PY" -m pip install -q --no-index --find-links gpu_wheels "jax[cuda12]" \
    || "$PY" -m pip install -q --no-index --find-links gpu_wheels "jax[cuda13]"
fi
driver="$(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | head -1 || true)"

# 1. frames (about a minute on a GPU)
timeout $((deadline - SECONDS)) "$PY" -m scripts.benchmarks.gpu_check $QUICK \
  --out "$OUT/frames.json" > "$OUT/frames.log" 2>&1 || echo "frames: exit $?" >> "$OUT/errors.txt"

# 2. the benchmark fit, cold (empty compilation cache) and warm, and its steady LM step
budget=10; [[ -n "$QUICK" ]] && budget=3
timeout $((deadline - SECONDS - 150)) "$PY" -m scripts.benchmarks.bench --parts fit \
  --no-mitsuba --no-cli --budget "$budget" $QUICK --out "$OUT/fit" > "$OUT/fit.log" 2>&1 \
  || echo "fit: exit $?" >> "$OUT/errors.txt"

# 3. the GPU-relevant tests, in the time left
tests="tests/test_resident.py tests/test_render.py tests/test_raster.py tests/test_precision.py"
[[ -n "$QUICK" ]] && tests="tests/test_resident.py -k report_can_fail"
left=$((deadline - SECONDS)); (( left < 30 )) && left=30
set +e
timeout "$left" "$PY" -m pytest -q -x -p no:cacheprovider $tests > "$OUT/tests.log" 2>&1
rc=$?
set -e

"$PY" - "$OUT" "$driver" "$rc" <<'PYEOF'
import json, os, sys
out, driver, rc = sys.argv[1], sys.argv[2], int(sys.argv[3])
def load(path):
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        return {"error": f"{path}: {e}"}
frames = load(os.path.join(out, "frames.json"))
fit = load(os.path.join(out, "fit", "bench.json")).get("fit", {}).get("jaxnm", {})
pick = ("time_to_1deg_s", "s_per_step", "first_loss_s", "backend_compile_s")
tail = open(os.path.join(out, "tests.log")).read().strip().splitlines()[-1:] if \
    os.path.exists(os.path.join(out, "tests.log")) else []
res = {"metadata": {**frames.get("metadata", {}), "driver": driver},
       "frames": frames.get("frames", frames),
       "fit": {k: {p: v.get(p) for p in pick} for k, v in fit.items() if isinstance(v, dict)},
       "fit_goals": {"lm_step_ms": 2.0, "time_to_1deg_cold_s": 3.0, "time_to_1deg_warm_s": 0.8},
       "tests": {"exit": rc, "summary": tail[0] if tail else None}}
if os.path.exists(os.path.join(out, "errors.txt")):
    res["errors"] = open(os.path.join(out, "errors.txt")).read().split("\n")[:-1]
with open(os.path.join(out, "gpu_check.json"), "w") as f:
    json.dump(res, f, indent=1)
print(json.dumps(res, indent=1))
PYEOF
