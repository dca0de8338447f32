r"""Perspective-correct interpolation and screen-space derivatives (GLSL ``dFdx``/``dFdy``).

Everything here evaluates *the pixel's own triangle* (from `Fragments`) at
window positions, so quad neighbours are true **helper pixels**: the
neighbour's value is the same triangle's interpolant at the neighbour's centre,
also where that centre lies outside the triangle, under another triangle or
outside the image.

**Derivative modes** (``derivatives=``):

- ``"fine"``: GLSL ``dFdxFine``/``dFdyFine``. Quads are 2x2 pixel blocks
  aligned to even window coordinates. ``dFdx`` = right minus left pixel of the
  quad *in the pixel's own row*; ``dFdy`` = upper minus lower pixel *in the
  pixel's own column* (window y points up, so "upper" is the image row above).
  One exception: where the quad partner's centre sees the triangle's plane
  behind the camera (the partner is beyond the plane's horizon, which happens
  at grazing views near the horizon), a GPU's difference is meaningless (the
  interpolant passes through infinity) and the analytic derivative is used.
- ``"coarse"``: GLSL ``dFdxCoarse``/``dFdyCoarse``: one value per quad, taken
  from the row and column named by `COARSE_REFERENCE`.
- ``"analytic"``: the exact derivative of the perspective-correct interpolant
  with respect to window x and y at the pixel centre (the reference).
- ``"gbuffer"``: differences of the *stored* neighbour values within the quad,
  as a deferred renderer would compute them: across a triangle edge or a
  silhouette the neighbour belongs to another triangle (or to the background,
  which stores 0), which produces the familiar edge artefacts.

``derivatives=None`` interpolates the values only.

**How they relate.** With ``S(x, y) = \sum_i E_i(x, y)`` (the denominator of
the barycentrics, affine in screen space and proportional to ``1/w``) and
``G_i = a_i S - E_i a_S`` (``a = \partial E/\partial x``), the barycentric
derivatives are

.. math::
    \partial_x b_i = \frac{G_i}{S(p)^2}, \qquad
    \mathrm{dFdxFine}\, b_i = \frac{G_i}{S(p)\, S(p')},

where ``p'`` is the pixel's horizontal quad partner (``G_i`` does not depend on
``x``). So fine differences equal the analytic derivative scaled by
``S(p)/S(p') = w(p')/w(p)``: they agree exactly for affine attributes
(orthographic views, or attributes that are affine in screen space) and differ
by the change of depth across one pixel under perspective. Coarse derivatives
additionally take ``G`` from the reference row/column, which differs from the
pixel's own under perspective.

Differences are formed *algebraically* (as above) rather than by subtracting
two interpolated values, so they keep full float32 precision for geometry far
from the origin and for extreme close-ups, where GPU hardware would lose digits
to cancellation; the values are the same up to rounding.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping

import jax
import jax.numpy as jnp
from jax import Array

from ._exec.arrays import xyw
from ._exec.fusion import materialize
from .camera import to_window
from .numerics import safe_div
from .raster import Fragments

__all__ = [
    "Attribute", "Barycentrics", "DERIVATIVE_MODES", "PRECISIONS", "at_precision",
    "COARSE_REFERENCE", "barycentrics", "interpolate", "triangle_corners", "check_derivatives",
    "check_precision", "require_x64"
]

#: The screen-space derivative modes (the scene key ``derivatives``, ``--derivatives``).
DERIVATIVE_MODES = ("fine", "coarse", "analytic", "gbuffer")

#: Fragment-shader arithmetic precisions (the scene key ``precision``, ``--precision``):
#: ``float32`` is GLSL ``highp``; ``float16`` is ``mediump`` on hardware with half-precision
#: ALUs (IEEE binary16: 11-bit significand, largest 65504); ``bfloat16`` keeps float32's
#: range with an 8-bit significand (what some ML accelerators offer instead); ``float64``
#: (needs 64-bit JAX, ``jax_enable_x64``) computes the frame in double precision from the
#: float32 interpolants, which shows what the arithmetic alone still costs in float32.
PRECISIONS = ("float32", "float16", "bfloat16", "float64")

#: ``dFdxCoarse`` is taken from the quad's lower row (window y even) and
#: ``dFdyCoarse`` from its left column (window x even): the quad's lower-left
#: pixel is the reference for both.
COARSE_REFERENCE = "lower_left"


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Attribute:
    """An interpolated attribute and its screen-space derivatives (image layout).

    **Fields:**
    - `value`: (H, W, C), 0 on background pixels.
    - `ddx`, `ddy`: (H, W, C) derivatives per pixel step in window x (right) and
      window y (**up**, i.e. towards image row ``r - 1``), or None when not
      computed. 0 on background pixels.
    """

    value: Array
    ddx: Array | None = None
    ddy: Array | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Barycentrics:
    """Perspective-correct barycentrics of each pixel's own triangle, with derivatives.

    ``value``, ``ddx``, ``ddy``: (H, W, 3), 0 on background. ``ddx``/``ddy`` are
    None for ``"gbuffer"`` and for ``derivatives=None`` (gbuffer derivatives are
    taken from the interpolated values instead).
    """

    value: Array
    ddx: Array | None
    ddy: Array | None
    mode: str | None = dataclasses.field(metadata=dict(static=True), default="fine")


def check_derivatives(derivatives: str | None, *, allow_none: bool = True) -> None:
    """Raise a `ValueError` unless ``derivatives`` is one of `DERIVATIVE_MODES` (or None,
    values only, where ``allow_none``)."""
    if derivatives is None and allow_none:
        return
    if derivatives not in DERIVATIVE_MODES:
        raise ValueError(f"unknown derivatives mode {derivatives!r}; expected one of "
                         f"{', '.join(DERIVATIVE_MODES)}")


def check_precision(precision: str) -> None:
    """Raise a `ValueError` unless ``precision`` is one of `PRECISIONS`."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; expected one of "
                         f"{', '.join(PRECISIONS)}")


