"""A fit that stops only when it is done and loses nothing when it is stopped: the stopping
rule on starts where the solvers hold their first steps back, checkpoints and resumed fits
(bitwise equal to uninterrupted ones), Ctrl-C during ``jaxnm fit`` and while it writes its
outputs, refused resumes, and atomic files."""

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm.fit.solve as S
import jaxnm.fit.stopping as T
from jaxnm import fit as F
from jaxnm.cli import _interrupt as cli_interrupt
from jaxnm.cli import main
from jaxnm.cli._fit import CHECKPOINT_NAME as _CHECKPOINT_NAME
from jaxnm.fit.report import stopped_in_words
from jaxnm.fit.texel_lm import TexelLM
from jaxnm.io import atomic_write, load_texture
from jaxnm.procedural import default_problem

_COMPILED: list = []
_LISTENING = [False]


def _on_compile(name, seconds, **kwargs):
    if _LISTENING[0] and name == "/jax/core/compile/backend_compile_duration":
        _COMPILED.append(kwargs.get("fun_name", "?"))


jax.monitoring.register_event_duration_secs_listener(_on_compile)  # (0.8.0: cannot unregister)


@pytest.fixture(scope="module")
def small():
    """The built-in problem, small: 64x64 renders, a 16x16 map, 6 lights, 2 views."""
    problem, gt, _ = default_problem(render_size=64, map_size=16, n_lights=6, views=2)
    return problem, gt, F.prepare(problem)


def _losses(res) -> list:
    return [h["loss"] for h in res.history]


# ----------------------------------------------------------------------------- stopping


def _old_rule(losses: list, ftol: float = 1e-3, patience: int = 3) -> int | None:
    """The step at which the previous rule (the loss fell by less than ``ftol`` over the
    last ``patience`` steps, whatever the steps) stopped a fit, or None."""
    for k in range(patience, len(losses)):
        before = losses[k - patience]
        if before - losses[k] <= ftol * abs(before):
            return k
    return None


def _dimmed(problem, c: float):
    """``problem`` with every light and target ``c`` times as bright: the same answer, the
    residuals times ``c``, the Gauss-Newton curvature times ``c**2``."""
    targets = []
    for t in problem.targets:
        d = t.lights.directional
        lights = dataclasses.replace(t.lights, directional=dataclasses.replace(
            d, intensity=d.intensity * c))
        targets.append(dataclasses.replace(t, lights=lights,
                                           image=np.asarray(t.image) * np.float32(c)))
    return dataclasses.replace(problem, targets=tuple(targets))


def _damped_start(solver: str, problem, monkeypatch):
    """``problem`` (or a variant) set up so that ``solver``'s first steps are held back.

    - lm: the problem 1000 times dimmer. optimistix's Levenberg-Marquardt starts at damping
      1 whatever the problem's scale, here a million times its curvature: gradient steps
      that barely move the loss.
    - lm-texel: its first damping (`TexelLM.lam0`) 1e6 times the curvature instead of 0.1.
    - lbfgs: the flat start. Its first trial step (the gradient, unscaled) is far too long,
      and the backtracking line search halves it four times, keeping the loss.
    - gn: a steep start (slopes (-4, -2) everywhere). Gauss-Newton takes every step, and
      its first ones raise the loss.
    """
    if solver == "lm":
        return _dimmed(problem, 1e-3)
    if solver == "lm-texel":
        monkeypatch.setattr(S, "make_solver", lambda o: TexelLM(
            cg_steps=o.lsmr_steps, rtol=o.rtol, atol=o.atol, lam0=1e6))
    if solver == "gn":
        monkeypatch.setattr(S, "_start_slopes", lambda size, o: np.broadcast_to(
            np.float32([-4.0, -2.0]), tuple(size) + (2,)).copy())
    return problem


