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

**A step and a driver.** `fit_step` is one solver step, a pure compiled function (state in,
state out, from `start_state`). `fit_normal_map` drives it in Python, which keeps what a
user needs between steps: a history with the angular error against a ground truth, a
progress bar, a time limit, a caller's request to stop (``should_stop``), Ctrl-C (return
the best map so far), checkpoints (`jaxnm.fit.checkpoint`), and, for a fit spread over
processes, every process's agreement on what is not a function of the loss (the time
limit, ``should_stop``, when to checkpoint).

**When a fit stops**: `jaxnm.fit.stopping` (the test that ended a fit is
`FitResult.stop_test`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import Array

from . import stopping
from ._processes import (
    allgather_json,
    fingerprint_across_processes,
    to_host,
)
from .checkpoint import (
    Checkpoint,
    check_fingerprint,
    fit_fingerprint,
    load_checkpoint,
    save_checkpoint,
)
from .diagnostics import angular_error, check_identifiability, seen_texels, texel_influence
from .distributed import spread_over_processes
from .model import ModelArgs, loss, residuals
from .prepare import Prepared, prepare, shard_views, with_map_size
from .problem import FitOptions, FitProblem, FitResult
from .texel_lm import TexelLM, texel_sum_tables

__all__ = ["fit_normal_map", "fit_step", "start_state", "StepResult", "compile_fit",
           "make_solver", "preconditioner", "level_sizes", "texel_sums_for"]

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
    with or without deterministic GPU ops (if None: whether ``XLA_FLAGS`` asks for them):
    ``"tables"`` or ``"scatter"``.

    ``"auto"`` is tables on an accelerator with deterministic ops (as the command line
    runs), where XLA would otherwise sort every scatter-add's indices, and scatter-adds
    elsewhere, where they are the faster (docs/guides/design.md has the timings). Always
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
        deterministic = _deterministic_ops() if deterministic is None else deterministic
        return "tables" if backend != "cpu" and deterministic else "scatter"
    return options.texel_sums


def _deterministic_ops() -> bool:
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
    step, two references to one value are two buffers (the size of the problem's
    linearisation each, and again in the step's output)."""
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
    learning rate), and `_unaliased` makes sure no state array is one of ``args``.

    Also returns ``(accepted, damping, predicted)``: whether the step accepted the point it
    evaluated, and how damped the move to that point was and what decrease the solver's
    model predicted for it (`_move`)."""
    args, solver = kept
    move = _move(solver, z, state)
    if isinstance(solver, TexelLM):
        f_before = state.f
        z, state, done, result, loss_value = solver.step(z, state, args)
        accepted = state.f < f_before  # a rejected point keeps the loss
    else:
        fn = _objective(solver)
        count = state.num_accepted_steps
        z, state, _ = solver.step(fn, z, args, {}, _restore(solver, state), frozenset())
        done, result = solver.terminate(fn, z, args, {}, state, frozenset())
        accepted = state.num_accepted_steps > count
        state, loss_value = _shed(solver, state), state.f_info.as_min()
    return z, state, done, result, loss_value, z * args.scale, (accepted, *move)


def _dot(a, b) -> Array:
    return sum(jnp.sum(x * y) for x, y in zip(jax.tree_util.tree_leaves(a),
                                               jax.tree_util.tree_leaves(b), strict=True))


def _share(held: Array, total: Array) -> Array:
    """``held / total`` clipped to [0, 1] (0 where ``total`` is 0: no move)."""
    ok = total > 0
    return jnp.clip(jnp.where(ok, held / jnp.where(ok, total, 1), 0.0), 0.0, 1.0)


def _move(solver, z, state) -> tuple[Array, Array]:
    """How the solver made the move from ``z`` to the point ``state`` asks the next step to
    evaluate: ``(damping, predicted)``, its damping in [0, 1] and the decrease of the loss
    its model predicted (see the module's "When a fit stops").

    - Levenberg-Marquardt: the damping's share of the curvature along the move ``d``,
      ``lambda |d|^2 / (d.H d + lambda |d|^2)``, and the Gauss-Newton model's decrease
      ``-(g.d + d.H d / 2)``. `TexelLM` keeps the latter, and ``d.(H + lambda I) d =
      -g.d`` (a conjugate-gradient iterate); for optimistix's, ``lambda = 1 / step size``,
      ``d.H d = |J d|^2`` and ``g.d = r.J d`` (one product with the linearisation the
      state holds).
    - Gauss-Newton: no damping (a fixed learning rate ``t``: ``1 - min(t, 1)``), the same
      model.
    - a backtracking line search (L-BFGS): ``1 - step / first step``, and the decrease
      the gradient predicts, ``-g.d``."""
    if isinstance(solver, TexelLM):
        d = state.delta
        return _share(state.lam * jnp.sum(d * d), -jnp.sum(state.g * d)), state.predicted
    d = jax.tree_util.tree_map(jnp.subtract, state.y_eval, z)
    info, search = state.f_info, solver.search
    if isinstance(info, optx.FunctionInfo.ResidualJac):
        jd = info.jac.mv(d)
        dhd = _dot(jd, jd)
        predicted = -(_dot(info.residual, jd) + 0.5 * dhd)
    else:
        dhd, predicted = None, -_dot(info.grad, d)
    if isinstance(search, optx.BacktrackingArmijo):
        damping = 1.0 - state.search_state.step_size / search.step_init
    elif isinstance(search, optx.LearningRate):
        damping = 1.0 - jnp.minimum(search.learning_rate, 1.0)
    elif dhd is not None and isinstance(solver.descent, optx.DampedNewtonDescent):
        dd = _dot(d, d)  # lambda |d|^2 / (|J d|^2 + lambda |d|^2), lambda = 1 / step size
        damping = _share(dd, state.search_state.step_size * dhd + dd)
    else:
        damping = jnp.zeros(())
    return damping, predicted


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
    # (an array spread over processes is copied where it lies)
    return jax.device_put(x, None if x.is_fully_addressable else x.sharding, may_alias=False)


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


def _start_slopes(size: tuple[int, int], options: FitOptions) -> np.ndarray:
    """The slopes a fit starts from, (h, w, 2) float32: the flat map, jittered by
    ``options.init_noise`` (standard deviation) from NumPy's generator seeded with
    ``options.seed`` — on the host, so no XLA program is compiled for it."""
    z = np.zeros(tuple(size) + (2,), np.float32)
    if options.init_noise > 0:
        rng = np.random.default_rng(options.seed)
        z = (options.init_noise * rng.standard_normal(z.shape)).astype(np.float32)
    return z


def _given_start(start, size: tuple[int, int], options: FitOptions,
                 source: str) -> np.ndarray:
    """`_start_slopes` for a fit given its start: the slopes of the unit normals ``start``
    (`normals_to_slopes` on the host: z clamped to 1e-3), resized to ``size`` where it
    differs, plus `_start_slopes`' jitter."""
    n = np.asarray(start, np.float64)
    if n.ndim != 3 or n.shape[-1] != 3 or not np.all(np.isfinite(n)):
        raise ValueError(f"{source}: the start must be finite (h, w, 3) normals, got shape "
                         f"{n.shape}")
    z = np.clip(n[..., :2] / np.maximum(n[..., 2:], 1e-3), -1e3, 1e3).astype(np.float32)
    if z.shape[:2] != tuple(size):
        z = np.asarray(_upsample(jax.device_put(z), tuple(size)), np.float32)
    return z + _start_slopes(size, options)


def _digest(x: np.ndarray) -> str:
    """A hash of an array's bytes (a fit's start, in its checkpoint's fingerprint)."""
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()


def level_sizes(map_size: tuple[int, int], coarse_to_fine: int,
                source: str = "<fit>") -> list[tuple[int, int]]:
    """The map sizes solved in turn: each coarser level halves the previous one (at least 2
    texels a side). A `ValueError` naming ``source`` where a level would not be smaller than
    the next (a 64 x 64 map has 5 coarser levels, down to 2 x 2)."""
    h, w = map_size
    most = (max(h, w) // 3).bit_length()  # the halvings of a side above 2
    if coarse_to_fine > most:
        raise ValueError(f"{source}: coarse_to_fine = {coarse_to_fine} asks for levels below "
                         f"2x2 texels: a {h}x{w} map has at most {most} coarser levels")
    return [(max(2, h >> k), max(2, w >> k)) for k in range(coarse_to_fine, -1, -1)]


def _like(level: Prepared, prep: Prepared) -> Prepared:
    """A coarse-to-fine level spread over the devices ``prep``'s views are spread over."""
    sharding = prep.batches[0].pixels.sharding
    if len(sharding.device_set) == 1:
        return level
    return shard_views(level, list(sharding.mesh.devices.flat))


def _upsample(slopes: Array, size: tuple[int, int]) -> Array:
    return jax.image.resize(slopes, size + (slopes.shape[-1],), "linear")


class _Progress:
    """Per-step progress on stderr: a tqdm bar (loss, error, ETA) for ``mode`` True where
    tqdm is installed, else a line per step (``mode`` ``"lines"``, or no tqdm); nothing for
    ``mode`` False."""

    def __init__(self, total: int, mode: bool | str, done: int = 0):
        self.bar = None
        self.enabled = bool(mode)
        self.total = max(total, done)  # a checkpoint past the step limit: nothing left
        self.count = done
        if mode is True:
            try:
                from tqdm import tqdm
            except ImportError:
                return
            self.bar = tqdm(total=self.total, initial=done, desc="fit", unit="step",
                            dynamic_ncols=True)

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


def _level_args(prep: Prepared, size: tuple[int, int], options: FitOptions,
                strength: float) -> tuple[ModelArgs, np.ndarray]:
    """The step's model arguments for the level of map ``size`` (``prep`` re-planned for it
    where it is a coarser level) and its texel scales (`preconditioner`) on the host."""
    h, w = prep.options[0].normal_map_shape
    lp = prep if tuple(size) == (h, w) else _like(with_map_size(prep, size), prep)
    scale_host = _host_preconditioner(lp)
    # least squares on reduced residuals (same loss and Gauss-Newton steps, fewer numbers
    # per pixel); L-BFGS only needs the loss and its gradient
    sums = texel_sum_tables(lp) if texel_sums_for(lp, options) == "tables" else None
    args = ModelArgs.create(lp, smoothness=options.smoothness, strength=strength,
                            scale=jax.device_put(scale_host), reduce=options.solver != "lbfgs",
                            texel_sums=sums)
    return args, scale_host


def _float32(fn):
    """``fn`` run with JAX's 64-bit types off. A fit's arithmetic is float32; a caller's
    ``jax_enable_x64`` would otherwise make the solvers' own scalars (optimistix's step
    sizes and damping) float64 beside float32 maps, which their programs refuse. The setting
    is thread-local and restored when ``fn`` returns."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        with jax.enable_x64(False):
            return fn(*args, **kwargs)
    return run


@_float32
def compile_fit(problem: FitProblem, options: FitOptions = FitOptions(), *,
                prepared: Prepared | None = None, strength: float = 1.0) -> float:
    """Compile the solver step of `fit_normal_map`'s first level ahead of time, without
    running it: the fit's first step then compiles nothing (later coarse-to-fine levels,
    of other map sizes, still compile when they start).

    For a caller that wants compilation apart from the fit: to time it, or to hand the
    compiler's working memory back to the system before the fit's own buffers are
    allocated (the command line does: its peak memory is then the larger of the two, not
    their sum).

    **Arguments:** as `fit_normal_map`'s (`prepared`: reuse a `prepare(problem)` result).

    **Returns:** the seconds it took.
    """
    t0 = time.perf_counter()
    prep = prepared if prepared is not None else prepare(problem)
    size = level_sizes(tuple(problem.map_size), options.coarse_to_fine, problem.source)[0]
    args, scale_host = _level_args(prep, size, options, strength)
    solver = make_solver(options)
    z = jax.device_put((_start_slopes(size, options) / scale_host).astype(np.float32))
    state = _fresh_state(solver, z, args)
    _step.lower((args, solver), z, _unaliased(state, (args, solver))).compile()
    return time.perf_counter() - t0


def _fresh_state(solver, z, args: ModelArgs):
    """The solver's state before the first step, in buffers of its own."""
    if isinstance(solver, TexelLM):  # made on the host, in buffers of its own
        return solver.init(z, args)
    # our own copy: the initial state can hold library-wide constant arrays (optimistix's
    # result codes), which donating it to `_step` would free
    return jax.tree_util.tree_map(lambda x: _copy(x) if isinstance(x, jax.Array) else x,
                                  _shed(solver, _init(solver, z, args)))


def _saved_state(path, fresh, leaves: list):
    """``fresh`` (a `_fresh_state`) with its arrays replaced by a checkpoint's ``leaves``
    (each put where the fresh one lives)."""
    dynamic, static = eqx.partition(fresh, eqx.is_array)
    now, treedef = jax.tree_util.tree_flatten(dynamic)
    if [(a.shape, a.dtype) for a in now] != [(a.shape, a.dtype) for a in leaves]:
        raise ValueError(f"{path}: cannot resume this fit: the checkpoint's solver state does "
                         "not fit this solver and problem")
    arrays = [_as_saved(a, b) for a, b in zip(leaves, now, strict=True)]
    return eqx.combine(treedef.unflatten(arrays), static)


def _as_saved(saved, fresh: Array) -> Array:
    """A checkpoint's array ``saved`` as the state's array ``fresh`` is: where it lives (an
    uncommitted fresh array stays uncommitted: jit places it beside the others, e.g. on
    every process's devices for a problem spread over processes), and weak-typed if it is
    (optimistix's counters are weak-typed scalars; a strong one would not match the
    compiled step, which would compile again)."""
    if jax.typeof(fresh).weak_type and np.ndim(saved) == 0:
        weak = jnp.asarray(np.asarray(saved).item())  # a Python scalar's type: weak
        if weak.dtype == fresh.dtype:
            saved = weak
    return jax.device_put(saved, fresh.sharding if fresh.committed else None)


class StepResult(NamedTuple):
    """What one solver step (`fit_step`) returns.

    - `z`: the accepted point (the preconditioned slopes, ``slopes = z * scale``).
    - `state`: the solver's state, to pass to the next step.
    - `done`, `result`: the solver's own test and its result code (``optx.RESULTS``).
    - `loss`: the loss at the accepted point (the solver's own evaluation).
    - `slopes`: the accepted point's slopes, (h, w, 2).
    - `accepted`, `damping`, `predicted`: whether the step accepted the point it evaluated,
      how damped the move to that point was and the decrease its model predicted
      (`jaxnm.fit.stopping`).
    """

    z: Array
    state: Any
    done: Array
    result: Any
    loss: Array
    slopes: Array
    accepted: Array
    damping: Array
    predicted: Array


@_float32
def fit_step(args: ModelArgs, solver, z: Array, state) -> StepResult:
    """One step of ``solver`` on the fit's model ``args``: state in, state out.

    A pure function, compiled once per problem shape and solver (the step is jitted with
    the solver, the model and the problem as arguments). ``z`` and ``state`` are donated:
    the new state reuses their buffers, so pass the returned ones to the next step and do
    not read the old ones again. The first state is `start_state`'s.
    """
    kept = (args, solver)
    z, state, done, result, loss_value, slopes, move = _step(kept, z, _unaliased(state, kept))
    return StepResult(z, state, done, result, loss_value, slopes, *move)


@_float32
def start_state(args: ModelArgs, solver, z: Array):
    """``solver``'s state before its first step from ``z`` on the model ``args`` (for
    `fit_step`), in buffers of its own."""
    return _fresh_state(solver, z, args)


@dataclasses.dataclass
class _Run:
    """A fit in progress, on the host: what the driver keeps between steps and what a
    checkpoint saves (`_save`)."""

    t_start: float
    history: list
    best: tuple  # (loss, slopes)
    stopped: str = "max_steps"
    test: str = "max_steps"
    start: tuple = (0, 0, False)  # level, step, whether that level had ended
    last: tuple | None = None  # (level, step, z, state) after the last step taken here


@dataclasses.dataclass(frozen=True)
class _Setup:
    """What a fit needs before its first step (`_setup`)."""

    prep: Prepared
    spread: bool
    writer: bool
    identifiability: dict
    sizes: list
    map_size: tuple[int, int]
    gt: np.ndarray | None
    seen: np.ndarray | None
    fingerprint: dict | None
    source: str | None
    saved: Any
    terms: tuple[int, float]
    start_slopes: np.ndarray  # the first level's, before any checkpoint

    def floor(self, loss_value: float) -> float:
        """The loss's noise floor at ``loss_value`` (`jaxnm.fit.stopping.noise_floor`)."""
        return stopping.noise_floor(loss_value, *self.terms)


class _Checkpoints:
    """When and where a fit saves itself (`jaxnm.fit.checkpoint`): every ``every`` seconds of
    fitting and when it ends; across processes, process 0 writes."""

    def __init__(self, path, every: float, setup: _Setup):
        self.path, self.every, self.setup = path, every, setup
        self.last_save = time.perf_counter()

    def due(self, k: int, max_steps: int) -> bool:
        """Whether to save after step ``k``."""
        return (self.path is not None and k < max_steps
                and time.perf_counter() - self.last_save >= self.every)

    def save(self, run: _Run, level_done: bool) -> None:
        """Save ``run`` as it stands after its last step (a collective across processes)."""
        level, k, z, state = run.last
        leaves = [to_host(x) for x in jax.tree_util.tree_leaves(eqx.filter(state,
                                                                         eqx.is_array))]
        if self.setup.writer:
            meta = {"fingerprint": self.setup.fingerprint, "level": level, "next_step": k + 1,
                    "level_done": level_done, "stopped": run.stopped, "stop_test": run.test,
                    "best_loss": run.best[0], "seconds": time.perf_counter() - run.t_start,
                    "history": run.history}
            save_checkpoint(self.path, Checkpoint(meta=meta, z=np.asarray(z),
                                                  best_slopes=np.asarray(run.best[1]),
                                                  state=leaves))
        self.last_save = time.perf_counter()


def _agreed(*flags: bool) -> tuple[bool, ...]:
    """``flags`` or-ed over every process (a collective)."""
    every = allgather_json([bool(f) for f in flags])
    return tuple(any(p[i] for p in every) for i in range(len(flags)))


def _layout(prep: Prepared) -> list:
    """How ``prep`` was laid out: its arrays' shapes, types and device counts."""
    return [[list(x.shape), str(x.dtype), len(x.sharding.device_set)]
            for x in jax.tree_util.tree_leaves(prep) if isinstance(x, jax.Array)]


def _check_call(problem, options, *, strength, time_limit, progress) -> None:
    """One-line errors for `fit_normal_map`'s arguments of the wrong kind or range."""
    for name, value, kind in (("problem", problem, FitProblem),
                              ("options", options, FitOptions)):
        if not isinstance(value, kind):
            raise TypeError(f"fit_normal_map: {name} must be a {kind.__name__}, got "
                            f"{type(value).__name__}")
    try:
        scale = float(strength)
    except (TypeError, ValueError):
        scale = math.nan
    if isinstance(strength, bool) or not (math.isfinite(scale) and scale != 0):
        raise ValueError(f"{problem.source}: strength must be a finite number other than 0 "
                         f"(the map's x/y scale), got {strength!r}")
    if time_limit is not None and not time_limit >= 0:
        raise ValueError(f"{problem.source}: time_limit must be a number of seconds >= 0 "
                         f"(0: the start alone) or None, got {time_limit!r}")
    if progress not in (True, False, "lines"):
        raise ValueError(f"fit_normal_map: progress must be True, False or 'lines', got "
                         f"{progress!r}")


def _setup(problem: FitProblem, options: FitOptions, *, prepared, ground_truth, error_texels,
           strength, checkpoint, checkpoint_every, resume, start) -> _Setup:
    """`fit_normal_map`'s arguments checked, the problem prepared, the first level's start
    made and any checkpoint to resume from read and matched against the fit."""
    if not (isinstance(checkpoint_every, (int, float)) and checkpoint_every >= 0):
        raise ValueError(f"checkpoint_every must be a number of seconds >= 0, got "
                         f"{checkpoint_every!r}")
    source = checkpoint if resume is True else (resume or None)
    if resume is True and checkpoint is None:
        raise ValueError("resume=True needs the `checkpoint` to resume from")
    if checkpoint is not None:  # a folder, or a file as its folder: refused before the work
        from ..io import writable  # (as `save_checkpoint` imports it)

        writable(checkpoint)
    prep = prepared if prepared is not None else prepare(problem)
    spread = spread_over_processes(prep)
    if spread and options.coarse_to_fine:
        raise ValueError(f"{problem.source}: coarse_to_fine is not available for a fit across "
                         "processes (solve.coarse_to_fine must be 0)")
    # (warns when the lights cannot determine the map)
    identifiability = check_identifiability(prep, source=problem.source)
    h, w = problem.map_size
    if prep.options[0].normal_map_shape != (h, w):
        raise ValueError(f"{problem.source}: `prepared` was made for a "
                         f"{prep.options[0].normal_map_shape} map, not {(h, w)}")
    if start is not None and np.shape(start) != (h, w, 3):
        raise ValueError(f"{problem.source}: the start is {np.shape(start)}, not the map's "
                         f"{(h, w, 3)}")
    sizes = level_sizes((h, w), options.coarse_to_fine, problem.source)
    # (on the host; the device gets z later)
    slopes = (_start_slopes(sizes[0], options) if start is None
              else _given_start(start, sizes[0], options, problem.source))
    gt = seen = None
    if ground_truth is not None:
        gt = np.asarray(ground_truth, np.float64)
        seen = (seen_texels(prep, (h, w)) if error_texels is None
                else np.asarray(error_texels, bool))
        if gt.shape != (h, w, 3) or seen.shape != (h, w):
            raise ValueError(f"{problem.source}: the ground truth {gt.shape} and error texels "
                             f"{seen.shape} must match the map size {(h, w)}")
    fingerprint = saved = None
    if checkpoint is not None or source is not None:
        layout = _layout(prep) if start is None else [_layout(prep), _digest(slopes)]
        fingerprint = fit_fingerprint(problem, options, strength=strength, layout=layout)
        if spread:  # each process hashed its own targets' images
            fingerprint = fingerprint_across_processes(fingerprint)
    if source is not None:
        saved = load_checkpoint(source)
        check_fingerprint(source, saved.meta.get("fingerprint", {}), fingerprint)
    return _Setup(prep, spread, not spread or jax.process_index() == 0, identifiability, sizes,
                  (h, w), gt, seen, fingerprint, source, saved, stopping.loss_terms(prep),
                  slopes)


def _start(setup: _Setup, options: FitOptions, t_start: float) -> _Run:
    """The fit's record before its first step: a fresh one, or the checkpoint's."""
    run = _Run(t_start=t_start, history=[], best=(math.inf, setup.start_slopes))
    if setup.saved is not None:
        m = setup.saved.meta
        run.history, run.best = m["history"], (float(m["best_loss"]), setup.saved.best_slopes)
        run.stopped, run.test = m["stopped"], m["stop_test"]
        run.start = (m["level"], m["next_step"], m["level_done"])
        run.t_start = time.perf_counter() - m["seconds"]  # the fit's clock goes on
    return run


def _level_start(setup: _Setup, solver, resuming: bool, slopes, args: ModelArgs,
                 scale_host: np.ndarray):
    """The first ``(z, state)`` of a level: the checkpoint's where it ``resuming`` that
    level, else from ``slopes``."""
    if resuming:
        z = jax.device_put(setup.saved.z)
        return z, _saved_state(setup.source, _fresh_state(solver, z, args), setup.saved.state)
    z = jax.device_put((np.asarray(slopes) / scale_host).astype(np.float32))
    return z, _fresh_state(solver, z, args)


def _record(run: _Run, setup: _Setup, out: StepResult, level: int, size, k: int) -> dict:
    """The history record of step ``k`` (its loss, time and how the solver took it; the
    angular error of the best map so far against a ground truth), and the best map
    updated."""
    rec = {"level": level, "size": list(size), "step": k, "loss": float(out.loss),
           "seconds": time.perf_counter() - run.t_start}
    if k > 0:  # (step 0 evaluates the start)
        rec.update(accepted=bool(out.accepted), damping=float(out.damping),
                   predicted=float(out.predicted))
    if np.isfinite(rec["loss"]) and rec["loss"] < run.best[0]:
        run.best = (rec["loss"], out.slopes)
    if setup.gt is not None and size == setup.map_size:
        err = angular_error(_unit_normals(run.best[1]), setup.gt)[setup.seen]
        rec["mean_angular_error_deg"] = float(err.mean())
    run.history.append(rec)
    return rec


def _run_level(run: _Run, setup: _Setup, options: FitOptions, solver, level: int, size, *,
               strength, time_limit, should_stop, saves: _Checkpoints | None, bar) -> None:
    """Steps of ``level`` until a test ends it (`jaxnm.fit.stopping.decide`) or its steps
    are taken; saves a checkpoint when one is due."""
    resuming = setup.saved is not None and level == run.start[0]
    if level > 0 and not resuming:  # from the coarser level's best, upsampled
        run.best = (math.inf, _upsample(run.best[1], size))
    run.stopped, run.test = "max_steps", "max_steps"
    args, scale_host = _level_args(setup.prep, size, options, strength)
    z, state = _level_start(setup, solver, resuming, run.best[1], args, scale_host)
    records = [rec for rec in run.history if rec["level"] == level]
    # optimistix's first step evaluates the start and proposes the first move, so the
    # start's loss arrives with it: it is recorded as step 0
    for k in range(run.start[1] if resuming else 0, options.max_steps + 1):
        out = fit_step(args, solver, z, state)
        z, state = out.z, out.state
        rec = _record(run, setup, out, level, size, k)
        records.append(rec)
        run.last = (level, k, z, state)
        if k > 0:
            bar.update(rec)
        late = time_limit is not None and rec["seconds"] > time_limit
        if setup.spread:  # what is not a function of the loss, agreed by every process
            late, asked, due = _agreed(late, should_stop is not None and bool(should_stop(rec)),
                                       saves is not None and saves.due(k, options.max_steps))
        run.stopped, run.test = stopping.decide(
            rec, records, options, setup.floor, done=bool(out.done), result=out.result,
            late=late, asked=((lambda: asked) if setup.spread
                              else lambda: should_stop is not None and should_stop(rec)))
        if run.test != "max_steps":
            return
        if due if setup.spread else saves is not None and saves.due(k, options.max_steps):
            saves.save(run, level_done=False)


def _result(run: _Run, setup: _Setup) -> FitResult:
    """The `FitResult` of a fit that has stopped: its best map, at the full size."""
    final = run.best[1]
    if final.shape[:2] != setup.map_size:  # stopped during a coarse level
        final = _upsample(final, setup.map_size)
    start_floor = setup.floor(run.history[0]["loss"]) if run.history else 0.0
    stopped = run.stopped
    if (run.test in ("ftol", "solver_tolerance", "max_steps") and run.history
            and not run.best[0] < run.history[0]["loss"] - start_floor):
        stopped = "no_progress"
    return FitResult(normals=_unit_normals(final).astype(np.float32), slopes=np.asarray(final),
                     history=run.history, seconds=time.perf_counter() - run.t_start,
                     stopped=stopped, best_loss=float(run.best[0]),
                     identifiability=setup.identifiability, stop_test=run.test,
                     noise_floor=start_floor)


@_float32
def fit_normal_map(problem: FitProblem, options: FitOptions = FitOptions(), *,
                   ground_truth: np.ndarray | None = None, progress: bool | str = True,
                   prepared: Prepared | None = None, strength: float = 1.0,
                   time_limit: float | None = None,
                   error_texels: np.ndarray | None = None,
                   should_stop: Callable[[dict], bool] | None = None,
                   checkpoint: str | os.PathLike | None = None,
                   checkpoint_every: float = 30.0,
                   resume: bool | str | os.PathLike = False,
                   start: np.ndarray | None = None) -> FitResult:
    """Fit the normal map of ``problem`` (see `jaxnm.fit`).

    **Arguments:**
    - `problem`, `options`: what to fit and how.
    - `ground_truth`: optional (h, w, 3) decoded unit normals: the history then
      records the mean angular error at every step, over `error_texels` ((h, w)
      bool; default `seen_texels`).
    - `progress`: True: a progress bar on stderr (loss, step, elapsed, ETA; tqdm, else a
      line per step); ``"lines"``: a line per step; False: nothing.
    - `prepared`: reuse a `prepare(problem)` result.
    - `strength`: the map's x/y scale used when rendering (1: as fitted).
    - `time_limit`: stop (keeping the best map) after this many seconds.
    - `should_stop`: called after every step with its history record; when it returns
      True the fit ends after that step (``stopped == "interrupted"``, ``stop_test ==
      "should_stop"``), with a last checkpoint. No signal handler is installed: a
      command line's Ctrl-C handler can use this to stop cleanly.
    - `checkpoint`: a file (``.npz``, `jaxnm.fit.checkpoint`) to keep a checkpoint of
      the fit in, written atomically every `checkpoint_every` seconds of fitting (0:
      after every step) and when the fit ends (except on a ``KeyboardInterrupt``, which
      may land inside a step: the last checkpoint is then the one before). None (the
      default): nothing is written.
    - `resume`: carry on from a saved fit: a checkpoint file, or True for `checkpoint`
      (which must then exist). The same steps, history and result as if the fit had
      never stopped (bitwise on the CPU); new checkpoints go to `checkpoint` (None: none
      are written). The checkpoint must come from the same problem, map size, solver,
      arithmetic options (`jaxnm.fit.checkpoint.ARITHMETIC_OPTIONS`) and `strength`, else
      a one-line `ValueError` names the file and what differs; the stopping rule and the
      time limit (counted over the whole fit) may change. A checkpoint of a fit that had
      converged returns its result without a step.
    - `start`: (h, w, 3) unit normals to start from (e.g. a ray-cast bake) instead of the
      flat map (``z`` clamped to 1e-3; resized for a first coarse level; plus
      `options.init_noise`).

    **Returns:** a `FitResult`; its `stopped` says why the fit ended, `stop_test` which
    test ended it (`STOP_TESTS`; `jaxnm.fit.stopping` has the stopping rule and
    ``"no_progress"``).

    Warns (`FitWarning`) when no view has three lights with non-coplanar directions
    (`check_identifiability`). A `KeyboardInterrupt` (Ctrl-C) ends the fit with the best
    map so far (``stopped == "interrupted"``); no signal handler is installed.
    Deterministic for a given `options.seed`. History step 0 is the start; the loss of each
    record is that of the map the solver holds after the step; from step 1 on, ``accepted``,
    ``damping`` and ``predicted`` say how the solver took the step (`jaxnm.fit.stopping`).
    """
    t_start = time.perf_counter()
    _check_call(problem, options, strength=strength, time_limit=time_limit, progress=progress)
    setup = _setup(problem, options, prepared=prepared, ground_truth=ground_truth,
                   error_texels=error_texels, strength=strength, checkpoint=checkpoint,
                   checkpoint_every=checkpoint_every, resume=resume, start=start)
    solver = make_solver(options)
    run = _start(setup, options, t_start)
    bar = _Progress(options.max_steps * len(setup.sizes), progress,
                    done=sum(1 for rec in run.history if rec["step"] > 0))
    saves = None if checkpoint is None else _Checkpoints(checkpoint, checkpoint_every, setup)
    try:
        for level, size in enumerate(setup.sizes):
            if level < run.start[0] or (level == run.start[0] and run.start[2]):
                continue  # done before the checkpoint
            _run_level(run, setup, options, solver, level, size, strength=strength,
                       time_limit=time_limit, should_stop=should_stop, saves=saves, bar=bar)
            if run.test in ("time_limit", "should_stop"):
                break
        if saves is not None and run.last is not None:
            saves.save(run, level_done=run.test not in ("max_steps", "time_limit",
                                                        "should_stop"))
    except KeyboardInterrupt:  # Ctrl-C (or a caller's `_thread.interrupt_main`)
        run.stopped, run.test = "interrupted", "keyboard_interrupt"
    finally:
        bar.close()
    return _result(run, setup)
