r"""A fit through a normal map's storage: BC5 blocks or 8-bit codes, fitted to the shading.

A float fit (`jaxnm.fit.fit_normal_map`) finds the map whose rendering matches the targets;
shipping it as BC5 then hands it to a block encoder that minimises the error in *codes*,
blind to the shading. `fit_stored_map` instead fits what is stored:

- **BC5** (``storage="bc5"``): two BC4 blocks per 4x4 texels (`jaxnm.storage`). For fixed
  indices and mode a block's texels are affine in its two endpoints
  (`jaxnm.storage.bc4_weights`), so the endpoints are fitted to the fit's own shading
  residuals (`jaxnm.fit.model.map_residuals`) by Levenberg–Marquardt with the fit's
  conjugate-gradient inner solves (`jaxnm.fit.texel_lm`), alternating with re-indexing:
  each texel takes the palette entry nearest the start's float code.
- **8-bit codes** (``storage="rgb8"``): the three unsigned 8-bit channels of a PNG, as
  ``jaxnm fit`` writes ``normal_map.png``; the codes themselves are the variables.

**Rounding.** A stored endpoint or code is a byte, and a decoder truncates a BC4 palette
entry to a byte (texture2ddecoder, Pillow). Each round first fits the endpoints (or codes)
as real numbers, then goes on with the rounding in the loop: the residuals are those of the
rounded (and truncated) values, their Jacobian passes the rounding straight through (a
straight-through estimator), and a step is kept when the loss of the rounded map does not
rise. Every loss reported is that of the map as stored: the stored bytes decoded by the
decoder library.

**Start.** A `FitResult` or an (h, w, 3) map of unit normals (the float fit; None runs
`fit_normal_map` first). Its 8-bit codes, compressed by ``encoder`` (quicktex by default),
are the first blocks, and `StoredFit.start_loss` is their loss as stored: the float fit
compressed afterwards.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import storage as _st
from ..textures import NormalMapOptions, decode_normal_map, encode_normal_map
from .diagnostics import angular_error, seen_texels
from .model import ModelArgs, map_residuals
from .prepare import Prepared, prepare
from .problem import FitOptions, FitProblem, FitResult
from .solve import fit_normal_map, preconditioner
from .texel_lm import conjugate_gradient

__all__ = ["STORAGES", "StoredFit", "fit_stored_map", "stored_loss", "check_storage"]

#: What `fit_stored_map` fits through: ``"bc5"`` (BC5 blocks, one byte per texel) and
#: ``"rgb8"`` (three unsigned 8-bit channels, ``jaxnm fit``'s ``normal_map.png``).
STORAGES = ("bc5", "rgb8")


@dataclasses.dataclass(frozen=True)
class _Layout:
    """How the variables become texels (static in the compiled step)."""

    storage: str
    size: tuple[int, int]
    green: str
    uv_origin: str


@dataclasses.dataclass
class StoredFit:
    """A map fitted through its storage (`fit_stored_map`).

    **Fields:**
    - `storage`: one of `STORAGES`.
    - `data`: what is stored: for ``"bc5"`` the blocks (bytes, 16 per 4x4 texels, row by
      row of blocks, as `jaxnm.storage.decode_blocks` reads them); for ``"rgb8"`` the
      (h, w, 3) uint8 codes.
    - `texels`: (h, w, C) float32, the stored codes as a decoder reads them, over 255 (C = 2
      for BC5: ``x``, ``y``; 3 for RGB): what a scene's ``normal_map`` takes, with
      `map_options`.
    - `map_options`: the `NormalMapOptions` that decode `texels` (two or three unsigned
      channels, the green convention, the problem's uv origin).
    - `normals`: (h, w, 3) float32, the decoded texels normalised.
    - `loss`: the shading loss ``0.5 |r|^2`` of the map as stored (the fit's model, no
      smoothness term).
    - `start_loss`: the same for the start compressed by the encoder (or rounded to codes):
      the float fit stored afterwards.
    - `float_loss`: the start's own loss, unstored.
    - `errors`: with a ground truth, the mean angular error (degrees, over the seen
      texels) of ``"float"``, ``"start_stored"`` and ``"stored"``; else empty.
    - `history`: one dict per step: ``round``, ``phase`` (``"real"``: unrounded,
      ``"rounded"``: through the rounding, ``"reindex"``), ``loss`` (the phase's own loss
      after the step), ``accepted``.
    - `seconds`: the time it took (not counting the start's fit).
    """

    storage: str
    data: bytes | np.ndarray
    texels: np.ndarray
    map_options: NormalMapOptions
    normals: np.ndarray
    loss: float
    start_loss: float
    float_loss: float
    errors: dict
    history: list
    seconds: float

    def save(self, path: str | os.PathLike) -> None:
        """Write the stored map: a BC5 DDS file (`jaxnm.storage.save_dds_blocks`) or an
        8-bit RGB PNG."""
        if self.storage == "bc5":
            _st.save_dds_blocks(path, self.data, self.texels.shape[:2], format="bc5")
        else:
            from ..io import save_png

            save_png(path, self.data.astype(np.float32) / 255, bits=8)


# --------------------------------------------------------------------------- the model


def _round_ste(x: Array, fn) -> Array:
    """``fn(x)`` forward, the identity's derivative backward (straight-through)."""
    return x + jax.lax.stop_gradient(fn(x) - x)


def _raw(v: Array, fixed, lay: _Layout, rounded: Array) -> Array:
    """The stored texels (h, w, C) in [0, 1] of the variables ``v`` (code units), rounded
    where ``rounded`` (a traced bool: one compiled step for both phases)."""
    q = jnp.where(rounded, _round_ste(v, jnp.round), v)
    if lay.storage == "rgb8":
        return q / 255
    indices, eight = fixed
    c = _st.bc5_decode(q, indices, lay.size, eight_values=eight) * 255
    # the decoder's truncation of a palette entry to a byte
    c = jnp.where(rounded, _round_ste(c, lambda x: jnp.floor(x + 1e-3)), c)
    return c / 255


def _decode(raw: Array, lay: _Layout) -> Array:
    return decode_normal_map(raw, encoding="unsigned", channels=raw.shape[-1],
                             green=lay.green, uv_origin=lay.uv_origin)


def _flat(normals: Array, args: ModelArgs) -> Array:
    return jnp.concatenate([r.reshape(-1) for r in map_residuals(normals, args)])


@functools.partial(jax.jit, static_argnames=("lay",))
def _lm_step(u, scale, lam, rounded, cg_steps, fixed, args, *, lay):
    """One Levenberg–Marquardt step in the scaled variables ``u`` (``v = u scale``, clipped
    to 0..255): the damped Gauss–Newton move by conjugate gradients, and the loss before
    and after. ``lam <= 0``: start the damping at a hundredth of the curvature along the
    gradient."""
    def fn(u_):
        v = jnp.clip(u_ * scale, 0.0, 255.0)
        return _flat(_decode(_raw(v, fixed, lay, rounded), lay), args)

    r, lin = jax.linearize(fn, u)
    transpose = jax.linear_transpose(lin, u)
    g = transpose(r)[0]
    jg = lin(g)
    lam = jnp.where(lam > 0, lam,
                    1e-2 * jnp.sum(jg * jg) / jnp.maximum(jnp.sum(g * g), 1e-30))
    delta = conjugate_gradient(lambda x: transpose(lin(x))[0] + lam * x, -g, cg_steps)
    jd = lin(delta)
    predicted = -(jnp.sum(g * delta) + 0.5 * jnp.sum(jd * jd))
    u_new = jnp.clip((u + delta) * scale, 0.0, 255.0) / scale
    r_new = fn(u_new)
    return u_new, 0.5 * jnp.sum(r * r), 0.5 * jnp.sum(r_new * r_new), predicted, lam


@jax.jit
def _loss_of(normals, args):
    r = _flat(normals, args)
    return 0.5 * jnp.sum(r * r)


def stored_loss(texels: np.ndarray, map_options: NormalMapOptions, args: ModelArgs) -> float:
    """The shading loss ``0.5 |r|^2`` (no smoothness term) of a stored map's ``texels``
    (h, w, C) in [0, 1], decoded with ``map_options``, under the model ``args``."""
    n = decode_normal_map(jnp.asarray(texels, jnp.float32), encoding=map_options.encoding,
                          channels=map_options.channels, green=map_options.green,
                          uv_origin=map_options.uv_origin)
    return float(_loss_of(n, args))


# --------------------------------------------------------------------------- BC5 blocks


#: Index remaps that swap a BC4 block's endpoints and keep its texels: eight-value mode
#: (``i -> 9 - i``), six-value mode (``i -> 7 - i`` for 2..5; 6 and 7 are the end codes).
_SWAP8 = np.array([1, 0, 7, 6, 5, 4, 3, 2], np.uint8)
_SWAP6 = np.array([1, 0, 5, 4, 3, 2, 6, 7], np.uint8)


def _canonical(e: np.ndarray, idx: np.ndarray, eight: np.ndarray):
    """Rounded endpoints, indices and modes (fitted with the mode held fixed) as a BC4
    block stores them: the mode is ``e_0 > e_1``, so a block whose endpoints crossed has
    them swapped and its indices remapped, and an eight-value block whose endpoints met
    takes index 0 everywhere (its palette is one value). Same texels, valid bytes."""
    e, idx = e.copy(), idx.copy()
    e0, e1 = e[..., 0], e[..., 1]
    equal8 = eight & (e0 == e1)
    swap8 = eight & (e0 < e1)
    swap6 = ~eight & (e0 > e1)
    idx[swap8] = _SWAP8[idx[swap8]]
    idx[swap6] = _SWAP6[idx[swap6]]
    idx[equal8] = 0
    swap = swap8 | swap6
    e[swap] = e[swap][:, ::-1]
    return e, idx, e[..., 0] > e[..., 1]


def _palettes(e: np.ndarray, eight: np.ndarray) -> np.ndarray:
    """(..., 8) each block's palette as a decoder gives it (truncated to bytes)."""
    w, c = _st.bc4_weights(np.broadcast_to(np.arange(8), e.shape[:-1] + (8,)), eight)
    p = np.einsum("...ik,...k->...i", np.asarray(w, np.float64), e.astype(np.float64))
    return np.floor(p + np.asarray(c, np.float64) + 1e-6)


def _reindex(e: np.ndarray, eight: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Each texel's index: the palette entry nearest its ``target`` code (..., 16)."""
    p = _palettes(e, eight)
    return np.argmin(np.abs(p[..., None, :] - target[..., None]), -1).astype(np.uint8)


def _blockwise(codes: np.ndarray) -> np.ndarray:
    """(h, w, 2) -> (h/4, w/4, 2, 16): each block's texels per channel, row-major."""
    h, w, _ = codes.shape
    return codes.reshape(h // 4, 4, w // 4, 4, 2).transpose(0, 2, 4, 1, 3).reshape(
        h // 4, w // 4, 2, 16)


# --------------------------------------------------------------------------- the fit


def _start_normals(problem, options, start, prep, progress) -> tuple[np.ndarray, float]:
    if start is None:
        start = fit_normal_map(problem, options, prepared=prep, progress=progress)
    n = start.normals if isinstance(start, FitResult) else start
    n = np.asarray(n, np.float64)
    if n.shape != tuple(problem.map_size) + (3,):
        raise ValueError(f"{problem.source}: the start map is {n.shape}, expected "
                         f"{tuple(problem.map_size) + (3,)}")
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def check_storage(problem: FitProblem, storage: str) -> None:
    """Raise a one-line `ValueError` where ``problem``'s map cannot be stored as ``storage``
    (an unknown storage, a BC5 map whose sides are not multiples of 4 texels, or the
    ``storage`` extra missing), before anything is fitted."""
    if storage not in STORAGES:
        raise ValueError(f"fit_stored_map: unknown storage={storage!r}; expected one of "
                         f"{', '.join(repr(s) for s in STORAGES)}")
    h, w = (int(s) for s in problem.map_size)
    if storage == "bc5":
        if h % 4 or w % 4:
            raise ValueError(f"{problem.source}: a BC5 map must be a multiple of 4 texels on "
                             f"each side, got {w}x{h}")
        for module in ("quicktex", "texture2ddecoder", "PIL"):
            _st.require_module(module)


def fit_stored_map(problem: FitProblem, options: FitOptions = FitOptions(), *,
                   storage: str = "bc5", start: FitResult | np.ndarray | None = None,
                   encoder: str = "quicktex", green: str = "up", rounds: int = 2,
                   steps: int = 6, cg_steps: int | None = None,
                   ground_truth: np.ndarray | None = None,
                   error_texels: np.ndarray | None = None,
                   prepared: Prepared | None = None, progress: bool = False,
                   should_stop: Callable[[], bool] | None = None) -> StoredFit:
    """Fit ``problem``'s normal map as it will be stored: BC5 blocks or 8-bit codes whose
    decoded map best matches the targets' shading (see `jaxnm.fit.stored`).

    **Arguments:**
    - `problem`, `options`: as `fit_normal_map`'s (`options` also runs the start's fit when
      `start` is None; ``options.lsmr_steps`` is the default of `cg_steps`).
    - `storage`: one of `STORAGES`. BC5 needs the map's size to be a multiple of 4 texels.
    - `start`: the float fit (a `FitResult` or (h, w, 3) unit normals), or None to run it.
    - `encoder`: the BC5 encoder of the first blocks (`jaxnm.storage.ENCODERS`).
    - `green`: the stored map's green convention (``"up"`` or ``"down"``); the uv origin is
      the problem's (``problem.sampling``).
    - `rounds`: BC5: endpoint fits, each after re-indexing the previous one's blocks (the
      first keeps the encoder's indices); 8-bit: passes of the code fit.
    - `steps`: Levenberg–Marquardt steps per phase (unrounded, then through the rounding).
    - `cg_steps`: conjugate-gradient iterations per step.
    - `ground_truth`, `error_texels`: (h, w, 3) normals and (h, w) bool texels
      (default: `seen_texels`) for `StoredFit.errors`.
    - `prepared`: reuse a `prepare(problem)` result. `progress`: a line per round on stderr.
    - `should_stop`: called after each round; when it returns True the fit ends there,
      keeping the best data so far (a command line's Ctrl-C).

    **Returns:** a `StoredFit`: the stored data, its decoded map, and its loss as stored
    beside the start's (float, and compressed afterwards).
    """
    check_storage(problem, storage)
    h, w = (int(s) for s in problem.map_size)
    for name, v, lo in (("rounds", rounds, 1), ("steps", steps, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ValueError(f"fit_stored_map: {name} must be an integer >= {lo}, got {v!r}")
    cg_steps = int(options.lsmr_steps if cg_steps is None else cg_steps)
    prep = prepared if prepared is not None else prepare(problem)
    n0 = _start_normals(problem, options, start, prep, progress)
    t0 = time.perf_counter()
    uv_origin = problem.sampling.uv_origin
    lay = _Layout(storage, (h, w), green, uv_origin)
    channels = 2 if storage == "bc5" else 3
    map_options = NormalMapOptions(encoding="unsigned", channels=channels, green=green,
                                   uv_origin=uv_origin, wrap=problem.sampling.wrap,
                                   filter=problem.sampling.filter)
    args = ModelArgs.create(prep, reduce=True)
    # the start's codes, unrounded (the re-indexing's targets) and as bytes
    target = np.asarray(encode_normal_map(n0, channels=channels, green=green,
                                          uv_origin=uv_origin), np.float64) * 255
    texel_scale = np.asarray(preconditioner(prep))[..., 0]  # (h, w)
    float_loss = float(_loss_of(jnp.asarray(n0), args))
    run = _StoredRun(lay, map_options, args, steps, cg_steps,
                     _start_blocks(storage, target, texel_scale, encoder))
    start_data = run.data
    start_loss = run.loss_of(start_data)
    best = _stored_rounds(run, rounds, start_loss, progress, should_stop)
    loss_final, data = best
    texels = run.as_stored(data)
    dec = np.asarray(_decode(jnp.asarray(texels), lay), np.float64)
    normals = (dec / np.linalg.norm(dec, axis=-1, keepdims=True)).astype(np.float32)
    errors = {}
    if ground_truth is not None:
        seen = (seen_texels(prep, (h, w)) if error_texels is None
                else np.asarray(error_texels, bool))
        start_dec = np.asarray(_decode(jnp.asarray(run.as_stored(start_data)), lay), np.float64)
        for name, m in (("float", n0), ("start_stored", start_dec), ("stored", dec)):
            errors[name] = float(angular_error(m, ground_truth)[seen].mean())
    return StoredFit(storage=storage, data=data, texels=texels, map_options=map_options,
                     normals=normals, loss=float(loss_final), start_loss=float(start_loss),
                     float_loss=float_loss, errors=errors, history=run.history,
                     seconds=time.perf_counter() - t0)


def _start_blocks(storage: str, target: np.ndarray, texel_scale: np.ndarray, encoder: str):
    """The stored fit's start from the float fit's unrounded codes ``target`` (h, w, C):
    ``(data, v, scale, idx, eight, tblocks)``, the stored data (BC5 blocks by ``encoder``,
    or the rounded codes), the variables (BC5: the blocks' endpoints; 8-bit: the codes)
    with their scales from the texels' (`preconditioner`), and for BC5 the blocks'
    indices, whether each uses 8 levels, and the targets block by block."""
    h, w = texel_scale.shape
    codes = np.clip(np.round(target), 0, 255).astype(np.uint8)
    if storage == "rgb8":
        v = target.astype(np.float32)
        scale = np.broadcast_to(texel_scale[..., None], v.shape).astype(np.float32)
        return codes, v, scale, None, None, None
    data = _st.encode_blocks(codes, format="bc5", encoder=encoder)
    e, idx = _st.bc5_blocks(data, (h, w))
    eight = e[..., 0] > e[..., 1]
    v = e.astype(np.float32)
    block_scale = texel_scale.reshape(h // 4, 4, w // 4, 4).mean((1, 3))
    scale = np.broadcast_to(block_scale[:, :, None, None], v.shape).astype(np.float32)
    return data, v, scale, idx, eight, _blockwise(target)


class _StoredRun:
    """A stored fit in progress: its layout and model, the current variables ``v`` and
    stored ``data`` (BC5: with the blocks' ``idx`` and ``eight``), and its history."""

    def __init__(self, lay, map_options, args, steps, cg_steps, start):
        self.lay, self.map_options, self.args = lay, map_options, args
        self.steps, self.cg_steps = steps, cg_steps
        self.data, self.v, self.scale, self.idx, self.eight, self.tblocks = start
        self.scale_d = jax.device_put(self.scale)
        self.history: list = []

    def as_stored(self, data) -> np.ndarray:
        """The texels (h, w, C) in [0, 1] that ``data`` stores."""
        if self.lay.storage == "rgb8":
            return np.asarray(data, np.float32) / 255
        return _st.decode_blocks(data, self.lay.size, format="bc5").astype(np.float32) / 255

    def loss_of(self, data) -> float:
        """The fit's loss of the map ``data`` stores."""
        return stored_loss(self.as_stored(data), self.map_options, self.args)

    def phase(self, rnd: int, phase: str, fixed, rounded: bool) -> None:
        """Up to ``steps`` Levenberg–Marquardt steps from ``v`` (through the rounding where
        ``rounded``), each recorded in the history; ``v`` becomes the last accepted."""
        u = jax.device_put((self.v / self.scale).astype(np.float32))
        lam = np.float32(-1.0)
        for _ in range(self.steps):
            u_new, f, f_new, pred, lam = _lm_step(u, self.scale_d, lam, np.bool_(rounded),
                                                  np.int32(self.cg_steps), fixed, self.args,
                                                  lay=self.lay)
            f, f_new, pred = float(f), float(f_new), float(pred)
            gain = f - f_new
            accepted = gain >= 0 if rounded else gain > 0.01 * max(pred, 0.0)
            self.history.append({"round": rnd, "phase": phase, "accepted": bool(accepted),
                                 "loss": f_new if accepted else f})
            if accepted:
                u = u_new
                lam = lam / 3.5 if pred > 0 and gain > 0.99 * pred else lam
            else:
                lam = 4.0 * lam
            if pred <= 1e-7 * f:  # nothing left to gain at this rounding
                break
        self.v = np.asarray(u) * self.scale

    def quantized(self):
        """The stored data of the rounded variables, and (BC5) the canonical endpoints and
        levels they give."""
        q = np.clip(np.round(self.v), 0, 255)
        if self.lay.storage == "rgb8":
            return q.astype(np.uint8), None, None
        e_q, idx_q, eight_q = _canonical(q.astype(np.uint8), self.idx, self.eight)
        return _st.pack_bc4_blocks(e_q.reshape(-1, 2), idx_q.reshape(-1, 16)), e_q, eight_q

    def reindex(self, rnd: int, e, eight) -> None:
        """BC5: new indices for endpoints ``e`` (the targets' nearest levels), the endpoints
        the variables again; the loss as stored recorded."""
        self.eight = eight
        self.idx = _reindex(e, eight, self.tblocks)
        self.v = e.astype(np.float32)
        self.history.append({"round": rnd + 1, "phase": "reindex", "accepted": True,
                             "loss": self.loss_of(_st.pack_bc4_blocks(
                                 e.reshape(-1, 2), self.idx.reshape(-1, 16)))})


def _stored_rounds(run: _StoredRun, rounds: int, start_loss: float, progress: bool,
                   should_stop) -> tuple[float, np.ndarray]:
    """`fit_stored_map`'s rounds: each fits the variables unrounded, then through the
    rounding, and stores them; BC5 re-indexes the blocks before the next. Returns the best
    ``(loss as stored, data)``, the start's included."""
    best = (start_loss, run.data)
    storage = run.lay.storage
    for rnd in range(rounds):
        fixed = None if storage == "rgb8" else (jnp.asarray(run.idx), jnp.asarray(run.eight))
        run.phase(rnd, "real", fixed, False)
        run.phase(rnd, "rounded", fixed, True)
        run.data, e_q, eight_q = run.quantized()
        loss_now = run.loss_of(run.data)
        if progress:
            print(f"stored fit ({storage}) round {rnd + 1}/{rounds}: loss as stored "
                  f"{loss_now:.5g} (start {start_loss:.5g})", file=sys.stderr, flush=True)
        if loss_now < best[0]:
            best = (loss_now, run.data)
        elif rnd > 0:
            break  # re-indexing found nothing better
        if should_stop is not None and should_stop():
            break
        if storage == "bc5" and rnd + 1 < rounds:
            run.reindex(rnd, e_q, eight_q)
    return best