@pytest.mark.parametrize("solver", F.SOLVERS)
def test_a_held_back_start_is_not_taken_for_convergence(small, solver, monkeypatch):
    """On a start where the solver holds its first steps back (or, Gauss-Newton, raises the
    loss), the previous rule stopped the fit within 3 steps with nothing gained; the new
    one goes on to a loss far below the start."""
    problem, _, _ = small
    problem = _damped_start(solver, problem, monkeypatch)
    prep = F.prepare(problem)
    res = F.fit_normal_map(problem, F.FitOptions(solver=solver, max_steps=25), prepared=prep,
                           progress=False)
    loss = _losses(res)
    first = res.history[1:4]
    # the start is what it claims: held back, rejected, or uphill
    assert all(h["damping"] > 0.5 or not h["accepted"] or h["loss"] > loss[0] for h in first)
    old = _old_rule(loss)
    assert old is not None and old <= 3, old  # the previous rule would have stopped here,
    assert loss[old] > 0.9 * loss[0]  # with nothing gained
    assert len(res.history) - 1 > old + 10  # the new one went on
    assert res.best_loss < (0.3 if solver == "gn" else 1e-3) * loss[0]
    assert res.stopped in ("converged", "max_steps"), res.stopped
    if res.stopped == "converged":  # it stopped when it was done
        assert res.stop_test in ("ftol", "solver_tolerance")
        assert res.best_loss < 1e-6 * loss[0]


def test_stops_when_done_and_says_which_test_stopped_it(small):
    """A plain fit stops by the ``ftol`` test well before ``max_steps``, at the float32
    floor of its loss, and the rule holds on the recorded history."""
    problem, _, prep = small
    opts = F.FitOptions(max_steps=60)
    res = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
    assert res.stopped == "converged" and res.stop_test in F.STOP_TESTS
    assert len(res.history) - 1 < 40
    assert res.best_loss < 1e-6 * res.history[0]["loss"]
    if res.stop_test == "ftol":
        floor = res.noise_floor / res.history[0]["loss"]  # (relative to the start: tiny)
        assert floor < 1e-3
        assert T.stop_test(res.history, opts, lambda x: T.noise_floor(
            x, *T.loss_terms(prep))) == "ftol"
        assert T.stop_test(res.history[:-1], opts, lambda x: T.noise_floor(
            x, *T.loss_terms(prep))) is None


def test_a_fit_that_cannot_improve_says_it_made_no_progress(small):
    """Targets rendered from the flat start itself: the start is the answer, the loss is
    at its rounding from the first step, and the fit says it made no progress."""
    problem, _, prep = small
    flat = np.zeros((16, 16, 3), np.float32)
    flat[..., 2] = 1
    images = [np.asarray(im) for v in F.render_with_map(prep, jnp.asarray(flat)) for im in v]
    done = dataclasses.replace(problem, targets=tuple(
        dataclasses.replace(t, image=im) for t, im in zip(problem.targets, images, strict=True)))
    res = F.fit_normal_map(done, F.FitOptions(solver="lm", max_steps=20),
                           prepared=F.prepare(done), progress=False)
    assert res.stopped == "no_progress" and res.stop_test in ("ftol", "solver_tolerance")
    assert len(res.history) - 1 < 20
    assert not res.best_loss < res.history[0]["loss"] - res.noise_floor


# ----------------------------------------------------------------------------- resume


@pytest.mark.parametrize("solver,levels", [("lm-texel", 0), ("lm", 1), ("gn", 0),
                                           ("lbfgs", 0)])
def test_a_resumed_fit_is_the_uninterrupted_fit(small, solver, levels, tmp_path):
    """Stopped after step 3 of its last level (a checkpoint after every step), then resumed
    from the checkpoint: the same losses from the resumed step on and the same map, bitwise,
    as the fit that ran through; so is a checkpoint written part-way (every step), and a
    resumed finished fit is the finished fit without a step. The resumed fit runs the step
    the first fit compiled: the saved solver state has the fresh state's types (weak-typed
    scalars included)."""
    problem, gt, prep = small
    opts = F.FitOptions(solver=solver, max_steps=7, ftol=0.0, coarse_to_fine=levels,
                        init_noise=0.05, seed=3)  # (the other tests' compiled steps)
    kw = dict(prepared=prep, progress=False, ground_truth=gt)
    ref = F.fit_normal_map(problem, opts, **kw)
    ck = tmp_path / "fit.npz"
    part = F.fit_normal_map(problem, opts, checkpoint=ck, checkpoint_every=0.0,
                            should_stop=lambda rec: rec["level"] == levels and rec["step"] == 3,
                            **kw)
    assert part.stopped == "interrupted" and part.stop_test == "should_stop"
    assert len(part.history) < len(ref.history)
    _COMPILED.clear()
    _LISTENING[0] = True
    try:
        res = F.fit_normal_map(problem, opts, checkpoint=ck, resume=True, **kw)
    finally:
        _LISTENING[0] = False
    assert not [f for f in _COMPILED if "_step" in f], _COMPILED
    assert res.stopped == ref.stopped == "max_steps"
    keys = ("level", "step", "loss", "accepted", "damping", "predicted",
            "mean_angular_error_deg")
    strip = lambda hist: [{k: h.get(k) for k in keys} for h in hist]  # noqa: E731
    assert strip(res.history) == strip(ref.history)
    np.testing.assert_array_equal(res.slopes, ref.slopes)
    np.testing.assert_array_equal(res.normals, ref.normals)
    assert res.best_loss == ref.best_loss
    again = F.fit_normal_map(problem, opts, resume=ck, **kw)  # the final checkpoint
    np.testing.assert_array_equal(again.slopes, ref.slopes)
    assert strip(again.history) == strip(ref.history)


