"""The solver loop: the solvers driven one step at a time, compiled once per shape.

**Solvers**: ``"lm-texel"`` (`jaxnm.fit.texel_lm`, the default) Levenberg–Marquardt on
the texel-space normal equations; from optimistix, ``"lm"`` Levenberg–Marquardt and
``"gn"`` Gauss–Newton, both matrix-free: the Jacobian is a linearised function
(forward-mode JVP, transposed for the VJP) and each step is solved by
lineax's iterative LSMR — no dense Jacobian is ever formed; ``"lbfgs"``:
the first-order baseline, L-BFGS on the sum of squares.

**One compilation per shape.** The step is a module-level function jitted
with the solver, the model and the problem as arguments, so every call of
`fit_normal_map` — and every restart on a problem of the same shapes — reuses
the compiled step. The loss reported per step is the solver's own evaluation
(no second compiled program). Coarse-to-fine levels have different map sizes,
so each level compiles once.

**Driving the loop in Python** keeps what a user needs between steps: a
progress bar, Ctrl-C (return the best map so far), a time limit, and a history with
the angular error against a ground truth.
"""

from __future__ import annotations

import math
import os
import sys
import time

import equinox as eqx
import jax
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array

from .diagnostics import angular_error, check_identifiability, seen_texels, texel_influence
from .model import ModelArgs, loss, residuals
from .prepare import Prepared, prepare, shard_views, with_map_size
from .problem import FitOptions, FitProblem, FitResult
from .texel_lm import TexelLM, texel_sum_tables

__all__ = ["fit_normal_map", "make_solver", "preconditioner", "level_sizes", "start_slopes",
           "texel_sums_for"]


def make_solver(options: FitOptions):
    """The solver named by ``options.solver``: optimistix's, or a `TexelLM`."""
    if options.solver == "lm-texel":
        return TexelLM(cg_steps=options.lsmr_steps, rtol=options.rtol, atol=options.atol)
    lsmr = lx.LSMR(rtol=1e-4, atol=1e-6, max_steps=options.lsmr_steps)
    if options.solver == "lm":
        return optx.LevenbergMarquardt(rtol=options.rtol, atol=options.atol, linear_solver=lsmr)
    if options.solver == "gn":
        return optx.GaussNewton(rtol=options.rtol, atol=options.atol, linear_solver=lsmr)
    return optx.LBFGS(rtol=options.rtol, atol=options.atol)


def texel_sums_for(prep: Prepared, options: FitOptions, backend: str | None = None,
                   deterministic: bool | None = None) -> str:
    """What ``options.texel_sums`` means for ``prep`` on ``backend`` (JAX's default if None)
    with or without deterministic GPU ops (`deterministic_ops` if None):
    ``"tables"`` or ``"scatter"``.

    ``"auto"`` is tables on an accelerator with deterministic ops (as the command line
    runs), where XLA would otherwise sort every scatter-add's indices, and scatter-adds
    elsewhere. Measured on an H100 (README, GPU), the fit benchmark's step of 10
    conjugate-gradient iterations: deterministic ops 11.0-11.2 ms with scatter-adds, 6.3-7.6
    with tables; without them 5.1 and 7.3 ms; on the CPU 32-36 against 38-45 ms. Always
    scatter-adds for solvers other than ``"lm-texel"`` and for views spread over several
    devices (a chunk's tables index the pixels of all its views)."""
    spread = len(prep.batches[0].pixels.sharding.device_set) > 1
    if spread and options.texel_sums == "tables":
        raise ValueError("FitOptions.texel_sums 'tables' needs the views on one device; these "
                         "are spread over several (use 'auto' or 'scatter')")
    if options.solver != "lm-texel" or spread:
        return "scatter"
    if options.texel_sums == "auto":
        backend = jax.default_backend() if backend is None else backend
        deterministic = deterministic_ops() if deterministic is None else deterministic
        return "tables" if backend != "cpu" and deterministic else "scatter"
    return options.texel_sums


def deterministic_ops() -> bool:
    """Whether XLA was asked for deterministic GPU arithmetic (``--xla_gpu_deterministic_ops``
    in ``XLA_FLAGS``, as the command line sets it unless ``--nondeterministic``)."""
    return "--xla_gpu_deterministic_ops=true" in os.environ.get("XLA_FLAGS", "").split()


def _residual_fn(z, args):
    return residuals(z, args), None


