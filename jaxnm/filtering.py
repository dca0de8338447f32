r"""Filtering normal maps as engines do: mip chains of unit normals, Toksvig's gloss, LEAN.

Averaging unit normals (a mip level, a bilinear or trilinear fetch) gives a vector shorter
than 1 wherever the normals under the footprint differ. A renderer can throw that length
away or use it:

- **Renormalised mip chains** (`normal_mipmaps` with ``mode="renormalize"``): every level
  normalised after filtering, as CryEngine's resource compiler writes them. The shader then
  shades the filtered direction with the material's exponent: from afar the surface looks
  *more polished* than it is, since the spread of the normals under a pixel is lost
  (CryEngine's documentation: "speculars which are broad and noisy when nearby ... but
  sharp and small when far away").
- **Shortened mip chains** (``mode="shortened"``): the plain box-filtered average, whose
  length ``|N_a| <= 1`` measures the spread.
- **Toksvig's factor** (`toksvig_factor`, `toksvig_specular`): assuming the normals under a
  texel spread like a Gaussian lobe, Toksvig (2005) turns the length into a per-texel gloss,

  .. math::
      f_t = \frac{|N_a|}{|N_a| + s\,(1 - |N_a|)}, \qquad s' = f_t\, s,

  for a Blinn-Phong exponent ``s``, and scales the lobe by ``(1 + s') / (1 + s)`` so that
  its integral over the hemisphere, ``2\pi / (1 + s)``, is unchanged by the filtering (the
  average of lobes has the integral of one lobe).
- **LEAN mapping** (`lean_moments`, `lean_specular`; Olano & Baker 2010): store the slopes
  ``b = (n_x, n_y) / n_z`` and their second moments ``(b_x^2, b_y^2, b_x b_y)``, five
  linearly filterable channels; any filtered texel then gives the slopes' mean and
  covariance ``\Sigma_n = M - \bar b \bar b^T``, and the specular lobe is the Gaussian in
  slope space whose covariance adds the material's own, ``\Sigma = \Sigma_n + I / s``.

Engines ship the same idea as a *roughness prefilter*: the variance that the shortened
normal reveals is folded into the roughness channel of each mip level offline, instead of
an exponent changed at shading time (Filament's ``roughness-prefilter`` tool writes one
roughness map per mip level from a normal map; Unreal Engine's composite textures add a
normal map's variance to a roughness texture's mips). Both rest on the estimate Toksvig's
factor makes: the spread of the normals under a texel, read from what filtering did to
their average.

References:

- Michael Toksvig, "Mipmapping Normal Maps", Journal of Graphics Tools 10(3), 2005
  (NVIDIA technical brief, 2004).
- Marc Olano and Dan Baker, "LEAN Mapping", ACM I3D 2010.
- CryEngine documentation, "Tangent Space Normal Mapping" (renormalised mip levels).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .numerics import dot as _dot
from .numerics import safe_normalize
from .textures import build_mipmaps

__all__ = [
    "NORMAL_MIP_MODES",
    "normal_mipmaps",
    "blinn_phong_lobe",
    "toksvig_factor",
    "toksvig_specular",
    "lean_moments",
    "lean_specular",
]

#: How `normal_mipmaps` treats the filtered averages: ``"renormalize"`` (every level unit,
#: CryEngine's resource compiler) or ``"shortened"`` (the plain average, length <= 1).
NORMAL_MIP_MODES = ("renormalize", "shortened")


def _floats(func: str, name: str, x: ArrayLike, last: int | None = None) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    if last is not None and (x.ndim < 1 or x.shape[-1] != last):
        raise ValueError(f"{func}: `{name}` must have shape (..., {last}), got {x.shape}")
    return x


def _scalar_like(x: ArrayLike, batch: tuple[int, ...], dtype) -> Array:
    """A scalar or per-pixel (...) value, broadcast (explicitly) to ``batch``."""
    x = jnp.asarray(x, dtype)
    if x.ndim > len(batch):
        raise ValueError(f"filtering: cannot broadcast shape {x.shape} to {batch}")
    return jnp.broadcast_to(x.reshape((1,) * (len(batch) - x.ndim) + x.shape), batch)


def normal_mipmaps(normals: ArrayLike, *, mode: str = "renormalize",
                   levels: int | None = None) -> tuple[Array, ...]:
    """The mip chain of a decoded normal map, renormalised per level or not.

    **Arguments:**
    - `normals`: (H, W, 3) decoded unit normals (level 0, image layout).
    - `mode`: one of `NORMAL_MIP_MODES`: ``"renormalize"`` (each level normalised, each
      filtered from the renormalised level above it) or ``"shortened"`` (the box-filtered
      average of level 0, length ``|N_a| <= 1``, which `toksvig_factor` reads).
    - `levels`: as in `jaxnm.textures.build_mipmaps` (None: the full chain).

    **Returns:** a tuple of (H_k, W_k, 3) arrays, level 0 first (level 0 as given). The
    filter is `jaxnm.textures.build_mipmaps`' exact box filter.
    """
    if mode not in NORMAL_MIP_MODES:
        raise ValueError(f"normal_mipmaps: unknown mode={mode!r}; expected one of "
                         f"{', '.join(repr(m) for m in NORMAL_MIP_MODES)}")
    normals = _floats("normal_mipmaps", "normals", normals, 3)
    if normals.ndim != 3:
        raise ValueError(f"normal_mipmaps: `normals` must be (H, W, 3), got {normals.shape}")
    return build_mipmaps(normals, levels=levels, renormalize=mode == "renormalize")


def _pos_pow(x: Array, n: Array) -> Array:
    """``max(x, 0) ** n`` with ``0 ** 0 = 1`` and finite gradients everywhere."""
    ok = x > jnp.finfo(x.dtype).tiny
    y = jnp.exp(n * jnp.log(jnp.where(ok, x, jnp.ones_like(x))))
    return jnp.where(ok, y, jnp.where(n == 0, 1.0, 0.0).astype(y.dtype))


def blinn_phong_lobe(n: ArrayLike, h: ArrayLike, shininess: ArrayLike) -> Array:
    """Blinn-Phong's specular lobe ``max(0, n . h)^s`` (``n`` and ``h`` used as given).

    **Arguments:**
    - `n`: (..., 3) normals; `h`: (..., 3) unit half vectors, broadcasting against `n`.
    - `shininess`: the exponent ``s >= 0``, a scalar or (...).

    **Returns:** (...). The same lobe as `jaxnm.shading.blinn_phong`'s specular term
    (without the light's radiance, the specular colour and the ``n . l > 0`` gate).
    """
    n = _floats("blinn_phong_lobe", "n", n, 3)
    h = _floats("blinn_phong_lobe", "h", h, 3)
    shape = jnp.broadcast_shapes(n.shape, h.shape)
    dtype = jnp.result_type(n, h)
    n, h = (jnp.broadcast_to(a.reshape((1,) * (len(shape) - a.ndim) + a.shape), shape)
            .astype(dtype) for a in (n, h))
    return _pos_pow(_dot(n, h), _scalar_like(shininess, shape[:-1], dtype))


def toksvig_factor(n_avg: ArrayLike, shininess: ArrayLike) -> Array:
    r"""Toksvig's factor ``f_t = |N_a| / (|N_a| + s (1 - |N_a|))`` of a filtered normal.

    **Arguments:**
    - `n_avg`: (..., 3) filtered (not renormalised) normals, e.g. a sample of a
      ``"shortened"`` `normal_mipmaps` chain; lengths above 1 (quantisation) count as 1.
    - `shininess`: the Blinn-Phong exponent ``s >= 0``, a scalar or (...).

    **Returns:** (...) in [0, 1]: 1 for a unit normal (no spread), 0 for a vanishing
    average. The filtered exponent is ``f_t s``. Finite gradients everywhere.
    """
    n_avg = _floats("toksvig_factor", "n_avg", n_avg, 3)
    s = _scalar_like(shininess, n_avg.shape[:-1], n_avg.dtype)
    return _toksvig_factor(n_avg, s)


@jax.jit
def _toksvig_factor(n_avg: Array, s: Array) -> Array:
    sq = _dot(n_avg, n_avg)
    ok = sq > jnp.finfo(sq.dtype).tiny
    length = jnp.minimum(jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0), 1.0)
    den = length + s * (1 - length)
    ok = den > 0
    return jnp.where(ok, length / jnp.where(ok, den, 1.0), 1.0)


def toksvig_specular(n_avg: ArrayLike, h: ArrayLike, shininess: ArrayLike) -> Array:
    r"""The Blinn-Phong lobe of a filtered normal with Toksvig's gloss.

    .. math::
        \frac{1 + f_t s}{1 + s}\,\max(0, \hat N_a \cdot h)^{f_t s}

    with ``\hat N_a`` the normalised average. The factor in front keeps the lobe's integral
    over the hemisphere, ``2\pi / (1 + s')``, at the unfiltered ``2\pi / (1 + s)``. To shade
    with `jaxnm.shade` instead, pass ``f_t s`` as a per-pixel `Material.shininess` and the
    specular colour times the factor in front as a per-pixel `Material.specular`.

    **Arguments:**
    - `n_avg`: (..., 3) filtered (not renormalised) normals.
    - `h`: (..., 3) unit half vectors, broadcasting against `n_avg`.
    - `shininess`: the exponent ``s``, a scalar or (...).

    **Returns:** (...).
    """
    n_avg = _floats("toksvig_specular", "n_avg", n_avg, 3)
    h = _floats("toksvig_specular", "h", h, 3)
    ft = toksvig_factor(n_avg, shininess)
    s = _scalar_like(shininess, ft.shape, ft.dtype)
    scale = (1 + ft * s) / (1 + s)
    return scale * blinn_phong_lobe(safe_normalize(n_avg), h, ft * s)


def lean_moments(normals: ArrayLike) -> Array:
    r"""LEAN mapping's five linearly filterable channels of a normal map.

    .. math::
        b = \left(\frac{n_x}{n_z}, \frac{n_y}{n_z}\right), \qquad
        (b_x, b_y, b_x^2, b_y^2, b_x b_y)

    Filter (mip-map, sample) the result like any texture; `lean_specular` reads the mean
    and covariance of the slopes under the footprint from a filtered texel.

    **Arguments:**
    - `normals`: (..., 3) decoded normals with ``n_z > 0`` (need not be unit).

    **Returns:** (..., 5). Where ``n_z <= 0`` the slopes are zero (a flat texel), with zero
    gradient.
    """
    normals = _floats("lean_moments", "normals", normals, 3)
    return _lean_moments(normals)


@jax.jit
def _lean_moments(n: Array) -> Array:
    z = n[..., 2]
    ok = z > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, z, 1.0), 0.0)
    bx, by = n[..., 0] * inv, n[..., 1] * inv
    return jnp.stack([bx, by, bx * bx, by * by, bx * by], -1)


def lean_specular(moments: ArrayLike, h: ArrayLike, shininess: ArrayLike) -> Array:
    r"""The specular lobe of a filtered LEAN texel: a Gaussian in slope space.

    With the filtered mean slope ``\bar b``, the covariance ``\Sigma_n = M - \bar b \bar b^T``
    (its variances clamped at 0) and ``\Sigma = \Sigma_n + I / s``,

    .. math::
        \frac{\exp\!\left(-\tfrac12 d^T \Sigma^{-1} d\right)}{\sqrt{\det(I + s\,\Sigma_n)}},
        \qquad d = \frac{(h_x, h_y)}{h_z} - \bar b,

    the average over the slopes' Gaussian of ``\exp(-\tfrac{s}{2} |\tilde h - b|^2)``, which
    is Blinn-Phong's ``(n \cdot h)^s`` near its peak (Olano & Baker's Beckmann-like lobe,
    scaled so that a single normal's lobe peaks at 1 as Blinn-Phong's does).

    **Arguments:**
    - `moments`: (..., 5) filtered `lean_moments`.
    - `h`: (..., 3) unit half vectors in tangent space, broadcasting against `moments`.
    - `shininess`: the Blinn-Phong exponent ``s > 0``, a scalar or (...).

    **Returns:** (...). Zero where ``h_z <= 0``. Finite gradients everywhere.
    """
    m = _floats("lean_specular", "moments", moments, 5)
    h = _floats("lean_specular", "h", h, 3)
    batch = jnp.broadcast_shapes(m.shape[:-1], h.shape[:-1])
    dtype = jnp.result_type(m, h)
    m = jnp.broadcast_to(m.reshape((1,) * (len(batch) - m.ndim + 1) + m.shape), batch + (5,))
    h = jnp.broadcast_to(h.reshape((1,) * (len(batch) - h.ndim + 1) + h.shape), batch + (3,))
    return _lean_specular(m.astype(dtype), h.astype(dtype),
                          _scalar_like(shininess, batch, dtype))


@jax.jit
def _lean_specular(m: Array, h: Array, s: Array) -> Array:
    bx, by = m[..., 0], m[..., 1]
    sxx = jnp.maximum(m[..., 2] - bx * bx, 0.0)
    syy = jnp.maximum(m[..., 3] - by * by, 0.0)
    sxy = m[..., 4] - bx * by
    hz = h[..., 2]
    up = hz > 0
    inv_hz = 1.0 / jnp.where(up, hz, 1.0)
    dx, dy = h[..., 0] * inv_hz - bx, h[..., 1] * inv_hz - by
    # Sigma = Sigma_n + I / s, written as (s Sigma_n + I) / s: inverse s adj / det(s Sigma)
    axx, ayy, axy = 1 + s * sxx, 1 + s * syy, s * sxy
    # det(I + s Sigma_n) >= 1 for a covariance; filtering rounding can leave Sigma_n a
    # little indefinite, hence the clamps
    det = jnp.maximum(axx * ayy - axy * axy, 1.0)
    quad = jnp.maximum(s * (ayy * dx * dx - 2 * axy * dx * dy + axx * dy * dy) / det, 0.0)
    out = jnp.exp(-0.5 * quad) / jnp.sqrt(det)
    return jnp.where(up, out, 0.0)

