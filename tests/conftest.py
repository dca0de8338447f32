"""Shared test configuration: strict JAX numerics, small scenes, optional GL."""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# reproducible on a GPU too (fixed-order scatter-adds; a no-op on the CPU)
if "--xla_gpu_deterministic_ops=true" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_gpu_deterministic_ops=true").strip()

# The suite is compile-bound, and many programs recur: in other test modules (each module
# drops its compiled code, see `_release_compiled_code`), in the other pytest-xdist worker,
# and in the command-line subprocesses. One run compiles each program once: JAX's persistent
# compilation cache, in a temporary folder that the first process (pytest's controller)
# makes and removes, and that the workers and the command line (JAXNM_COMPILATION_CACHE)
# share. Hermetic: the user's own cache is neither read nor filled.
_CACHE_ENV = "JAXNM_TEST_COMPILATION_CACHE"
if _CACHE_ENV not in os.environ:
    os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxnm-test-xla-")
    atexit.register(shutil.rmtree, os.environ[_CACHE_ENV], ignore_errors=True)
os.environ["JAXNM_COMPILATION_CACHE"] = os.environ[_CACHE_ENV]

import jax  # noqa: E402

jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_ENV])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# Deterministic property tests: the same examples on every run and in CI.
settings.register_profile("jaxnm", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("jaxnm")


def pytest_configure(config):
    """With ``JAXNM_TEST_COMPILE_REPORT=FOLDER``, report each test's compilations
    (`compile_report`). With ``JAXNM_REQUIRE_GL=1`` (set by .ci/run) the GLSL comparison
    must run: a missing OpenGL 4.5 context is an error instead of a skip."""
    if os.environ.get("JAXNM_TEST_COMPILE_REPORT"):  # tests/compile_report.py
        config.pluginmanager.import_plugin("compile_report")
    if os.environ.get("JAXNM_REQUIRE_GL") != "1":
        return
    from glref import gl_available  # tests/ is on sys.path: pytest put it there for conftest

    ok, why = gl_available()
    if not ok:
        raise pytest.UsageError(f"JAXNM_REQUIRE_GL=1 but no OpenGL 4.5 context: {why}")


def _mapped_regions() -> int | None:
    """How many memory regions this process has mapped (Linux), else None."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


def _region_budget() -> int:
    """The mapped regions past which the compiled code is dropped: 60 % of Linux's
    ``vm.max_map_count``, which leaves room for the programs of the next test (one frame
    program maps about 700 regions)."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(0.6 * int(f.read()))
    except (OSError, ValueError):
        return 39000


_REGION_BUDGET = _region_budget()


@pytest.fixture(autouse=True)
def _release_compiled_code():
    """Drop every compiled executable once the process maps many memory regions. XLA's CPU
    backend maps each executable's code into its own regions and never returns them while
    the jit caches hold it; over the whole suite one process passed Linux's
    ``vm.max_map_count`` (65530 regions) and the next compile segfaulted inside LLVM.
    Checked after every test, so that a test adds at most its own programs past the budget;
    dropped only when needed, because the tests of one module and of the next share many
    programs (dropped after every module instead, ten rendering modules took 5-11 % longer
    in two paired runs on a 2-core Xeon, ``pytest -n 2``). Where the regions cannot be
    counted (no ``/proc``: not Linux, whose limit this is), nothing is dropped."""
    yield
    regions = _mapped_regions()
    if regions is None or regions < _REGION_BUDGET:
        return
    import gc

    jax.clear_caches()
    gc.collect()