def _loss_fn(z, args):
    return loss(z, args), None


def _objective(solver):
    """The function the solver sees: residuals for least squares, the loss otherwise."""
    return _residual_fn if isinstance(solver, optx.AbstractLeastSquaresSolver) else _loss_fn


@eqx.filter_jit
def _init(solver, z, args: ModelArgs):
    """An optimistix solver's first state (`TexelLM` makes its own on the host)."""
    fn = _objective(solver)
    f_struct, aux_struct = jax.eval_shape(fn, z, args)
    return solver.init(fn, z, args, {}, f_struct, aux_struct, frozenset())


def _holds_two_linearisations(solver) -> bool:
    """Whether ``solver``'s state keeps the linearisation twice: optimistix's Gauss-Newton
    family with the damped-Newton descent (Levenberg-Marquardt) stores it as the state's
    ``f_info`` and as the descent state's, and after every step, accepted or rejected,
    the two are the same value."""
    return (isinstance(solver, optx.AbstractGaussNewton)
            and isinstance(solver.descent, optx.DampedNewtonDescent))


def _shed(solver, state):
    """``state`` with the descent's copy of the linearisation dropped: out of a compiled
    step, two references to one value are two buffers (38 MB each for the built-in
    problem, and again in the step's output)."""
    if not _holds_two_linearisations(solver):
        return state
    return eqx.tree_at(lambda s: s.descent_state.f_info, state, None)


def _restore(solver, state):
    """The inverse of `_shed`: the descent's linearisation is the state's."""
    if not _holds_two_linearisations(solver):
        return state
    return eqx.tree_at(lambda s: s.descent_state.f_info, state, state.f_info,
                       is_leaf=lambda x: x is None)


@eqx.filter_jit(donate="all-except-first")
def _step(kept, z, state):
    """One solver step; ``kept = (args, solver)``. Returns the accepted point, the state
    (`_shed`), whether to stop, the solver's result code, the loss at the accepted point
    (from the solver's own evaluation) and the accepted point's slopes (``z * scale``,
    here rather than as a program of its own after every step).

    ``z`` and ``state`` are donated (the new state reuses their buffers instead of
    doubling them); ``kept`` is not (the solver too may hold arrays, e.g. Gauss-Newton's
    learning rate), and `_unaliased` makes sure no state array is one of ``args``."""
    args, solver = kept
    if isinstance(solver, TexelLM):
        z, state, done, result, loss_value = solver.step(z, state, args)
    else:
        fn = _objective(solver)
        z, state, _ = solver.step(fn, z, args, {}, _restore(solver, state), frozenset())
        done, result = solver.terminate(fn, z, args, {}, state, frozenset())
        state, loss_value = _shed(solver, state), state.f_info.as_min()
    return z, state, done, result, loss_value, z * args.scale


def _buffers(x) -> tuple:
    return tuple(shard.data.unsafe_buffer_pointer() for shard in x.addressable_shards)


def _unaliased(state, args):
    """``state`` with every array that shares its buffer with an array of ``args`` (the
    model arguments and the solver) copied.

    A jitted function returns an input it passes through unchanged as the same buffer; a
    solver state built from ``args`` (its linearisation closes over them) can therefore
    hold the caller's arrays, and donating the state to `_step` would free them."""
    held = {b for x in jax.tree_util.tree_leaves(args) if isinstance(x, jax.Array)
            for b in _buffers(x)}
    return jax.tree_util.tree_map(
        lambda x: _copy(x) if isinstance(x, jax.Array) and set(_buffers(x)) & held else x,
        state)