def test_resuming_with_more_steps_continues_the_fit(small, tmp_path):
    """A fit that ran out of steps, resumed with more, is the fit run with more from the
    start (the stopping rule's settings may change between the two)."""
    problem, _, prep = small
    short = F.FitOptions(max_steps=4, ftol=0.0)
    longer = dataclasses.replace(short, max_steps=9)
    ck = tmp_path / "fit.npz"
    F.fit_normal_map(problem, short, prepared=prep, progress=False, checkpoint=ck)
    res = F.fit_normal_map(problem, longer, prepared=prep, progress=False, checkpoint=ck,
                           resume=True)
    ref = F.fit_normal_map(problem, longer, prepared=prep, progress=False)
    assert _losses(res) == _losses(ref) and len(res.history) == 10
    np.testing.assert_array_equal(res.slopes, ref.slopes)


def test_resuming_with_fewer_steps_returns_the_checkpoint_and_says_so(small, tmp_path):
    """A checkpoint already past the step limit is the result, with no step taken, and the
    words for its stop say so, not that it reached the limit."""
    problem, _, prep = small
    opts = F.FitOptions(max_steps=3, ftol=0.0)
    ck = tmp_path / "fit.npz"
    ref = F.fit_normal_map(problem, opts, prepared=prep, progress=False, checkpoint=ck)
    fewer = dataclasses.replace(opts, max_steps=2)
    res = F.fit_normal_map(problem, fewer, prepared=prep, progress=False, resume=ck)
    np.testing.assert_array_equal(res.slopes, ref.slopes)
    assert _losses(res) == _losses(ref)
    assert stopped_in_words(res, fewer) == "was resumed past the step limit (2 steps)"
    assert stopped_in_words(ref, opts) == "reached the step limit (3 steps)"


def test_no_checkpoint_unless_asked(small, tmp_path, monkeypatch):
    problem, _, prep = small
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(S, "save_checkpoint", lambda *a: pytest.fail("a checkpoint"))
    F.fit_normal_map(problem, F.FitOptions(max_steps=2), prepared=prep, progress=False,
                     should_stop=lambda rec: rec["step"] == 1)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- the CLI


def _fit_file(folder, *, map_size=16, solver="lm", scale=1.0, max_steps=6, held_out=True):
    """A small fit file in ``folder``: the built-in torus seen by one 64x64 camera under six
    lights (targets saved as .npy, ``scale`` times as bright), a held-out seventh."""
    problem, _, _ = default_problem(render_size=64, map_size=16, n_lights=7, views=1)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.json").write_text(json.dumps({
        "mesh": "builtin:torus", "width": 64, "height": 64,
        "camera": {"eye": [0.0, -2.35, 1.75], "target": [0, 0, 0], "up": [0, 0, 1],
                   "fov_y_deg": 45},
        "albedo": [0.85, 0.6, 0.38],
        "material": {"model": "blinn_phong", "specular": [0.15, 0.15, 0.15], "shininess": 24,
                     "ambient": [0, 0, 0]}}))
    entries = []
    for i, t in enumerate(problem.targets):
        np.save(folder / f"t{i}.npy", np.asarray(t.image, np.float32) * np.float32(scale))
        d = np.asarray(t.lights.directional.direction)[0].tolist()
        entries.append({"image": f"t{i}.npy", "lights": [{"type": "directional",
                                                          "direction": d}]})
    fit = {"scene": "scene.json", "targets": entries[:6], "map": {"size": map_size},
           "solver": {"method": solver, "max_steps": max_steps, "lsmr_steps": 10,
                      "ftol": 0, "rtol": 0, "atol": 0}}
    if held_out:
        fit["held_out"] = entries[6:]
    path = folder / "fit.json"
    path.write_text(json.dumps(fit))
    return path


def _run(*args) -> int:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", F.FitWarning)
        return main(["fit", *map(str, args), "--no-progress"])