def require_x64(what: str) -> None:
    """Raise a `ValueError` naming ``what`` unless 64-bit JAX is enabled (without it a
    float64 array silently becomes float32)."""
    if not jax.config.jax_enable_x64:
        raise ValueError(f"{what} needs 64-bit JAX: set JAX_ENABLE_X64=1 or call "
                         "jax.config.update('jax_enable_x64', True) before rendering")


def at_precision(attr: Attribute, precision: str, mask: Array, *,
                 derivatives: str | None, pixels: tuple[Array, Array] | None = None
                 ) -> Attribute:
    """``attr`` as a shader running at ``precision`` sees it (a model of GLSL ``mediump``).

    The rasterizer's interpolators stay float32 (fixed-function hardware); the shader
    receives the value rounded to ``precision``, and a quad derivative is the difference,
    in ``precision``, of the two *rounded* quad values. So the derivative of a value that
    changes by less than its own rounding step across a pixel is 0 or one whole step: the
    close-up noise Schüler's readers report ("the differences between pixels of the texture
    coordinate become too small for floating point precision", 2013 comments).

    - ``fine`` and ``gbuffer``: exactly that; the partner's value is this pixel's value
      plus or minus the float32 difference (the partner is the helper pixel to the right
      of or above a quad's left or lower pixel, and to the left or below otherwise).
    - ``coarse``: the same construction from the pixel's own value; a GPU takes both
      values from the quad's reference pixel, whose value differs (same step size, a
      different sample of the rounding).
    - ``analytic``: value and derivatives rounded (the exact reference, stored at
      ``precision``).

    - ``float64``: value and derivatives converted exactly (nothing to round).

    ``mask`` is an image's coverage (H, W), or that of packed fragments with their window
    pixels ``pixels = Fragments.window_pixels()`` (which say which quad partner a pixel
    has).

    Returns an `Attribute` whose arrays have ``precision``'s dtype (0 on background).
    """
    check_precision(precision)
    if precision == "float32":
        return attr
    if precision == "float64":
        require_x64("precision 'float64'")
        f64 = jnp.float64
        return Attribute(attr.value.astype(f64),
                         *(None if d is None else d.astype(f64) for d in (attr.ddx, attr.ddy)))
    dt = jnp.dtype(precision)
    v = attr.value
    lo = v.astype(dt)
    if attr.ddx is None:
        return Attribute(lo)
    if derivatives == "analytic":
        return Attribute(lo, attr.ddx.astype(dt), attr.ddy.astype(dt))
    if pixels is None:
        height, width = mask.shape
        first_x = (jnp.arange(width) % 2 == 0)[None, :, None]  # left pixel of its quad
        first_y = ((height - 1 - jnp.arange(height)) % 2 == 0)[:, None, None]  # lower pixel
    else:
        first_x, first_y = ((q % 2 == 0)[..., None] for q in pixels)

    def diff(d, first):
        partner = jnp.where(first, v + d, v - d).astype(dt)
        return jnp.where(first, partner - lo, lo - partner)

    m = mask[..., None]
    zero = jnp.zeros((), dt)
    return Attribute(lo, jnp.where(m, diff(attr.ddx, first_x), zero),
                     jnp.where(m, diff(attr.ddy, first_y), zero))


