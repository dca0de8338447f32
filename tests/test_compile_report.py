"""The suite's opt-in compile report (`tests/compile_report.py`) counts what JAX compiled in
each test, and orders modules and tests by compile time."""

import json
import os
import subprocess
import sys
from pathlib import Path

import compile_report as R  # tests/ is on sys.path (pytest put it there for conftest)

INNER = '''
import jax, jax.numpy as jnp

def test_compiles_two_programs():
    x = jnp.arange(7.0)
    assert float(jax.jit(lambda v: jnp.sin(v) * 3.0)(x).sum()) != 0
    assert float(jax.jit(lambda v: jnp.cumsum(v)[-1])(x)) == 21.0

def test_compiles_nothing():
    assert sum(range(4)) == 6
'''


def test_summarize_orders_modules_and_tests_by_compile_time():
    lines = [dict(test="tests/test_a.py::one", wall_s=3.0, compile_s=2.0, compiled=4,
                  from_cache=1),
             dict(test="tests/test_a.py::two", wall_s=1.0, compile_s=0.5, compiled=1,
                  from_cache=0),
             dict(test="tests/test_b.py::three", wall_s=4.0, compile_s=3.0, compiled=2,
                  from_cache=5)]
    text = R.summarize(lines, top=2).splitlines()
    assert text[0] == ("3 tests: 8.0 s in tests, 5.5 s compiling; 7 programs compiled, "
                       "6 read from the persistent cache")
    modules = text[2:4]  # test_b (3.0 s) before test_a (2.5 s)
    assert modules[0].split() == ["3.0", "4.0", "2", "5", "tests/test_b.py", "(1", "tests)"]
    assert modules[1].split() == ["2.5", "4.0", "5", "1", "tests/test_a.py", "(2", "tests)"]
    tests = text[5:]  # the two longest only
    assert [t.split()[-1] for t in tests] == ["tests/test_b.py::three", "tests/test_a.py::one"]


def test_a_run_writes_each_tests_compilations(tmp_path):
    (tmp_path / "test_inner.py").write_text(INNER)
    report = tmp_path / "report"
    report.mkdir()
    (report / "stale.jsonl").write_text('{"test": "from an earlier run"}\n')
    env = dict(os.environ, JAXNM_TEST_COMPILE_REPORT=str(report), JAX_PLATFORMS="cpu",
               PYTHONPATH=str(Path(__file__).parent),
               JAX_COMPILATION_CACHE_DIR=str(tmp_path / "cache"),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          "-p", "compile_report", "-p", "no:xdist", "test_inner.py"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert [p.name for p in report.iterdir()] == ["main.jsonl"]
    lines = {r["test"]: r for r in map(json.loads, (report / "main.jsonl").read_text()
                                       .splitlines())}
    two, none = lines["test_inner.py::test_compiles_two_programs"], lines[
        "test_inner.py::test_compiles_nothing"]
    # each jit compiles its program, and JAX's own small programs (arange, sum) besides
    assert two["compiled"] >= 2 and two["compile_s"] > 0 and two["from_cache"] == 0
    assert none["compiled"] == 0 and none["compile_s"] == 0
    assert "compilations (" in out.stdout and "test_inner.py (2 tests)" in out.stdout