def _unit_normals(slopes) -> np.ndarray:
    """`jaxnm.fit.model.slopes_to_normals` on the host in float64: for the error of every
    step and the result (as JAX operations, a dozen small compilations)."""
    s = np.asarray(slopes, np.float64)
    n = np.concatenate([s, np.ones(s.shape[:-1] + (1,))], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _copy(x):
    """A copy of ``x`` in new buffers, made without compiling anything (``jnp.copy`` is an
    XLA program per shape and dtype: 20 small compilations for an LM state)."""
    return jax.device_put(x, may_alias=False)


def preconditioner(prep: Prepared) -> Array:
    """(h, w, 1) Jacobi-like texel scales: the solver works on ``z = slopes / scale``, where
    ``scale = sqrt(c_ref / (c + 0.01 c_ref))`` evens out how strongly each texel is observed
    (``c`` its `texel_influence`, ``c_ref`` the median over observed texels)."""
    # (device_put: jnp.asarray of a NumPy array compiles a program per shape)
    return jax.device_put(_host_preconditioner(prep))


def _host_preconditioner(prep: Prepared) -> np.ndarray:
    """`preconditioner` as a NumPy array."""
    c = np.asarray(texel_influence(prep))
    seen = c[c > 0]
    c_ref = float(np.median(seen)) if seen.size else 1.0
    return np.sqrt(c_ref / (c + 0.01 * c_ref))[..., None].astype(np.float32)


def start_slopes(size: tuple[int, int], options: FitOptions) -> np.ndarray:
    """The slopes a fit starts from, (h, w, 2) float32: the flat map, jittered by
    ``options.init_noise`` (standard deviation) from NumPy's generator seeded with
    ``options.seed`` — on the host, so no XLA program is compiled for it."""
    z = np.zeros(tuple(size) + (2,), np.float32)
    if options.init_noise > 0:
        rng = np.random.default_rng(options.seed)
        z = (options.init_noise * rng.standard_normal(z.shape)).astype(np.float32)
    return z


def level_sizes(map_size: tuple[int, int], coarse_to_fine: int) -> list[tuple[int, int]]:
    """The map sizes solved in turn: each coarser level halves the previous one (at least 2)."""
    h, w = map_size
    return [(max(2, h >> k), max(2, w >> k)) for k in range(coarse_to_fine, -1, -1)]


def _flat(history: list, level: int, options: FitOptions) -> bool:
    """Whether this level's loss fell by less than ``options.ftol`` (relative) over the last
    ``options.patience`` steps."""
    losses = [h["loss"] for h in history if h["level"] == level]
    if options.ftol <= 0 or len(losses) <= options.patience:
        return False
    before, now = losses[-1 - options.patience], losses[-1]
    return bool(before - now <= options.ftol * abs(before))


def _like(level: Prepared, prep: Prepared) -> Prepared:
    """A coarse-to-fine level spread over the devices ``prep``'s views are spread over."""
    sharding = prep.batches[0].pixels.sharding
    if len(sharding.device_set) == 1:
        return level
    return shard_views(level, list(sharding.mesh.devices.flat))


def _upsample(slopes: Array, size: tuple[int, int]) -> Array:
    return jax.image.resize(slopes, size + (slopes.shape[-1],), "linear")


class _Progress:
    """Per-step progress on stderr: a tqdm bar (loss, error, ETA), or a line per step where
    tqdm is not installed; nothing when disabled."""

    def __init__(self, total: int, enabled: bool):
        self.bar = None
        self.enabled = enabled
        self.total = total
        self.count = 0
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:
                return
            self.bar = tqdm(total=total, desc="fit", unit="step", dynamic_ncols=True)

    def update(self, rec: dict) -> None:
        if not self.enabled:
            return
        post = {"loss": f"{rec['loss']:.4g}"}
        if "mean_angular_error_deg" in rec:
            post["err"] = f"{rec['mean_angular_error_deg']:.2f}deg"
        self.count += 1
        if self.bar is None:
            print(f"fit step {self.count}/{self.total} ({rec['seconds']:.1f} s): "
                  + ", ".join(f"{k} {v}" for k, v in post.items()), file=sys.stderr, flush=True)
            return
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def fit_normal_map(problem: FitProblem, options: FitOptions = FitOptions(), *,
                   ground_truth: np.ndarray | None = None, progress: bool = True,
                   prepared: Prepared | None = None, strength: float = 1.0,
                   time_limit: float | None = None,
                   error_texels: np.ndarray | None = None) -> FitResult:
    """Fit the normal map of ``problem`` (see `jaxnm.fit`).

    **Arguments:**
    - `problem`, `options`: what to fit and how.
    - `ground_truth`: optional (h, w, 3) decoded unit normals: the history then
      records the mean angular error at every step, over `error_texels` ((h, w)
      bool; default `seen_texels`).
    - `progress`: show a progress bar (loss, step, elapsed, ETA).
    - `prepared`: reuse a `prepare(problem)` result.
    - `strength`: the map's x/y scale used when rendering (1: as fitted).
    - `time_limit`: stop (keeping the best map) after this many seconds.

    Warns (`FitWarning`) when no view has three lights with non-coplanar
    directions (`check_identifiability`; the report is in the result). A
    `KeyboardInterrupt` (Ctrl-C) during the fit ends it and returns the best map so far
    (``stopped == "interrupted"``); no signal handler is installed.
    Deterministic for a given `options.seed`. History step 0 is the start; the
    loss of each record is that of the map the solver holds after the step.
    """
    t_start = time.perf_counter()
    prep = prepared if prepared is not None else prepare(problem)
    identifiability = check_identifiability(prep)  # warns when the lights cannot determine it
    h, w = problem.map_size
    if prep.options[0].normal_map_shape != (h, w):
        raise ValueError(f"{problem.source}: `prepared` was made for a "
                         f"{prep.options[0].normal_map_shape} map, not {(h, w)}")
    sizes = level_sizes((h, w), options.coarse_to_fine)
    slopes = start_slopes(sizes[0], options)  # (host; the device gets z below)
    seen = gt = None
    if ground_truth is not None:
        gt = np.asarray(ground_truth, np.float64)
        seen = seen_texels(prep, (h, w)) if error_texels is None else np.asarray(error_texels,
                                                                                bool)
        if gt.shape != (h, w, 3) or seen.shape != (h, w):
            raise ValueError(f"{problem.source}: the ground truth {gt.shape} and error texels "
                             f"{seen.shape} must match the map size {(h, w)}")
    solver = make_solver(options)
    history: list = []
    stopped = "max_steps"
    best = (math.inf, slopes)
    bar = _Progress(options.max_steps * len(sizes), progress)
    try:
        for level, size in enumerate(sizes):
            if level > 0:
                slopes = _upsample(best[1], size)
                best = (math.inf, slopes)
            lp = prep if size == (h, w) else _like(with_map_size(prep, size), prep)
            scale_host = _host_preconditioner(lp)
            scale = jax.device_put(scale_host)
            # least squares on reduced residuals (same loss and Gauss-Newton steps,
            # fewer numbers per pixel); L-BFGS only needs the loss and its gradient
            sums = (texel_sum_tables(lp) if texel_sums_for(lp, options) == "tables"
                    else None)
            args = ModelArgs.create(lp, smoothness=options.smoothness, strength=strength,
                                    scale=scale, reduce=options.solver != "lbfgs",
                                    texel_sums=sums)
            z = jax.device_put((np.asarray(slopes) / scale_host).astype(np.float32))
            if isinstance(solver, TexelLM):  # made on the host, in buffers of its own
                state = solver.init(z, args)
            else:
                # our own copy: the initial state can hold library-wide constant arrays
                # (optimistix's result codes), which donating it to `_step` would free
                state = jax.tree_util.tree_map(
                    lambda x: _copy(x) if isinstance(x, jax.Array) else x,
                    _shed(solver, _init(solver, z, args)))
            # optimistix's first step evaluates the start and proposes the first move,
            # so the start's loss arrives with it: record it as step 0
            for k in range(options.max_steps + 1):
                z, state, done, result, loss_value, slopes = _step(
                    (args, solver), z, _unaliased(state, (args, solver)))
                rec = {"level": level, "size": list(size), "step": k,
                       "loss": float(loss_value), "seconds": time.perf_counter() - t_start}
                if np.isfinite(rec["loss"]) and rec["loss"] < best[0]:
                    best = (rec["loss"], slopes)
                if gt is not None and size == (h, w):
                    err = angular_error(_unit_normals(best[1]), gt)[seen]
                    rec["mean_angular_error_deg"] = float(err.mean())
                history.append(rec)
                if k > 0:
                    bar.update(rec)
                if time_limit is not None and rec["seconds"] > time_limit:
                    stopped = "time_limit"
                    break
                if k > 0 and bool(done):
                    stopped = ("converged" if result == optx.RESULTS.successful
                               else str(result))
                    break
                if _flat(history, level, options):
                    stopped = "converged"
                    break
            if stopped in ("interrupted", "time_limit"):
                break
    except KeyboardInterrupt:  # Ctrl-C (or a caller's `_thread.interrupt_main`)
        stopped = "interrupted"
    finally:
        bar.close()
    final = best[1]
    if final.shape[:2] != (h, w):  # stopped during a coarse level
        final = _upsample(final, (h, w))
    return FitResult(normals=_unit_normals(final).astype(np.float32), slopes=np.asarray(final),
                     history=history, seconds=time.perf_counter() - t_start, stopped=stopped,
                     best_loss=float(best[0]), identifiability=identifiability)

