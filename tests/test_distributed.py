"""A fit across processes (`jaxnm.fit.prepare_processes`, ``jaxnm fit --distributed``): two
local processes on the CPU, joined by ``jax.distributed`` with gloo collectives.

- the loss, the gradient, the history and the fitted map equal the single-process fit's to
  float32 reduction order (the texel sums are added per process, then across processes);
- each process reads only its own views' images;
- only process 0 writes a checkpoint, and both processes resume from it to the fit an
  uninterrupted one ends with (bitwise);
- a process that dies mid-fit makes the other fail at once with one line;
- processes told another process count, or given another fit file, refuse in one line.

One pair of processes serves the equality and the resume checks; the pairs share a
compilation cache in a temporary folder. Every subprocess runs under a timeout, so a hang
fails the test instead of stalling CI."""

import json
import os
import socket
import subprocess
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnm import fit as F
from jaxnm.config import load_fit
from jaxnm.procedural import DEFAULT_FIT_EYES, default_problem

SIZE, MAP, STEPS = 32, 16, 2
TIMEOUT = 240  # seconds a pair of processes may take (a few s each when the machine is idle)
LOST_AFTER = 20  # the dying-process test's --timeout (s)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def fit_file(tmp_path_factory):
    """Three 32x32 views of the built-in torus under four lights each, as a fit file."""
    folder = tmp_path_factory.mktemp("distributed")
    problem, _, _ = default_problem(render_size=SIZE, map_size=MAP, n_lights=4, views=3)
    cam = {"target": [0, 0, 0], "up": [0, 0, 1], "fov_y_deg": 45}
    (folder / "scene.json").write_text(json.dumps({
        "mesh": "builtin:torus", "width": SIZE, "height": SIZE,
        "camera": {"eye": list(DEFAULT_FIT_EYES[0]), **cam}, "albedo": [0.85, 0.6, 0.38],
        "material": {"model": "blinn_phong", "specular": [0.15, 0.15, 0.15], "shininess": 24,
                     "ambient": [0, 0, 0]}}))
    views = [{"camera": {"eye": list(e), **cam}, "width": SIZE, "height": SIZE}
             for e in DEFAULT_FIT_EYES]
    entries = []
    for i, t in enumerate(problem.targets):
        np.save(folder / f"t{i}.npy", np.asarray(t.image, np.float32))
        d = np.asarray(t.lights.directional.direction)[0].tolist()
        entries.append({"image": f"t{i}.npy", "view": i // 4,
                        "lights": [{"type": "directional", "direction": d}]})
    fit = {"scene": "scene.json", "views": views, "targets": entries, "map": {"size": MAP},
           "solver": {"max_steps": STEPS, "lsmr_steps": 5, "ftol": 0, "rtol": 0, "atol": 0}}
    path = folder / "fit.json"
    path.write_text(json.dumps(fit))
    return path


def _start(code: str, *args, cwd=None, cache=None) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONWARNINGS="ignore")
    if cache is not None:  # the command line's compilation cache
        env["JAXNM_COMPILATION_CACHE"] = str(cache)
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], env=env, cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(procs) -> list:
    out = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=TIMEOUT)
            out.append((p.returncode, stdout, stderr))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return out


