r"""Texture sampling with GL semantics, mipmaps, normal-map decoding and sRGB.

**Layout and coordinates.** Textures are floating-point arrays ``(H, W, C)`` in
*image layout*: row 0 is the top row of the image file. Texture coordinates
``uv`` follow the GL texel-centre convention: ``u = 0`` is the left edge of
column 0 and texel column ``c`` has its centre at ``u = (c + 0.5) / W``. The
vertical origin is chosen with ``uv_origin``:

- ``"bottom_left"`` (default; OpenGL, OBJ, modelling packages): ``v = 0`` is the
  bottom edge of the image as displayed and row ``r`` has its centre at
  ``v = 1 - (r + 0.5) / H``. This is what GL does after the usual vertical flip
  on upload.
- ``"top_left"`` (glTF, Direct3D, and GL when the file is uploaded unflipped):
  ``v = 0`` is the top edge and row ``r`` has its centre at ``v = (r + 0.5) / H``.

**Filtering** follows the GL 4.5 specification (section 8.14): wrap modes act on
integer texel indices (``"repeat"``, ``"clamp"`` = ``CLAMP_TO_EDGE``,
``"mirror"`` = ``MIRRORED_REPEAT``); ``"nearest"`` is ``GL_NEAREST``,
``"bilinear"`` is ``GL_LINEAR`` on level 0 and ``"trilinear"`` is
``GL_LINEAR_MIPMAP_LINEAR`` with the exact isotropic scale factor (see `lod`).

**Plans.** In a normal-map fit the uvs and their screen derivatives are fixed
while the texels change, so sampling is split into `plan_sample` (integer
indices into the concatenated flattened mip levels, and weights; computed once)
and `apply_plan` (one gather and one weighted sum; linear in the texels and
differentiable). `sample` composes the two.

**Normal maps** are filtered as stored (like the GPU) and decoded afterwards
with `decode_normal_map`; see there for the green-channel convention.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.custom_derivatives import SymbolicZero
from jax.typing import ArrayLike
from jaxtyping import Float, Real

from ._exec.sums import SumTables, sum_by_tables, sum_tables
from .interpolate import Attribute
from .numerics import safe_normalize, safe_sqrt, tiny

__all__ = [
    "NormalMapOptions", "MAP_SPACES", "FILTERS", "WRAPS", "UV_ORIGINS", "ENCODINGS", "GREENS",
    "SamplePlan", "mip_sizes", "build_mipmaps", "lod", "plan_sample", "apply_plan", "sample",
    "decode_normal_map", "encode_normal_map", "srgb_to_linear", "linear_to_srgb", "quantize",
    "plan_sum_tables", "transpose_plan", "box_filter_matrix"
]

FILTERS = ("nearest", "bilinear", "trilinear")
WRAPS = ("repeat", "clamp", "mirror")
UV_ORIGINS = ("bottom_left", "top_left")
ENCODINGS = ("unsigned", "unsigned_exact", "signed")
GREENS = ("up", "down")
#: What a map's texels mean: tangent-space normals, object-space normals, or a derivative
#: map ``(dh/du, dh/dv)`` (Mikkelsen's surface-gradient bump mapping).
MAP_SPACES = ("tangent", "object", "derivative")


def _check_option(func: str, name: str, value, valid: Sequence) -> None:
    if value not in valid:
        raise ValueError(f"{func}: unknown {name}={value!r}; expected one of "
                         f"{', '.join(repr(v) for v in valid)}")


def _check_float(func: str, name: str, x: Array, image: bool = True) -> None:
    if not jnp.issubdtype(x.dtype, jnp.floating):
        hint = " (convert integer image data with x / (2**bits - 1) first)" if image else ""
        raise ValueError(f"{func}: `{name}` must be floating point{hint}, got {x.dtype}")


def _check_texture(func: str, name: str, tex: Array) -> None:
    if tex.ndim != 3:
        raise ValueError(f"{func}: `{name}` must have shape (H, W, C), got {tex.shape}")
    _check_float(func, name, tex)


@dataclasses.dataclass(frozen=True)
class NormalMapOptions:
    """How a normal map's texels are decoded and sampled (hashable: a static argument).

    Validated when constructed, however it was built (a scene file, Python code,
    `dataclasses.replace`), so a bad option is refused before anything compiles.

    **Fields:**
    - `encoding`: one of `ENCODINGS`: ``"unsigned"`` (``2x - 1``),
      ``"unsigned_exact"`` (Schüler's exact expansion ``x*255/127 - 128/127``
      for 8 bits), or ``"signed"`` (values already in [-1, 1]).
    - `channels`: 3, or 2 (``z = sqrt(max(0, 1 - x^2 - y^2))``).
    - `green`: one of `GREENS`: ``"up"`` (OpenGL: +green points to the top of
      the image as displayed) or ``"down"`` (DirectX). With
      ``uv_origin="bottom_left"``, "up" means the map's +y is along +v.
    - `strength`: a finite number that scales the map's x and y.
    - `uv_origin`: one of `UV_ORIGINS` (``"bottom_left"``: OpenGL/OBJ;
      ``"top_left"``: glTF/D3D images).
    - `wrap`, `filter`: texture sampling, one of `WRAPS` and `FILTERS`.
    - `space`: one of `MAP_SPACES`: ``"tangent"``, ``"object"`` (an object-space
      normal map), or ``"derivative"`` (a derivative map ``(dh/du, dh/dv)`` in
      world units per unit of uv; scene files give a ``height_map`` instead,
      converted on load).
    - `bits`: bit depth of the stored values, 2 to 16 (used by ``"unsigned_exact"``).
    """

    encoding: str = "unsigned"
    channels: int = 3
    green: str = "up"
    strength: float = 1.0
    uv_origin: str = "bottom_left"
    wrap: str = "repeat"
    filter: str = "trilinear"
    space: str = "tangent"
    bits: int = 8

    def __post_init__(self):
        name = "NormalMapOptions"
        _check_normal_options(name, self.encoding, self.channels, self.green, self.bits,
                              self.uv_origin)
        _check_option(name, "wrap", self.wrap, WRAPS)
        _check_option(name, "filter", self.filter, FILTERS)
        _check_option(name, "space", self.space, MAP_SPACES)
        if (isinstance(self.strength, bool) or not isinstance(self.strength, (int, float))
                or not math.isfinite(self.strength)):
            raise ValueError(f"{name}: strength must be a finite number, got {self.strength!r}")


# --------------------------------------------------------------------------- mipmaps


def mip_sizes(size_hw: Sequence[int], levels: int | None = None) -> tuple[tuple[int, int], ...]:
    """The ``(H, W)`` of each mip level, GL style: ``max(1, floor(size / 2))`` per step.

    **Arguments:**
    - `size_hw`: ``(H, W)`` of level 0.
    - `levels`: number of levels, at most the full chain down to 1x1,
      ``floor(log2(max(H, W))) + 1``; None for the full chain.
    """
    if len(size_hw) != 2:
        raise ValueError(f"mip_sizes: size_hw must be (H, W), got {size_hw!r}")
    h, w = int(size_hw[0]), int(size_hw[1])
    if h < 1 or w < 1:
        raise ValueError(f"mip_sizes: size_hw must be positive, got {size_hw!r}")
    full = max(h, w).bit_length()
    if levels is None:
        levels = full
    if not 1 <= levels <= full:
        raise ValueError(f"mip_sizes: levels must be between 1 and {full} for a {h}x{w} "
                         f"texture, got {levels}")
    sizes = [(h, w)]
    for _ in range(levels - 1):
        h, w = max(1, h // 2), max(1, w // 2)
        sizes.append((h, w))
    return tuple(sizes)


def _downsample_axis(x: Array, axis: int) -> Array:
    """Exact box filter from ``N`` to ``max(1, N // 2)`` samples along ``axis`` (0 or 1).

    Output sample ``i`` averages the input interval ``[i N/M, (i+1) N/M)`` by
    area: 2 taps (1/2, 1/2) for even ``N``; for odd ``N = 2n + 1``, 3 taps on
    inputs ``2i, 2i+1, 2i+2`` with weights ``(n - i, n, i + 1) / (2n + 1)``.
    """
    n_in = x.shape[axis]
    if n_in == 1:
        return x

    def take(start, stop):
        return jax.lax.slice_in_dim(x, start, stop, stride=2, axis=axis)

    if n_in % 2 == 0:
        return 0.5 * (take(0, n_in) + take(1, n_in))
    n = n_in // 2
    i = np.arange(n, dtype=np.float64)
    shape = (n, 1, 1) if axis == 0 else (1, n, 1)

    def weight(values):
        return jnp.asarray((values / (2 * n + 1)).reshape(shape), x.dtype)

    return (weight(n - i) * take(0, 2 * n) + weight(np.full(n, float(n))) * take(1, 2 * n)
            + weight(i + 1) * take(2, 2 * n + 1))


def box_filter_matrix(n_in: int) -> np.ndarray:
    """(max(1, n_in // 2), n_in) float64: `build_mipmaps`' box filter along one axis of
    ``n_in`` texels as a matrix (an axis of 1 kept), for
    host-side work through the mip chain, such as its transpose."""
    if n_in == 1:
        return np.ones((1, 1))
    n_out = n_in // 2
    m = np.zeros((n_out, n_in))
    i = np.arange(n_out)
    if n_in % 2 == 0:
        m[i, 2 * i] = m[i, 2 * i + 1] = 0.5
    else:
        n = n_out
        m[i, 2 * i], m[i, 2 * i + 1], m[i, 2 * i + 2] = (n - i) / n_in, n / n_in, (i + 1) / n_in
    return m


def _renormalize(x: Array) -> Array:
    xyz = safe_normalize(x[..., :3])  # a vanishing average becomes the zero vector
    return jnp.concatenate([xyz, x[..., 3:]], -1) if x.shape[-1] > 3 else xyz


def build_mipmaps(tex: Float[ArrayLike, "H W C"], *, levels: int | None = None,
                  renormalize: bool = False) -> tuple[Float[Array, "_ _ C"], ...]:
    r"""Mip chain of a texture by repeated exact box filtering.

    Level ``k + 1`` has size ``max(1, floor(size_k / 2))`` per axis (GL) and is
    the area average of level ``k`` over each output texel's footprint,
    separably: a 2x2 box for even sizes; along an odd axis ``N = 2n + 1`` each
    output texel ``i`` covers ``N / n`` input texels and takes inputs
    ``2i, 2i+1, 2i+2`` with weights ``(n - i, n, i + 1) / (2n + 1)`` (an axis of
    size 1 is kept). The weights of every input texel sum to the same value, so
    each level has exactly the mean of the previous one, and a constant stays
    constant. (``glGenerateMipmap`` leaves the filter to the implementation.)

    **Arguments:**
    - `tex`: level 0, ``(H, W, C)`` float, image layout.
    - `levels`: number of levels to return; None for the full chain to 1x1.
    - `renormalize`: for *decoded* normal maps (unit vectors in channels 0-2;
      further channels are filtered but not touched): normalise the xyz of
      every level after level 0, as CryEngine's Resource Compiler does. Each
      level is filtered from the (renormalised) previous one. Where the
      average vanishes (opposite normals) the result is the zero vector, with
      zero gradient; the frame stage then falls back to the unperturbed normal.
      Level 0 is returned as given. Leave False for raw (encoded) maps and
      colour textures.

    **Returns:** a tuple of ``(H_k, W_k, C)`` arrays, level 0 first. Every level
    is a differentiable function of level 0.
    """
    tex = jnp.asarray(tex)
    _check_texture("build_mipmaps", "tex", tex)
    if renormalize and tex.shape[-1] < 3:
        raise ValueError("build_mipmaps: renormalize=True needs at least 3 channels (xyz), "
                         f"got shape {tex.shape}")
    return _build_mipmaps(tex, len(mip_sizes(tex.shape[:2], levels)), bool(renormalize))


@functools.partial(jax.jit, static_argnums=(1, 2))
def _build_mipmaps(tex: Array, levels: int, renormalize: bool) -> tuple[Array, ...]:
    out = [tex]
    for _ in range(levels - 1):
        nxt = _downsample_axis(_downsample_axis(out[-1], 0), 1)
        out.append(_renormalize(nxt) if renormalize else nxt)
    return tuple(out)


# --------------------------------------------------------------------------- level of detail


def lod(duvdx: ArrayLike, duvdy: ArrayLike, size_hw: Sequence[int]) -> Array:
    r"""GL level of detail ``lambda = log2(rho)`` from the screen derivatives of uv.

    .. math::
        \rho = \max\Big(\sqrt{(W\,\partial_x u)^2 + (H\,\partial_x v)^2},\;
                        \sqrt{(W\,\partial_y u)^2 + (H\,\partial_y v)^2}\Big)

    (GL 4.5, section 8.14.1, with the exact square roots and no approximation of
    the max). The sign of the derivatives
    does not matter, so ``dFdy`` with window y up or down gives the same value.

    **Arguments:**
    - `duvdx`, `duvdy`: ``(..., 2)`` derivatives of ``(u, v)`` per pixel step.
    - `size_hw`: ``(H, W)`` of level 0.

    **Returns:** ``(...)``. Where ``rho^2 <= tiny(dtype)`` (e.g. background
    pixels with zero derivatives) it returns ``0.5 * log2(tiny)`` (about -50 in
    float32), i.e. magnification / level 0, with zero gradient.
    """
    duvdx = jnp.asarray(duvdx)
    duvdy = jnp.asarray(duvdy)
    if duvdx.shape[-1:] != (2,) or duvdy.shape != duvdx.shape:
        raise ValueError("lod: duvdx and duvdy must both have shape (..., 2), got "
                         f"{duvdx.shape} and {duvdy.shape}")
    return _lod(duvdx, duvdy, tuple(int(s) for s in size_hw))


@functools.partial(jax.jit, static_argnums=2)
def _lod(duvdx: Array, duvdy: Array, size_hw: tuple[int, int]) -> Array:
    h, w = size_hw
    rho2_x = (duvdx[..., 0] * w) ** 2 + (duvdx[..., 1] * h) ** 2
    rho2_y = (duvdy[..., 0] * w) ** 2 + (duvdy[..., 1] * h) ** 2
    rho2 = jnp.maximum(rho2_x, rho2_y)
    small = tiny(rho2.dtype)
    ok = rho2 > small
    return jnp.where(ok, 0.5 * jnp.log2(jnp.where(ok, rho2, 1.0)), 0.5 * math.log2(small))


# --------------------------------------------------------------------------- sampling plans


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SamplePlan:
    """Where and how much each pixel reads from a mip chain (a pytree).

    **Fields:**
    - `index`: ``(..., T)`` int32 indices into the texels of the levels
      ``level_shapes``, flattened row-major per level and concatenated
      (level 0 first). Always in bounds.
    - `weight`: ``(..., T)`` float weights (they sum to 1 per pixel);
      differentiable functions of uv (and, for trilinear, of its derivatives).
    - `filter`, `wrap`, `uv_origin` (static): the modes the plan was made with.
    - `level_shapes` (static): ``(H_k, W_k)`` of each level the plan reads.

    ``T`` is 1 (nearest), 4 (bilinear) or 8 (trilinear: 4 taps on each of
    two levels).
    """

    index: Array
    weight: Array
    filter: str = dataclasses.field(metadata=dict(static=True), default="bilinear")
    wrap: str = dataclasses.field(metadata=dict(static=True), default="repeat")
    uv_origin: str = dataclasses.field(metadata=dict(static=True), default="bottom_left")
    level_shapes: tuple[tuple[int, int], ...] = dataclasses.field(
        metadata=dict(static=True), default=())

    @property
    def num_taps(self) -> int:
        return self.index.shape[-1]


def _wrap(i: Array, n, mode: str) -> Array:
    """GL wrap of integer texel indices ``i`` into ``[0, n)`` (``n`` int or like ``i``)."""
    if mode == "repeat":
        return jnp.mod(i, n)
    if mode == "clamp":
        return jnp.clip(i, 0, n - 1)
    m = jnp.mod(i, 2 * n)  # mirrored repeat: 0..n-1, then n-1..0
    return jnp.where(m < n, m, 2 * n - 1 - m)


def _linear_taps(s: Array, t: Array, h, w, offset, wrap: str, flip: bool):
    """``GL_LINEAR`` on one level: 4 flat indices and weights, each ``(..., 4)``.

    ``s, t`` are in GL texture space (``t = 0`` at the first stored row); ``h, w``
    and ``offset`` are Python ints or int arrays shaped like ``s``. With
    ``flip`` GL row ``j`` is image row ``h - 1 - j``.
    """
    dtype = s.dtype
    wf = w if isinstance(w, int) else w.astype(dtype)
    hf = h if isinstance(h, int) else h.astype(dtype)
    x = s * wf - 0.5
    y = t * hf - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    a = x - x0
    b = y - y0
    i0 = x0.astype(jnp.int32)
    j0 = y0.astype(jnp.int32)
    c0, c1 = _wrap(i0, w, wrap), _wrap(i0 + 1, w, wrap)
    r0, r1 = _wrap(j0, h, wrap), _wrap(j0 + 1, h, wrap)
    if flip:
        r0, r1 = h - 1 - r0, h - 1 - r1
    base0 = offset + r0 * w
    base1 = offset + r1 * w
    index = jnp.stack([base0 + c0, base0 + c1, base1 + c0, base1 + c1], -1)
    weight = jnp.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], -1)
    return index, weight


def _nearest_taps(s: Array, t: Array, h: int, w: int, wrap: str, flip: bool):
    c = _wrap(jnp.floor(s * w).astype(jnp.int32), w, wrap)
    r = _wrap(jnp.floor(t * h).astype(jnp.int32), h, wrap)
    if flip:
        r = h - 1 - r
    return (r * w + c)[..., None], jnp.ones_like(s)[..., None]


def plan_sample(uv: ArrayLike | Attribute, duvdx: ArrayLike | None = None,
                duvdy: ArrayLike | None = None, *, size_hw: Sequence[int], levels: int = 1,
                filter: str = "bilinear", wrap: str = "repeat",
                uv_origin: str = "bottom_left", lod_bias: ArrayLike = 0.0) -> SamplePlan:
    r"""Plan GL texture lookups: which texels each pixel reads and with what weight.

    **Arguments:**
    - `uv`: ``(..., 2)`` texture coordinates, or an `Attribute` whose ``value``,
      ``ddx`` and ``ddy`` supply `uv`, `duvdx` and `duvdy`. Any finite value is
      allowed (background pixels hold 0); indices always land in bounds.
    - `duvdx`, `duvdy`: ``(..., 2)`` screen derivatives; needed for trilinear.
    - `size_hw`: ``(H, W)`` of level 0 (static).
    - `levels`: number of mip levels available (trilinear only; the other
      filters read level 0).
    - `filter`: ``"nearest"`` (``GL_NEAREST``: texel ``floor(u W)``, 1 tap),
      ``"bilinear"`` (``GL_LINEAR`` on level 0, 4 taps) or ``"trilinear"``
      (``GL_LINEAR_MIPMAP_LINEAR``, 8 taps): ``lambda = lod(...) + lod_bias``
      clamped to ``[0, levels - 1]``, bilinear on levels ``floor(lambda)`` and
      ``min(floor(lambda) + 1, levels - 1)``, blended by ``frac(lambda)``.
    - `wrap`: ``"repeat"``, ``"clamp"`` (to edge) or ``"mirror"`` (mirrored
      repeat), applied to texel indices as in GL.
    - `uv_origin`: ``"bottom_left"`` or ``"top_left"`` (see the module docs).
    - `lod_bias`: added to lambda (trilinear), like ``GL_TEXTURE_LOD_BIAS``.

    **Returns:** a `SamplePlan` for `apply_plan`. The modes, `size_hw` and
    `levels` are static: under `jax.jit` pass them as static arguments.
    """
    if isinstance(uv, Attribute):
        duvdx = uv.ddx if duvdx is None else duvdx
        duvdy = uv.ddy if duvdy is None else duvdy
        uv = uv.value
    _check_option("plan_sample", "filter", filter, FILTERS)
    _check_option("plan_sample", "wrap", wrap, WRAPS)
    _check_option("plan_sample", "uv_origin", uv_origin, UV_ORIGINS)
    uv = jnp.asarray(uv)
    _check_float("plan_sample", "uv", uv, image=False)
    if uv.shape[-1:] != (2,):
        raise ValueError(f"plan_sample: uv must have shape (..., 2), got {uv.shape}")
    sizes = mip_sizes(size_hw, levels)
    if filter != "trilinear":
        return _plan_sample(uv, None, None, None, sizes[:1], filter, wrap, uv_origin)
    if duvdx is None or duvdy is None:
        raise ValueError("plan_sample: filter='trilinear' needs duvdx and duvdy")
    duvdx = jnp.asarray(duvdx, uv.dtype)
    duvdy = jnp.asarray(duvdy, uv.dtype)
    if duvdx.shape != uv.shape or duvdy.shape != uv.shape:
        raise ValueError(f"plan_sample: duvdx {duvdx.shape} and duvdy {duvdy.shape} must "
                         f"have the shape of uv {uv.shape}")
    lod_bias = jnp.asarray(lod_bias, uv.dtype)
    return _plan_sample(uv, duvdx, duvdy, lod_bias, sizes, filter, wrap, uv_origin)


@functools.partial(jax.jit, static_argnums=(4, 5, 6, 7))
def _plan_sample(uv, duvdx, duvdy, lod_bias, sizes, filter, wrap, uv_origin) -> SamplePlan:
    flip = uv_origin == "bottom_left"
    s, t = uv[..., 0], uv[..., 1]
    h, w = sizes[0]
    levels = len(sizes)
    if filter == "nearest":
        index, weight = _nearest_taps(s, t, h, w, wrap, flip)
    elif filter == "bilinear":
        index, weight = _linear_taps(s, t, h, w, 0, wrap, flip)
    else:
        lam = _lod(duvdx, duvdy, sizes[0]) + lod_bias
        lam = jnp.clip(lam, 0.0, float(levels - 1))
        lam0 = jnp.floor(lam)
        frac = lam - lam0
        d0 = lam0.astype(jnp.int32)
        d = jnp.stack([d0, jnp.minimum(d0 + 1, levels - 1)], -1)  # (..., 2) levels
        hs = jnp.asarray([hk for hk, _ in sizes], jnp.int32)[d]
        ws = jnp.asarray([wk for _, wk in sizes], jnp.int32)[d]
        offsets = jnp.asarray(np.cumsum([0] + [hk * wk for hk, wk in sizes[:-1]]), jnp.int32)[d]
        index, weight = _linear_taps(s[..., None], t[..., None], hs, ws, offsets, wrap, flip)
        weight = weight * jnp.stack([1 - frac, frac], -1)[..., None]  # (..., 2, 4)
        index = index.reshape(index.shape[:-2] + (8,))
        weight = weight.reshape(weight.shape[:-2] + (8,))
    return SamplePlan(index.astype(jnp.int32), weight, filter=filter, wrap=wrap,
                      uv_origin=uv_origin, level_shapes=sizes)


def apply_plan(plan: SamplePlan, mips: ArrayLike | Sequence[ArrayLike]) -> Array:
    """Execute a `SamplePlan`: one gather and one weighted sum.

    **Arguments:**
    - `plan`: from `plan_sample`.
    - `mips`: the mip chain (tuple of ``(H_k, W_k, C)``, e.g. from
      `build_mipmaps`) or a single level-0 texture. Levels the plan does not
      read are ignored; the ones it reads must have the planned shapes.

    **Returns:** ``(..., C)`` in the texel dtype. Linear in the texels (so
    differentiable w.r.t. them, and through `build_mipmaps` w.r.t. level 0) and
    differentiable w.r.t. the plan's weights.
    """
    if not isinstance(mips, (tuple, list)):
        mips = (mips,)
    shapes = plan.level_shapes
    if len(mips) < len(shapes):
        raise ValueError(f"apply_plan: the plan reads {len(shapes)} mip levels but only "
                         f"{len(mips)} were given")
    used = [jnp.asarray(m) for m in mips[: len(shapes)]]
    for k, (m, hw) in enumerate(zip(used, shapes)):
        _check_texture("apply_plan", f"mips[{k}]", m)
        if m.shape[:2] != hw or m.shape[-1] != used[0].shape[-1]:
            raise ValueError(f"apply_plan: mips[{k}] has shape {m.shape}; the plan expects "
                             f"{hw + (used[0].shape[-1],)}")
    return _apply_plan(plan, tuple(used))


@jax.jit
def _apply_plan(plan: SamplePlan, used: tuple[Array, ...]) -> Array:
    channels = used[0].shape[-1]
    dtype = jnp.result_type(*used)
    flat = jnp.concatenate([m.reshape(-1, channels).astype(dtype) for m in used], 0)
    return _gather_weighted(flat, plan.index, plan.weight.astype(dtype))


def plan_sum_tables(plan: SamplePlan, indices: Sequence[ArrayLike] | None = None) -> SumTables:
    """The fixed-order texel sums of ``plan``'s gather (each texel's taps grouped once, on the
    host, and summed in a fixed order): what `transpose_plan` needs. Built on the host from
    the plan's concrete indices, or from ``indices`` (a list of index arrays of plans with
    ``plan``'s levels, e.g. the chunks of one: the tables are then stacked, one per
    array)."""
    size = sum(h * w for h, w in plan.level_shapes)
    if indices is None:
        return sum_tables(np.asarray(plan.index), size)
    return sum_tables([np.asarray(i) for i in indices], size)


def transpose_plan(plan: SamplePlan, tables: SumTables, cotangent: ArrayLike,
                   mips: Sequence[ArrayLike]) -> tuple[Array, ...]:
    """The cotangent of `apply_plan` ``(plan, mips)`` w.r.t. ``mips`` for the output
    cotangent ``cotangent`` (..., C): what ``jax.vjp`` gives (a scatter-add of the weighted
    cotangent into the texels), summed instead through ``tables`` (`plan_sum_tables` of
    this plan) in a fixed order: the same on every run, on every device, with no sort. One
    array per level of ``mips`` (zeros for the levels the plan does not read)."""
    cot = jnp.asarray(cotangent)
    channels = cot.shape[-1]
    parts = (plan.weight.astype(cot.dtype)[..., None] * cot[..., None, :]).reshape(-1, channels)
    flat = sum_by_tables(parts, tables)
    out, offset = [], 0
    for k, m in enumerate(mips):
        if k < len(plan.level_shapes):
            h, w = plan.level_shapes[k]
            out.append(flat[offset:offset + h * w].reshape(h, w, channels).astype(m.dtype))
            offset += h * w
        else:
            out.append(jnp.zeros(jnp.shape(m), jnp.result_type(m)))
    return tuple(out)


def _gather(flat: Array, index: Array) -> Array:
    return flat.at[index].get(mode="promise_in_bounds")  # (..., T, C); plans are in bounds


def _weighted_taps(weight: Array, texels: Array) -> Array:
    # unrolled over the few taps: XLA fuses it into the gather (a reduction over the
    # tap axis, or a batched dot, is several times slower on CPU)
    out = weight[..., 0, None] * texels[..., 0, :]
    for t in range(1, weight.shape[-1]):
        out = out + weight[..., t, None] * texels[..., t, :]
    return out


@jax.custom_jvp
def _gather_weighted(flat: Array, index: Array, weight: Array) -> Array:
    """``sum_t weight[..., t] * flat[index[..., t]]``, shape ``(..., C)``."""
    return _weighted_taps(weight, _gather(flat, index))


def _gather_weighted_jvp(primals, tangents):
    # Same values; the tangents are written as contractions so that their transposes
    # (the backward pass) are one outer product feeding one scatter-add, rather than
    # the chain of padded slices that transposing `_weighted_taps` would give.
    flat, index, weight = primals
    dflat, _, dweight = tangents
    texels = _gather(flat, index)
    out = _weighted_taps(weight, texels)
    dout = jnp.zeros_like(out)
    if not isinstance(dflat, SymbolicZero):
        dout = dout + jnp.einsum("...t,...tc->...c", weight, _gather(dflat, index),
                                 precision=jax.lax.Precision.HIGHEST)
    if not isinstance(dweight, SymbolicZero):
        dout = dout + jnp.einsum("...t,...tc->...c", dweight, texels,
                                 precision=jax.lax.Precision.HIGHEST)
    return out, dout


_gather_weighted.defjvp(_gather_weighted_jvp, symbolic_zeros=True)


def sample(mips_or_tex: ArrayLike | Sequence[ArrayLike], uv: ArrayLike | Attribute,
           duvdx: ArrayLike | None = None, duvdy: ArrayLike | None = None, *,
           filter: str = "bilinear", wrap: str = "repeat", uv_origin: str = "bottom_left",
           lod_bias: ArrayLike = 0.0) -> Array:
    """Sample a texture: ``apply_plan(plan_sample(...), mips)``.

    `mips_or_tex` is a mip chain (tuple) or a single ``(H, W, C)`` texture; with
    a single texture and ``filter="trilinear"`` the full chain is built with
    `build_mipmaps` (no renormalisation). A tuple is used as given: trilinear
    then blends among its ``len(mips)`` levels. Other arguments as in
    `plan_sample`. Returns ``(..., C)``.
    """
    if isinstance(mips_or_tex, (tuple, list)):
        mips = tuple(jnp.asarray(m) for m in mips_or_tex)
    else:
        tex = jnp.asarray(mips_or_tex)
        mips = build_mipmaps(tex) if filter == "trilinear" else (tex,)
    _check_texture("sample", "mips[0]", mips[0])
    levels = len(mips) if filter == "trilinear" else 1
    plan = plan_sample(uv, duvdx, duvdy, size_hw=mips[0].shape[:2], levels=levels,
                       filter=filter, wrap=wrap, uv_origin=uv_origin, lod_bias=lod_bias)
    return apply_plan(plan, mips)


# --------------------------------------------------------------------------- normal maps


def _flip_green(green: str, uv_origin: str) -> bool:
    """Whether stored green must be negated to point along +v (the frame's B = grad v)."""
    return (green == "up") != (uv_origin == "bottom_left")


def _check_normal_options(func: str, encoding: str, channels: int, green: str, bits: int,
                          uv_origin: str) -> None:
    _check_option(func, "encoding", encoding, ENCODINGS)
    if not isinstance(channels, (int, np.integer)) or channels not in (2, 3):
        raise ValueError(f"{func}: unknown channels={channels!r}; expected one of 2, 3")
    _check_option(func, "green", green, GREENS)
    _check_option(func, "uv_origin", uv_origin, UV_ORIGINS)
    if not isinstance(bits, (int, np.integer)) or not 2 <= bits <= 16:
        raise ValueError(f"{func}: bits must be an integer between 2 and 16, got {bits!r}")


def decode_normal_map(raw: Real[ArrayLike, "*batch C"], *, encoding: str = "unsigned",
                      channels: int = 3, green: str = "up", strength: ArrayLike = 1.0,
                      bits: int = 8,
                      uv_origin: str = "bottom_left") -> Float[Array, "*batch 3"]:
    r"""Decode (filtered) normal-map values into a tangent-space vector ``(x, y, z)``.

    Apply this *after* filtering, as a shader does after the texture fetch. The
    result is expressed in the frame ``(T, B, N) = (grad u, grad v, N)`` of the
    uv the map is sampled with: ``x`` along +u, ``y`` along +v.

    **Arguments:**
    - `raw`: ``(..., C)`` with ``C >= channels``; the first `channels` are used.
    - `encoding`:
        - ``"unsigned"``: unorm data in [0, 1], expanded by ``2 r - 1``.
        - ``"unsigned_exact"``: Schüler's exact sign expansion of `bits`-bit
          unorm data, ``(r (2^b - 1) - 2^{b-1}) / (2^{b-1} - 1)`` (for 8 bits
          ``r * 255/127 - 128/127``): code ``2^{b-1}`` (128) decodes to exactly 0
          and ``2^b - 1`` (255) to exactly 1, code 1 to exactly -1; results
          below -1 (code 0) are clamped to -1, as snorm hardware maps both -128
          and -127 to -1. Exact for ``r = k / (2^b - 1)`` in float32.
        - ``"signed"``: values already in [-1, 1] (snorm or float maps).
    - `channels`: 3 (xyz stored) or 2 (xy stored, ``z = sqrt(max(0, 1 - x^2 - y^2))``,
      with a zero, not NaN, gradient where the argument is <= 0, e.g. |xy| > 1).
    - `green` (the map's convention, relative to the image *as displayed*):
        - ``"up"``: +green points to the top of the image (the "OpenGL"
          convention: Blender, Unity, glTF; 3ds Max according to Schüler).
        - ``"down"``: +green points to the bottom (the "DirectX" convention:
          Unreal, Substance's DirectX preset).
    - `uv_origin`: the uv convention the map is sampled with (as in
      `plan_sample`). With ``"bottom_left"`` (default) +v points to the top of
      the image, so ``green="up"`` is used as stored (y along +v) and
      ``"down"`` is negated. With ``"top_left"`` +v points *down* the image, so
      ``"up"`` is negated and ``"down"`` is used as stored. (Schüler's GLSL
      samples with the image data at ``t = 0``, i.e. ``top_left``; hence its
      ``GREEN_UP`` branch negates y.)
    - `strength`: scales ``x`` and ``y`` (after z reconstruction; z is
      unchanged), broadcasting against ``(...)``.
    - `bits`: bit depth for ``"unsigned_exact"``, 2 to 16 (8 or 16 in practice).

    **Returns:** ``(..., 3)``, *not* normalised: the frame stage normalises
    after the TBN product. A texel that decodes to the zero vector (e.g. raw
    0.5 grey, or a vanishing filtered average) is finite here and must be
    handled downstream with a safe normalisation whose fallback is the
    unperturbed normal (`jaxnm.numerics.safe_normalize(..., fallback=N)`).
    """
    _check_normal_options("decode_normal_map", encoding, channels, green, bits, uv_origin)
    raw = jnp.asarray(raw)
    _check_float("decode_normal_map", "raw", raw)
    if raw.ndim < 1 or raw.shape[-1] < channels:
        raise ValueError(f"decode_normal_map: raw must have at least {channels} channels, "
                         f"got shape {raw.shape}")
    return _decode(raw, jnp.asarray(strength, raw.dtype), encoding, int(channels),
                   _flip_green(green, uv_origin), int(bits))


@functools.partial(jax.jit, static_argnums=(2, 3, 4, 5))
def _decode(raw: Array, strength: Array, encoding: str, channels: int, flip: bool,
            bits: int) -> Array:
    v = raw[..., :channels]
    if encoding == "unsigned":
        v = 2 * v - 1
    elif encoding == "unsigned_exact":
        half = 2 ** (bits - 1)
        codes = _snap_to_codes(v * (2**bits - 1), 2**bits - 1)
        v = (codes - half) / (half - 1)
        v = jnp.where(v < -1, -1.0, v)
    x, y = v[..., 0], v[..., 1]
    z = v[..., 2] if channels == 3 else safe_sqrt(1 - x * x - y * y)
    if flip:
        y = -y
    return jnp.stack([x * strength, y * strength, z], -1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _snap_to_codes(t: Array, top: int) -> Array:
    """``t`` rounded to the nearest integer when within a few ulps of it; identity gradient.

    ``k / (2^b - 1) * (2^b - 1)`` is not always exactly ``k`` in floating point
    (it depends on how the data were scaled and on FMA contraction in the
    compiled kernel), so exact codes are restored before the sign expansion.
    The result is a ``select``, which the compiler cannot fuse into an FMA.
    """
    r = jnp.round(t)
    tol = 4 * jnp.finfo(t.dtype).eps * top
    return jnp.where(jnp.abs(t - r) <= tol, r, t)


@_snap_to_codes.defjvp
def _snap_to_codes_jvp(top, primals, tangents):
    return _snap_to_codes(primals[0], top), tangents[0]


def encode_normal_map(n: Float[ArrayLike, "*batch 3"], *, encoding: str = "unsigned",
                      channels: int = 3, green: str = "up", bits: int = 8,
                      uv_origin: str = "bottom_left") -> Float[Array, "*batch {channels}"]:
    """Inverse of `decode_normal_map` (with strength 1): vectors to storable values.

    **Arguments:**
    - `n`: ``(..., 3)`` tangent-space vectors (x along +u, y along +v), not
      normalised here. With ``channels=2`` z is dropped, so only unit vectors
      with ``z >= 0`` round-trip.
    - `encoding`, `channels`, `green`, `bits`, `uv_origin`: as in
      `decode_normal_map`.

    **Returns:** ``(..., channels)``: for the unsigned encodings values in
    [0, 1] (clipped) ready for saving, quantisation (``round(r (2^b - 1))``) left
    to the caller; for ``"signed"`` the components clipped to [-1, 1]. With
    ``"unsigned_exact"``, -1, 0 and 1 map exactly onto codes 1, ``2^{b-1}`` and
    ``2^b - 1``. For ``channels=2`` pad a third channel yourself if the file
    format needs one (decoding ignores it).
    """
    _check_normal_options("encode_normal_map", encoding, channels, green, bits, uv_origin)
    n = jnp.asarray(n)
    _check_float("encode_normal_map", "n", n)
    if n.shape[-1:] != (3,):
        raise ValueError(f"encode_normal_map: n must have shape (..., 3), got {n.shape}")
    return _encode(n, encoding, int(channels), _flip_green(green, uv_origin), int(bits))


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4))
def _encode(n: Array, encoding: str, channels: int, flip: bool, bits: int) -> Array:
    y = -n[..., 1] if flip else n[..., 1]
    v = jnp.stack([n[..., 0], y, n[..., 2]][:channels], -1)
    if encoding == "unsigned":
        return jnp.clip((v + 1) / 2, 0.0, 1.0)
    if encoding == "unsigned_exact":
        half = 2 ** (bits - 1)
        return jnp.clip((v * (half - 1) + half) / (2**bits - 1), 0.0, 1.0)
    return jnp.clip(v, -1.0, 1.0)


def quantize(x: ArrayLike, bits: int = 8) -> Array:
    """Round unorm values in [0, 1] to the nearest of the ``2^bits`` codes a ``bits``-bit image
    stores, ``round(x (2^b - 1)) / (2^b - 1)`` (what saving and reloading an image gives)."""
    if not isinstance(bits, (int, np.integer)) or not 1 <= bits <= 16:
        raise ValueError(f"quantize: bits must be an integer between 1 and 16, got {bits!r}")
    top = 2**int(bits) - 1
    return jnp.round(jnp.clip(jnp.asarray(x), 0.0, 1.0) * top) / top


# --------------------------------------------------------------------------- sRGB

_SRGB_DECODE_KNEE = 0.04045
_SRGB_ENCODE_KNEE = 0.0031308


def srgb_to_linear(x: ArrayLike) -> Array:
    """IEC 61966-2-1 sRGB decoding, elementwise (apply to colour, not alpha, channels).

    ``x / 12.92`` for ``x <= 0.04045``, else ``((x + 0.055) / 1.055)^2.4``.
    Finite gradients everywhere (the power branch only sees ``x >= 0.04045``).
    """
    x = jnp.asarray(x)
    _check_float("srgb_to_linear", "x", x)
    return _srgb_to_linear(x)


@jax.jit
def _srgb_to_linear(x: Array) -> Array:
    low = x <= _SRGB_DECODE_KNEE
    high = ((jnp.maximum(x, _SRGB_DECODE_KNEE) + 0.055) / 1.055) ** 2.4
    return jnp.where(low, x / 12.92, high)


def linear_to_srgb(x: ArrayLike) -> Array:
    """IEC 61966-2-1 sRGB encoding, elementwise (apply to colour, not alpha, channels).

    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055``. The
    power branch only sees ``x >= 0.0031308``, so the gradient at 0 is 12.92,
    not the infinite slope of ``x^(1/2.4)``.
    """
    x = jnp.asarray(x)
    _check_float("linear_to_srgb", "x", x)
    return _linear_to_srgb(x)


@jax.jit
def _linear_to_srgb(x: Array) -> Array:
    low = x <= _SRGB_ENCODE_KNEE
    high = 1.055 * jnp.maximum(x, _SRGB_ENCODE_KNEE) ** (1 / 2.4) - 0.055
    return jnp.where(low, 12.92 * x, high)
