"""Shared test configuration: strict JAX numerics, small scenes, optional GL."""

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# hermetic: the CLI tests must not read or fill the user's persistent compilation cache
os.environ["JAXNM_COMPILATION_CACHE"] = "off"
# reproducible on a GPU too (fixed-order scatter-adds; a no-op on the CPU)
if "--xla_gpu_deterministic_ops=true" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_gpu_deterministic_ops=true").strip()
# The suite is compile-bound: with XLA's LLVM backend at optimisation level 0 its programs
# compile in about two thirds of the time (the whole suite: 19.3 -> 14.7 min on 2 cores) and
# compute the same values (neither level allows value-changing rewrites; the GLSL and
# bitwise-resume tests pass at both). JAXNM_TEST_XLA_OPTIMIZED=1 keeps XLA's default level,
# the one users run; .ci/run runs the suite both ways.
if (os.environ.get("JAXNM_TEST_XLA_OPTIMIZED") != "1"
        and "--xla_backend_optimization_level" not in os.environ["XLA_FLAGS"]):
    os.environ["XLA_FLAGS"] += " --xla_backend_optimization_level=0"

import jax  # noqa: E402

jax.config.update("jax_numpy_rank_promotion", "raise")

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# Deterministic property tests: the same examples on every run and in CI.
settings.register_profile("jaxnm", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("jaxnm")


def pytest_configure(config):
    """With ``JAXNM_REQUIRE_GL=1`` (set by .ci/run) the GLSL comparison must run: a missing
    OpenGL 4.5 context is an error instead of a skip."""
    if os.environ.get("JAXNM_REQUIRE_GL") != "1":
        return
    from glref import gl_available  # tests/ is on sys.path: pytest put it there for conftest

    ok, why = gl_available()
    if not ok:
        raise pytest.UsageError(f"JAXNM_REQUIRE_GL=1 but no OpenGL 4.5 context: {why}")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop every compiled executable after each test module. XLA's CPU backend maps each
    executable's code into its own memory regions and never returns them while the jit
    caches hold it; over the whole suite one process passed Linux's ``vm.max_map_count``
    (65530 regions) and the next compile segfaulted inside LLVM. Shared fixtures are
    module-scoped, so this costs only the recompiles of the few functions several modules
    call."""
    yield
    import gc

    jax.clear_caches()
    gc.collect()