# One process of the library's fit across processes: its own views only; the loss and
# gradient at a fixed map; a fit with a checkpoint of its own; then the same fit stopped after
# one step and resumed by both processes from process 0's checkpoint. Both processes save what
# they got (process 1's arrays must be process 0's).
_PROCESS = r"""
import dataclasses, sys, warnings
import jax, jax.numpy as jnp, numpy as np
warnings.simplefilter("ignore")
path, port, me, out, cache = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.config.update("jax_compilation_cache_dir", cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
jax.distributed.initialize(f"127.0.0.1:{port}", 2, me, initialization_timeout=60,
                           heartbeat_timeout_seconds=60)
from jaxnm import fit as F
from jaxnm.config import load_fit

job = load_fit(path, images=lambda key, ts: F.process_targets(ts, 2)[me])
read = [i for i, t in enumerate(job.problem.targets) if t.image is not None]
prep = F.prepare_processes(job.problem)
assert F.spread_over_processes(prep) and prep.num_views == 3
z = jnp.asarray(np.random.default_rng(0).normal(0, 0.2, (MAP, MAP, 2)), jnp.float32)
loss, grad = jax.value_and_grad(F.loss)(z, F.ModelArgs.create(prep, reduce=True))
whole = F.fit_normal_map(job.problem, job.options, prepared=prep, progress=False,
                         checkpoint=f"{out}/own_{me}.npz", checkpoint_every=0)
shared = f"{out}/shared.npz"
F.fit_normal_map(job.problem, dataclasses.replace(job.options, max_steps=1), prepared=prep,
                 progress=False, checkpoint=shared, checkpoint_every=0)
resumed = F.fit_normal_map(job.problem, job.options, prepared=prep, progress=False,
                           checkpoint=shared, resume=True, checkpoint_every=0)
np.savez(f"{out}/process_{me}.npz", loss=np.asarray(loss), grad=np.asarray(grad),
         normals=whole.normals, history=[h["loss"] for h in whole.history],
         resumed_normals=resumed.normals, resumed_history=[h["loss"] for h in resumed.history],
         views=prep.local_views(), read=read)
print("DONE", me)
""".replace("MAP", str(MAP))


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A compilation cache shared by the subprocesses of this module (each pair compiles the
    same programs; the later ones load them)."""
    return tmp_path_factory.mktemp("xla_cache")


@pytest.fixture(scope="module")
def started(fit_file, cache, tmp_path_factory):
    """The pair of processes running `_PROCESS`, started first: the single-process
    reference is computed while they run."""
    out = tmp_path_factory.mktemp("pair")
    port = _port()
    procs = [_start(_PROCESS, fit_file, port, i, out, cache, cache=cache) for i in range(2)]
    yield procs, out
    for p in procs:  # (finished by `pair`; killed here if a fixture between failed)
        if p.poll() is None:
            p.kill()
            p.wait()


@pytest.fixture(scope="module")
def reference(fit_file, started):
    """The single-process fit of the fit file: loss and gradient at the same map, result."""
    job = load_fit(fit_file)
    prep = F.prepare(job.problem)
    z = jnp.asarray(np.random.default_rng(0).normal(0, 0.2, (MAP, MAP, 2)), jnp.float32)
    loss, grad = jax.value_and_grad(F.loss)(z, F.ModelArgs.create(prep, reduce=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", F.FitWarning)
        res = F.fit_normal_map(job.problem, job.options, prepared=prep, progress=False)
    return float(loss), np.asarray(grad), res


@pytest.fixture(scope="module")
def pair(started, reference):
    """Both processes' results (`_PROCESS`) and the folder they wrote into."""
    procs, out = started
    for rc, stdout, stderr in _finish(procs):
        assert rc == 0 and "DONE" in stdout, stderr[-3000:]
    return [dict(np.load(out / f"process_{i}.npz")) for i in range(2)], out


def test_fit_across_two_processes_equals_the_single_process_fit(pair, reference):
    (got, other), _ = pair
    loss, grad, res = reference
    # views dealt round-robin: process 0 holds views 0 and 2 (targets 0-3 and 8-11) and read
    # only their images
    assert got["views"].tolist() == [0, 2] and other["views"].tolist() == [1]
    assert got["read"].tolist() == [0, 1, 2, 3, 8, 9, 10, 11]
    assert other["read"].tolist() == [4, 5, 6, 7]
    # to float32 reduction order: each process sums its views' texel terms, then gloo adds
    # the two; one process adds all of them in another order
    np.testing.assert_allclose(float(got["loss"]), loss, rtol=2e-6)
    np.testing.assert_allclose(got["grad"], grad, rtol=0, atol=2e-5 * np.abs(grad).max())
    hist = [h["loss"] for h in res.history]
    assert len(got["history"]) == len(hist) == STEPS + 1
    # (the last losses are 1e-4 of the first: their rounding is the sums' over larger terms)
    np.testing.assert_allclose(got["history"], hist, rtol=1e-5, atol=1e-7 * hist[0])
    np.testing.assert_allclose(got["normals"], res.normals, rtol=0, atol=2e-5)
    # the fit moved (the comparison is not of two starting maps)
    assert hist[-1] < 0.5 * hist[0]
    # one SPMD program: both processes hold the same numbers
    for key in ("loss", "grad", "normals", "history"):
        np.testing.assert_array_equal(other[key], got[key])


def test_process_0_writes_the_checkpoints_and_both_processes_resume_from_them(pair):
    (got, other), out = pair
    assert (out / "own_0.npz").is_file() and not (out / "own_1.npz").exists()
    saved = F.load_checkpoint(out / "own_0.npz")
    assert saved.meta["next_step"] == STEPS + 1
    np.testing.assert_array_equal(saved.meta["history"][-1]["loss"], got["history"][-1])
    # stopped after one step and resumed by both processes from process 0's file: the fit an
    # uninterrupted one ends with, bitwise on the CPU
    for p in (got, other):
        np.testing.assert_array_equal(p["resumed_history"], got["history"])
        np.testing.assert_array_equal(p["resumed_normals"], got["normals"])


def _cli(fit_file, port, me, count=2, *extra, timeout=60):
    return ["fit", str(fit_file), "--distributed", "--coordinator",
            f"127.0.0.1:{port}", "--num-processes", str(count), "--process-id", str(me),
            "--timeout", str(timeout), "--no-progress", *map(str, extra)]


def _start_cli(args, cwd, cache, dies_after_step: int | None = None) -> subprocess.Popen:
    """``jaxnm ARGS`` in ``cwd``; with ``dies_after_step``, the process ends itself (exit
    code 7, no clean-up) once that step is taken."""
    code = "import sys; from jaxnm.cli import main; sys.exit(main(sys.argv[1:]))"
    if dies_after_step is not None:
        code = ("import os, jaxnm.fit.stopping as S\n"
                "test = S.stop_test\n"
                "def stop_test(records, *a, **k):\n"
                f"    if records[-1]['step'] >= {dies_after_step}:\n"
                "        os._exit(7)\n"
                "    return test(records, *a, **k)\n"
                "S.stop_test = stop_test\n") + code.replace("; ", "\n")
    return _start(code, *args, cwd=cwd, cache=cache)


