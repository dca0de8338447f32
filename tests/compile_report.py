"""Where the suite's time goes to XLA: an opt-in report of each test's compilations.

The suite is compile-bound (most of a test's time is XLA compiling its programs), so the way
to a quicker suite is to find the tests that compile the most. With
``JAXNM_TEST_COMPILE_REPORT=FOLDER`` set, `tests/conftest.py` loads this plugin: every test
process (each pytest-xdist worker) writes one JSON line per test to ``FOLDER/<process>.jsonl``
(the test's id, its wall time, the seconds spent in XLA's compiler and the programs it
compiled or read from the persistent cache), and the run ends with the modules and tests that
compiled the longest. The counts come from JAX's persistent compilation cache, which the suite
always uses (`tests/conftest.py`). Programs compiled in a test's subprocesses (the command
line's) are not counted; their time shows in the wall time alone.
"""

from __future__ import annotations

import collections
import json
import os
import time
from pathlib import Path

import jax.monitoring
import pytest

ENV = "JAXNM_TEST_COMPILE_REPORT"
#: JAX's monitoring events: the compiler's time (a compilation, or a read from the
#: persistent cache), and a program compiled or found in that cache.
COMPILE_SECONDS = "/jax/core/compile/backend_compile_duration"
COMPILED = "/jax/compilation_cache/cache_misses"
FROM_CACHE = "/jax/compilation_cache/cache_hits"

_seconds = collections.Counter()
_events = collections.Counter()


def _on_duration(event: str, seconds: float, **_):
    _seconds[event] += seconds


def _on_event(event: str, **_):
    _events[event] += 1


jax.monitoring.register_event_duration_secs_listener(_on_duration)
jax.monitoring.register_event_listener(_on_event)


def _folder() -> Path:
    return Path(os.environ[ENV])


def pytest_configure(config):
    """In the process that reports, before any worker starts: the previous run's lines
    go."""
    if not hasattr(config, "workerinput"):
        for path in _folder().glob("*.jsonl"):
            path.unlink()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Count one test's compilations (set-up and tear-down included) and write its line."""
    _seconds.clear()
    _events.clear()
    start = time.perf_counter()
    yield
    line = dict(test=item.nodeid, wall_s=time.perf_counter() - start,
                compile_s=_seconds[COMPILE_SECONDS], compiled=_events[COMPILED],
                from_cache=_events[FROM_CACHE])
    # (xdist's worker id from the configuration: its environment variable also reaches
    # pytest runs started by a test)
    worker = getattr(item.config, "workerinput", {}).get("workerid", "main")
    folder = _folder()
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / f"{worker}.jsonl", "a") as f:
        f.write(json.dumps(line) + "\n")


def _row(counts, name: str) -> str:
    return (f"{counts['compile_s']:10.1f} {counts['wall_s']:8.1f} {counts['compiled']:8d} "
            f"{counts['from_cache']:6d}  {name}")


def summarize(lines: list[dict], top: int = 15) -> str:
    """The report's text: totals, then the ``top`` modules and tests by compile seconds."""
    modules = collections.defaultdict(collections.Counter)
    for line in lines:
        m = modules[line["test"].split("::")[0]]
        m.update(dict(wall_s=line["wall_s"], compile_s=line["compile_s"],
                      compiled=line["compiled"], from_cache=line["from_cache"], tests=1))
    total = sum((m for m in modules.values()), collections.Counter())
    out = [f"{total['tests']} tests: {total['wall_s']:.1f} s in tests, "
           f"{total['compile_s']:.1f} s compiling; {total['compiled']} programs compiled, "
           f"{total['from_cache']} read from the persistent cache"]
    out.append(f"{'compile s':>10} {'wall s':>8} {'compiled':>8} {'cached':>6}  module")
    for name, m in sorted(modules.items(), key=lambda kv: -kv[1]["compile_s"])[:top]:
        out.append(_row(m, f"{name} ({m['tests']} tests)"))
    out.append(f"{'compile s':>10} {'wall s':>8} {'compiled':>8} {'cached':>6}  test")
    for line in sorted(lines, key=lambda t: -t["compile_s"])[:top]:
        out.append(_row(line, line["test"]))
    return "\n".join(out)


def pytest_terminal_summary(terminalreporter, config):
    """In the process that reports (pytest's, or xdist's controller): every process's lines."""
    if hasattr(config, "workerinput"):
        return
    lines = [json.loads(text) for path in sorted(_folder().glob("*.jsonl"))
             for text in path.read_text().splitlines()]
    terminalreporter.write_sep("-", f"compilations ({_folder()})")
    terminalreporter.write_line(summarize(lines) if lines else "no test ran")