def _pixel_setup(frags: Fragments):
    """Per pixel: the edge functions E_i at the centre and their gradients a_i, b_i (each
    a tuple of three arrays of the fragments' shape), and the mask.

    Written component by component, each an array of the fragments' shape, and stacked
    only at the end (`barycentrics`): on XLA's CPU every slice of a short last axis and
    every concatenation back into one cuts the per-pixel arithmetic into separate loops
    (the whole per-pixel program ran faster than with (..., 3) arrays)."""
    height, width = frags.image_shape
    mask = frags.mask
    tri = jnp.maximum(frags.triangle_id, 0)
    h = (xyw(to_window(frags.clip, width, height)) if frags.window is None
         else frags.window)  # (V, 3): x, y, w
    corner = frags.faces[tri]
    hv = [h[corner[..., v]] for v in range(3)]  # each vertex's (..., 3)
    x, y = frags.window_centers(h.dtype)
    # translate so the pixel centre is the origin, and normalise the scale: b = E / sum(E)
    # is invariant to both, and the smaller numbers keep E well conditioned
    hx = [q[..., 0] - x * q[..., 2] for q in hv]
    hy = [q[..., 1] - y * q[..., 2] for q in hv]
    hw = [q[..., 2] for q in hv]
    m3 = [jnp.maximum(jnp.maximum(jnp.abs(p), jnp.abs(q)), jnp.abs(r))
          for p, q, r in zip(hx, hy, hw)]
    scale = jnp.maximum(jnp.maximum(m3[0], m3[1]), m3[2])
    scale = jax.lax.stop_gradient(jnp.where(mask & (scale > 0), scale, 1.0))
    hx, hy, hw = ([q / scale for q in c] for c in (hx, hy, hw))
    e, a, b = [], [], []
    for i in range(3):  # edge i joins vertices j = i + 1 and k = i + 2
        j, k = (i + 1) % 3, (i + 2) % 3
        e.append(hx[j] * hy[k] - hy[j] * hx[k])
        a.append(hy[j] * hw[k] - hw[j] * hy[k])
        b.append(hw[j] * hx[k] - hx[j] * hw[k])
    return tuple(e), tuple(a), tuple(b), mask


def _sum3(c):
    return (c[0] + c[1]) + c[2]