def _readable(out) -> dict:
    """Read back ``out``'s map (PNG and npz) and report; fail on leftover temporary files."""
    assert not [p.name for p in out.iterdir() if p.name.endswith(".tmp")]
    texels, bits = load_texture(out / "normal_map.png", channels=3)
    with np.load(out / "normal_map.npz") as z:
        normals = z["normals"]
    assert texels.shape == normals.shape and np.isfinite(normals).all()
    return json.loads((out / "report.json").read_text())


@pytest.fixture
def sigint():
    """SIGINT handled by Python while the test runs (it is ignored in background jobs)."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def test_ctrl_c_while_writing_keeps_the_map_and_the_report(tmp_path, monkeypatch, sigint):
    """Ctrl-C while the held-out light is scored: the map and the report are written
    (readable, no temporary files), the report says the writing was interrupted and what it
    left out, the exit code is 130 and the previous handler is back."""
    path = _fit_file(tmp_path / "job")
    score = F.score_held_out

    def interrupted(*a, **k):
        signal.raise_signal(signal.SIGINT)
        return score(*a, **k)

    monkeypatch.setattr(F, "score_held_out", interrupted)
    out = tmp_path / "out"
    assert _run(path, "-o", out) == 130
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    rep = _readable(out)
    assert rep["interrupted"] is True and rep["interrupted_phase"] == "writing"
    assert rep["stopped"] == "max_steps" and rep["steps"] == 6  # the fit itself was not
    assert rep["skipped"] == ["renders", "loss_plot"] and "pending" not in rep
    assert "held_out" in rep  # (scored: the Ctrl-C came while it was)
    assert not (out / "render_00.png").exists() and not (out / "loss.png").exists()


def test_a_second_ctrl_c_stops_at_once_leaving_whole_files(tmp_path, monkeypatch, sigint):
    """Two Ctrl-C while the held-out light is scored: the command stops at once (130, its
    process ended by ``os._exit``, here ``sys.exit``); what it wrote before is whole — the
    map, and a report that lists what was still pending."""
    path = _fit_file(tmp_path / "job")

    def interrupted(*a, **k):
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)
        pytest.fail("not stopped")

    monkeypatch.setattr(F, "score_held_out", interrupted)
    monkeypatch.setattr(cli_interrupt, "hard_exit", sys.exit)
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as stop:
        _run(path, "-o", out)
    assert stop.value.code == 130
    rep = _readable(out)
    assert rep["pending"] == ["held_out", "renders", "loss_plot"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_ctrl_c_during_the_fit_then_resume(tmp_path, monkeypatch, sigint):
    """Ctrl-C after the fit's second step: the fit stops after that step, the map and the
    report are written (interrupted during the fit, optional outputs skipped) with a
    checkpoint; ``--resume`` then ends with the map of a fit that ran through, bitwise."""
    path = _fit_file(tmp_path / "job")
    ref = tmp_path / "ref"
    assert _run(path, "-o", ref, "--checkpoint-every", "0") == 0
    assert not (ref / _CHECKPOINT_NAME).exists() and (ref / "render_00.png").exists()
    update = S._Progress.update

    def interrupted(self, rec):
        update(self, rec)
        if rec["step"] == 2:
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(S._Progress, "update", interrupted)
    out = tmp_path / "out"
    assert _run(path, "-o", out) == 130
    rep = _readable(out)
    assert rep["stopped"] == "interrupted" and rep["stop_test"] == "should_stop"
    assert rep["interrupted"] is True and rep["interrupted_phase"] == "fit"
    assert rep["steps"] == 2 and rep["skipped"] == ["held_out", "renders", "loss_plot"]
    assert (out / _CHECKPOINT_NAME).exists()
    monkeypatch.setattr(S._Progress, "update", update)
    assert _run(path, "-o", out, "--resume") == 0
    rep = _readable(out)
    assert rep["stopped"] == "max_steps" and rep["steps"] == 6 and not rep["interrupted"]
    assert rep["checkpoint"]["file"] is None and rep["checkpoint"]["resumed"] is True
    assert not (out / _CHECKPOINT_NAME).exists()  # the fit is over: removed
    with np.load(out / "normal_map.npz") as a, np.load(ref / "normal_map.npz") as b:
        np.testing.assert_array_equal(a["slopes"], b["slopes"])
        np.testing.assert_array_equal(a["normals"], b["normals"])
    assert (out / "normal_map.png").read_bytes() == (ref / "normal_map.png").read_bytes()
    strip = lambda f: [(h["step"], h["loss"]) for h in json.loads(f.read_text())]  # noqa
    assert strip(out / "loss.json") == strip(ref / "loss.json")


@pytest.mark.parametrize("change,args,match", [
    (dict(scale=0.5), [], r"another problem \(its targets differ\)"),
    (dict(map_size=8), [], r"map size 16x16 in the checkpoint, 8x8 now"),
    ({}, ["--solver", "lbfgs"], r"solver 'lm' in the checkpoint, 'lbfgs' now"),
    ({}, ["--lsmr-steps", "5"], r"lsmr_steps 10 in the checkpoint, 5 now"),
])
def test_a_resume_of_another_fit_is_refused_in_one_line(tmp_path, capsys, change, args,
                                                        match):
    out = tmp_path / "out"
    assert _run(_fit_file(tmp_path / "a", max_steps=2), "-o", out, "--keep-checkpoint") == 0
    capsys.readouterr()
    other = _fit_file(tmp_path / "b", max_steps=2, **change)
    assert _run(other, "-o", out, "--resume", *args) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # (after the stage lines)
    assert err.startswith("jaxnm fit: error: ")
    assert str(out / _CHECKPOINT_NAME) in err
    assert re.search(match, err), err


def test_resume_without_a_checkpoint_is_refused(tmp_path, capsys):
    assert _run(_fit_file(tmp_path / "a"), "-o", tmp_path / "out", "--resume") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no checkpoint to resume from" in err  # (at once)


@pytest.mark.slow
def test_a_killed_fit_resumes_to_the_uninterrupted_map(tmp_path):
    """``jaxnm fit`` killed (SIGKILL) mid-fit, once a checkpoint exists: ``--resume`` ends
    with the ``normal_map.npz`` of a fit that ran through, bitwise."""
    path = _fit_file(tmp_path / "job", max_steps=300, held_out=False)
    ref = tmp_path / "ref"
    assert _run(path, "-o", ref, "--checkpoint-every", "0") == 0
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "jaxnm.cli", "fit", str(path), "-o", str(out), "--no-progress",
         "--checkpoint-every", "0.05"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONWARNINGS": "ignore"})
    try:
        deadline = time.monotonic() + 300
        while not (out / _CHECKPOINT_NAME).exists():
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline
            time.sleep(0.01)
        proc.kill()
        assert proc.wait() == -signal.SIGKILL
    finally:
        proc.kill()
        proc.stderr.close()
    saved = F.load_checkpoint(out / _CHECKPOINT_NAME).meta
    assert 0 < saved["next_step"] <= 300 and not (out / "normal_map.npz").exists()
    assert _run(path, "-o", out, "--resume") == 0
    with np.load(out / "normal_map.npz") as a, np.load(ref / "normal_map.npz") as b:
        np.testing.assert_array_equal(a["slopes"], b["slopes"])
        np.testing.assert_array_equal(a["normals"], b["normals"])


# ----------------------------------------------------------------------------- files


def test_an_interrupted_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "report.json"
    path.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(path) as f:
            f.write(b"half a fi")
            raise KeyboardInterrupt
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["report.json"]
    with atomic_write(path) as f:
        f.write(b"new")
    assert path.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_a_broken_checkpoint_is_one_line(tmp_path):
    bad = tmp_path / "fit.npz"
    bad.write_bytes(b"not an archive")
    with pytest.raises(ValueError, match=r"fit.npz: cannot read the checkpoint") as e:
        F.load_checkpoint(bad)
    assert "\n" not in str(e.value)


def test_a_checkpoint_that_could_not_be_written_is_refused_before_the_fit(small, tmp_path,
                                                                           monkeypatch):
    """(It was found at the first checkpoint, after the preparation, the compile and the
    first steps.)"""
    def too_late(*a, **k):
        raise AssertionError("the problem was prepared before the checkpoint was checked")

    monkeypatch.setattr(S, "prepare", too_late)
    (tmp_path / "file").write_text("x")
    opts = F.FitOptions(max_steps=2)
    for path, error, message in (
            (tmp_path, IsADirectoryError, f"{tmp_path}: is a folder; name the file to write"),
            (tmp_path / "file" / "c.npz", NotADirectoryError,
             f"{tmp_path / 'file' / 'c.npz'}: {tmp_path / 'file'} is a file, not a folder")):
        with pytest.raises(error, match=f"^{re.escape(message)}$"):
            F.fit_normal_map(small[0], opts, progress=False, checkpoint=path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