def _last_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("[Gloo]")]
    return lines[-1] if lines else ""


def test_a_process_that_dies_mid_fit_stops_the_other_with_one_line(fit_file, cache, tmp_path):
    port = _port()
    (tmp_path / "p0").mkdir()
    (tmp_path / "p1").mkdir()
    # (the coordination service notices the lost process when its heartbeat is --timeout late)
    a = _start_cli(_cli(fit_file, port, 0, 2, "-o", "out", "--checkpoint-every", 0.001,
                        timeout=LOST_AFTER), tmp_path / "p0", cache)
    b = _start_cli(_cli(fit_file, port, 1, 2, "-o", "out", "--checkpoint-every", 0.001,
                        timeout=LOST_AFTER), tmp_path / "p1", cache, dies_after_step=1)
    t = time.perf_counter()
    (rc0, _, err0), (rc1, _, err1) = _finish([a, b])
    assert time.perf_counter() - t < TIMEOUT / 2  # not a hang cut short by _finish
    assert rc1 == 7, err1[-3000:]
    assert rc0 == 1, err0[-3000:]
    assert "Traceback" not in err0
    line = _last_line(err0)
    assert line.startswith("jaxnm fit: error: process 0 of 2: lost another process"), err0
    assert err0.count("jaxnm fit: error") == 1
    # process 0 had written the checkpoint of the step before; process 1 wrote nothing
    assert (tmp_path / "p0" / "out" / "checkpoint.npz").is_file()
    assert not (tmp_path / "p1" / "out").exists()


def test_processes_refuse_another_count_or_another_fit_file_in_one_line(fit_file, cache,
                                                                        tmp_path):
    other = fit_file.parent / "other.json"
    data = json.loads(fit_file.read_text())
    data["solver"]["max_steps"] = STEPS + 1
    other.write_text(json.dumps(data))
    port, port2 = _port(), _port()
    procs = [_start_cli(_cli(fit_file, port, 0, 2, "-o", tmp_path / "a"), tmp_path, cache),
             _start_cli(_cli(fit_file, port, 1, 3, "-o", tmp_path / "a"), tmp_path, cache),
             _start_cli(_cli(fit_file, port2, 0, 2, "-o", tmp_path / "b"), tmp_path, cache),
             _start_cli(_cli(other, port2, 1, 2, "-o", tmp_path / "b"), tmp_path, cache)]
    results = _finish(procs)
    for (rc, _, err), what in zip(results, ["the process count"] * 2 + ["the fit file"] * 2):
        assert rc == 2, err[-3000:]
        line = _last_line(err)
        assert line.startswith("jaxnm fit: error: process "), err
        assert f"jaxnm fit --distributed: process 1 has {what}" in line, line
        assert "Traceback" not in err and err.count("jaxnm fit: error") == 1
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_process_that_cannot_reach_or_name_its_coordinator_stops_in_one_line(fit_file, cache,
                                                                              tmp_path):
    """Without process 0 listening, process 1 gives up after --timeout with one line (JAX's
    own wait ended the process with a fatal error and a native stack trace); a malformed
    address, a process count of 0, and --distributed with no cluster to detect are named
    before anything starts."""
    port = _port()  # nobody listens
    scheduled = any(k.startswith(("SLURM_", "OMPI_", "PMI_")) for k in os.environ)
    procs = [_start_cli(_cli(fit_file, port, 1, 2, timeout=2), tmp_path, cache),
             _start_cli(["fit", str(fit_file), "--distributed", "--coordinator", "nope",
                         "--num-processes", "2", "--process-id", "0"], tmp_path, cache),
             _start_cli(_cli(fit_file, port, 0, 0), tmp_path, cache)]
    if not scheduled:  # (a scheduler's variables would be detected as a cluster)
        procs.append(_start_cli(["fit", str(fit_file), "--distributed"], tmp_path, cache))
    results = _finish(procs)
    expected = [(1, f"could not reach the coordinator 127.0.0.1:{port} within 2 s ("),
                (2, "--coordinator must be HOST:PORT (process 0's address and a free port, 1 "
                    "to 65535), got 'nope'"),
                (2, "--num-processes must be at least 1, got 0"),
                (2, "--distributed: no cluster was detected to join (SLURM, Open MPI, a cloud "
                    "cluster); give --coordinator HOST:PORT, --num-processes N and "
                    "--process-id I")]
    for (rc, _, err), (code, message) in zip(results, expected):
        assert rc == code, err[-3000:]
        assert _last_line(err).startswith(f"jaxnm fit: error: {message}"), err[-3000:]
        assert "Traceback" not in err and "stack trace" not in err
    assert not (tmp_path / "fit_out").exists()