@functools.partial(jax.jit, static_argnames=("derivatives",))
def barycentrics(frags: Fragments, *, derivatives: str | None = "fine") -> Barycentrics:
    """Barycentrics of each pixel's triangle at its centre, and their screen derivatives.

    **Arguments:**
    - `frags`: from `jaxnm.rasterize`.
    - `derivatives`: one of `DERIVATIVE_MODES`, or None for values only
      (keyword-only, static).

    **Returns:** a `Barycentrics`; interpolating an attribute with it is linear,
    see `interpolate`.
    """
    check_derivatives(derivatives)
    e, a, b, mask = _pixel_setup(frags)
    s = jnp.where(mask, _sum3(e), 1.0)  # covered pixels have S != 0 (all E_i share its sign)

    def stack(parts):  # the three barycentrics' (...) arrays as one (..., 3), 0 on background
        return jnp.stack([jnp.where(mask, q, 0.0) for q in parts], -1)

    value = stack([q / s for q in e])
    if derivatives in ("gbuffer", None):
        return Barycentrics(value, None, None, derivatives)

    a_s, b_s = _sum3(a), _sum3(b)
    if derivatives == "analytic":
        ddx = stack([(p * s - q * a_s) / (s * s) for p, q in zip(a, e)])
        ddy = stack([(p * s - q * b_s) / (s * s) for p, q in zip(b, e)])
        return Barycentrics(value, ddx, ddy, derivatives)
    xi, yi = frags.window_pixels()
    if derivatives == "fine":
        # G at the pixel itself; partner at x ^ 1 (same row) and y ^ 1 (same column)
        ex, sx = e, s
        dxp = jnp.where(xi % 2 == 0, 1.0, -1.0)
        dyp = jnp.where(yi % 2 == 0, 1.0, -1.0)
    else:  # coarse: reference pixel = the quad's lower-left (x even, y even)
        ox = -(xi % 2).astype(s.dtype)
        oy = -(yi % 2).astype(s.dtype)
        ex = tuple(p + q * ox + r * oy for p, q, r in zip(e, a, b))  # E at the reference pixel
        sx = _sum3(ex)
        dxp = dyp = jnp.ones_like(ox)
    # S at the quad partner; where it has the other sign (or vanishes) the partner's
    # centre sees the triangle's plane behind the camera (beyond its horizon): there a
    # GPU's difference is meaningless (the interpolant wraps through infinity), so the
    # analytic derivative at the reference is used instead
    px, py = sx + dxp * a_s, sx + dyp * b_s
    px = jnp.where(px * sx > 0, px, sx)
    py = jnp.where(py * sx > 0, py, sx)
    ddx = stack([safe_div(p * sx - q * a_s, sx * px) for p, q in zip(a, ex)])
    ddy = stack([safe_div(p * sx - q * b_s, sx * py) for p, q in zip(b, ex)])
    return Barycentrics(value, ddx, ddy, derivatives)


def triangle_corners(attr: Array, frags: Fragments) -> Array:
    """Each pixel's triangle's corner values, ``(H, W, 3, C)``; zero on background.

    **Arguments:**
    - `attr`: per-vertex ``(V, C)`` or per-face-corner ``(F, 3, C)``.
    - `frags`: from `jaxnm.rasterize`.
    """
    corners = _corners(jnp.asarray(attr), frags)
    return jnp.where(frags.mask[..., None, None], corners, 0.0)


def _corners(attr: Array, frags: Fragments) -> Array:
    """`triangle_corners` unmasked: background pixels read triangle 0 (finite, unused)."""
    tri = jnp.maximum(frags.triangle_id, 0)
    num_faces = frags.faces.shape[0]
    if attr.ndim == 3 and attr.shape[:2] == (num_faces, 3):  # face-varying (F, 3, C)
        return attr[tri]
    if attr.ndim != 2:
        raise ValueError("interpolate: attributes must be per-vertex (V, C) or per face corner "
                         f"(F, 3, C); got shape {attr.shape}")
    if attr.shape[0] != frags.clip.shape[0]:
        raise ValueError(f"interpolate: per-vertex attribute has {attr.shape[0]} rows but the "
                         f"mesh has {frags.clip.shape[0]} vertices")
    return attr[frags.faces[tri]]


def _quad_partner_images(img: Array, mask: Array) -> tuple[Array, Array]:
    """Stored values of the horizontal and vertical quad partners (0 outside the image)."""
    height, width = mask.shape
    cols = jnp.arange(width) ^ 1  # window x partner; same column index in image layout
    rows_win = (height - 1 - jnp.arange(height)) ^ 1
    rows = height - 1 - rows_win  # image row of the window-y partner
    okc = cols < width
    okr = (rows >= 0) & (rows < height)
    hx = jnp.where(okc[None, :, None], img[:, jnp.clip(cols, 0, width - 1)], 0.0)
    hy = jnp.where(okr[:, None, None], img[jnp.clip(rows, 0, height - 1)], 0.0)
    return hx, hy


def _gbuffer_derivatives(value: Array, mask: Array) -> tuple[Array, Array]:
    height, width = mask.shape
    px, py = _quad_partner_images(value, mask)
    x_odd = (jnp.arange(width) % 2 == 1)[None, :, None]
    y_odd = ((height - 1 - jnp.arange(height)) % 2 == 1)[:, None, None]
    ddx = jnp.where(x_odd, value - px, px - value)
    ddy = jnp.where(y_odd, value - py, py - value)
    m = mask[..., None]
    return jnp.where(m, ddx, 0.0), jnp.where(m, ddy, 0.0)


@functools.partial(jax.jit, static_argnames=("derivatives",))
def interpolate(attr: Array | Mapping[str, Array], frags: Fragments, *,
                derivatives: str | None = "fine",
                bary: Barycentrics | None = None) -> Attribute | dict[str, Attribute]:
    r"""Interpolate vertex attributes perspective-correctly, with screen derivatives.

    **Arguments:**
    - `attr`: per-vertex ``(V, C)`` or per-face-corner ``(F, 3, C)`` values, or a
      dict of them (interpolated together, sharing one barycentric evaluation).
    - `frags`: from `jaxnm.rasterize`.
    - `derivatives`: one of `DERIVATIVE_MODES`, or None for values only
      (keyword-only, static).
    - `bary`: precomputed `barycentrics(frags, derivatives=...)` to reuse (of the same
      mode, or of any mode for ``derivatives=None``).

    **Returns:** an `Attribute` (or a dict of them). The value is
    ``A_0 + b_1 (A_1 - A_0) + b_2 (A_2 - A_0)``, and derivatives are formed from
    the barycentric derivatives the same way, so large common offsets (far
    from origin geometry) cancel exactly.
    """
    check_derivatives(derivatives)
    if isinstance(attr, Mapping):
        names = list(attr)
        arrays = [jnp.asarray(attr[n]) for n in names]
        sizes = [x.shape[-1] for x in arrays]
        dtype = jnp.result_type(*arrays)
        packed = jnp.concatenate([x.astype(dtype) for x in arrays], -1)
        out = interpolate(packed, frags, derivatives=derivatives, bary=bary)
        result, start = {}, 0
        for n, size in zip(names, sizes):
            sl = slice(start, start + size)
            result[n] = Attribute(
                out.value[..., sl],
                None if out.ddx is None else out.ddx[..., sl],
                None if out.ddy is None else out.ddy[..., sl],
            )
            start += size
        return result

    attr = jnp.asarray(attr)
    if bary is None:
        # materialised once: fused into the (H, W, C) consumers below, XLA would recompute
        # the barycentrics for every attribute channel
        bary = materialize(barycentrics(frags, derivatives=derivatives))
    elif derivatives is not None and bary.mode != derivatives:  # values: any mode will do
        raise ValueError(f"interpolate: `bary` was computed for derivatives={bary.mode!r}, "
                         f"not {derivatives!r}")
    corners = _corners(attr, frags)  # (H, W, 3, C)
    rel = corners[..., 1:, :] - corners[..., :1, :]  # (H, W, 2, C)
    mask = frags.mask[..., None]

    def combine(weights):
        w = weights.astype(rel.dtype)
        return w[..., 1:2] * rel[..., 0, :] + w[..., 2:3] * rel[..., 1, :]

    value = jnp.where(mask, corners[..., 0, :] + combine(bary.value), 0.0)
    if derivatives is None:
        return materialize(Attribute(value))
    if derivatives == "gbuffer":
        if frags.pixels is not None:
            raise ValueError("interpolate: 'gbuffer' derivatives difference the stored "
                             "neighbours, which packed fragments (`compact`) do not have")
        return materialize(Attribute(value, *_gbuffer_derivatives(value, frags.mask)))
    # materialised: consumers (frames, shading) read each channel many times, and a fused
    # consumer would redo the corner gathers for every read
    return materialize(Attribute(value, jnp.where(mask, combine(bary.ddx), 0.0),
                                 jnp.where(mask, combine(bary.ddy), 0.0)))
