r"""Detail mapping: combining a base and a detail tangent-space normal map.

A detail map is laid over a base map (a tiling fabric weave over a baked garment, small
wrinkles over a wave field). Both are decoded tangent-space normals ``(x, y, z)``, ``z``
along the surface normal. What the combination *should* be depends on how the detail was
authored; the common reference is the surface whose height field is the *sum* of the two
height fields, ``h = h_1 + h_2``. A unit normal of a height field over the tangent plane is

.. math::
    n = \frac{(-\partial_x h, -\partial_y h, 1)}{\sqrt{1 + |\nabla h|^2}},
    \qquad \nabla h = -\frac{(n_x, n_y)}{n_z},

so the gradients (the *derivative map*, `height_gradient`) of the two maps add exactly,
and the normal of the summed height field is ``normal_from_gradient(g_1 + g_2)``. That is
what ``"partial_derivative"`` and ``"surface_gradient"`` compute; the others are
approximations of it (or, for ``"reoriented"``, exact for a different reference: the detail
surface bent onto the base, see there).

The methods (``n_1`` the base, ``n_2`` the detail; every result is normalised):

- ``"linear"``: ``normalize(n_1 + n_2)``, the average of the two normals. It halves the
  detail's tilt on a flat base (the reason a linear blend looks washed out).
- ``"udn"`` (Unreal Developer Network): ``normalize(n_{1xy} + n_{2xy}, n_{1z})``.
- ``"whiteout"`` (Christopher Oat's, as named by Barré-Brisebois and Hill):
  ``normalize(n_{1xy} + n_{2xy}, n_{1z} n_{2z})``.
- ``"reoriented"`` (Reoriented Normal Mapping, RNM): the detail rotated by the rotation that
  takes ``(0, 0, 1)`` onto the base normal, with ``t = n_1 + (0, 0, 1)`` and
  ``u = (-n_{2x}, -n_{2y}, n_{2z})``: ``r = t (t \cdot u) / t_z - u``. For unit inputs ``r`` is
  unit; here it is computed as ``normalize(t (t \cdot u) - u t_z)``, the same vector without
  the division (``t_z = 1 + n_{1z} > 0`` for a base in the upper hemisphere).
- ``"partial_derivative"``: the partial derivatives ``n_{xy} / n_z`` added,
  ``normalize(n_{1xy} n_{2z} + n_{2xy} n_{1z}, n_{1z} n_{2z})`` (the division-free form
  Barré-Brisebois and Hill give).
- ``"surface_gradient"`` (Mikkelsen 2020): each normal's surface gradient relative to the
  tangent frame's normal ``e_z``, ``s = (k e_z - n) / \max(\epsilon, |k|)`` with
  ``k = n \cdot e_z``, the gradients added, and the normal resolved as
  ``normalize(e_z - s_1 - s_2)``. In tangent space ``s = (\nabla h, 0)``, so it agrees with
  ``"partial_derivative"`` wherever both ``z > 0``; the two differ only in how they treat
  ``z <= 0`` (Mikkelsen's framework is written for any surface in world space, where the
  same addition combines maps with different uvs and procedural bumps).

References:

- Colin Barré-Brisebois and Stephen Hill, "Blending in Detail" (2012): linear, overlay,
  partial derivatives, whiteout, UDN, reoriented normal mapping.
- Morten S. Mikkelsen, "Surface Gradient–Based Bump Mapping Framework", Journal of Computer
  Graphics Techniques 9(3), 2020.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .numerics import dot as _dot
from .numerics import safe_normalize, spread

__all__ = ["BLEND_METHODS", "blend_normal_maps", "height_gradient", "normal_from_gradient"]

#: The methods of `blend_normal_maps`.
BLEND_METHODS = ("linear", "udn", "whiteout", "reoriented", "partial_derivative",
                 "surface_gradient")

#: Mikkelsen's guard of the surface gradient's denominator (FLT_EPSILON).
_SG_EPS = 2.0**-23


def _vectors(func: str, **named: ArrayLike) -> tuple[Array, ...]:
    arrays = []
    for name, x in named.items():
        x = jnp.asarray(x)
        if not jnp.issubdtype(x.dtype, jnp.floating):
            x = x.astype(jnp.float32)
        if x.ndim < 1 or x.shape[-1] != 3:
            raise ValueError(f"{func}: `{name}` must have shape (..., 3), got {x.shape}")
        arrays.append(x)
    shape = jnp.broadcast_shapes(*(a.shape for a in arrays))
    dtype = jnp.result_type(*arrays)
    return tuple(jnp.broadcast_to(a.reshape((1,) * (len(shape) - a.ndim) + a.shape), shape)
                 .astype(dtype) for a in arrays)


def blend_normal_maps(base: ArrayLike, detail: ArrayLike, *,
                      method: str = "reoriented") -> Array:
    r"""Lay a detail normal map over a base normal map (decoded tangent-space normals).

    The formulas are in the module docstring, after Barré-Brisebois and Hill's "Blending in
    Detail" (2012) and Mikkelsen's surface gradients (JCGT 9(3), 2020).

    **Arguments:**
    - `base`: (..., 3) the base map's decoded normals (unit, ``z > 0``: a map's texels after
      `jaxnm.textures.decode_normal_map`, or a filtered and renormalised sample).
    - `detail`: (..., 3) the detail map's decoded normals, broadcasting against `base`.
    - `method`: one of `BLEND_METHODS`: ``"linear"``, ``"udn"``, ``"whiteout"``,
      ``"reoriented"`` (default), ``"partial_derivative"`` or ``"surface_gradient"``.

    **Returns:** (..., 3) unit normals in the broadcast shape. Where a method's vector
    vanishes (e.g. ``"reoriented"`` with a base of ``(0, 0, -1)``, or two normals lying in
    the tangent plane) the base is returned, normalised. Value and gradient are finite for
    every finite input.

    The exact answer for detail authored as a height field added to the base's is the
    normal of the summed height fields, ``normal_from_gradient(height_gradient(base) +
    height_gradient(detail))``: ``"partial_derivative"`` and ``"surface_gradient"`` give it
    (to rounding) for ``z > 0``; ``"reoriented"`` instead gives the detail *rotated* onto the
    base (a flat detail returns the base, a flat base returns the detail, and
    ``r . base = detail_z``).
    """
    if method not in BLEND_METHODS:
        raise ValueError(f"blend_normal_maps: unknown method={method!r}; expected one of "
                         f"{', '.join(repr(m) for m in BLEND_METHODS)}")
    n1, n2 = _vectors("blend_normal_maps", base=base, detail=detail)
    return _blend(n1, n2, method)


@functools.partial(jax.jit, static_argnums=2)
def _blend(n1: Array, n2: Array, method: str) -> Array:
    x1, y1, z1 = n1[..., 0], n1[..., 1], n1[..., 2]
    x2, y2, z2 = n2[..., 0], n2[..., 1], n2[..., 2]
    if method == "linear":
        r = n1 + n2
    elif method == "udn":
        r = jnp.stack([x1 + x2, y1 + y2, z1], -1)
    elif method == "whiteout":
        r = jnp.stack([x1 + x2, y1 + y2, z1 * z2], -1)
    elif method == "partial_derivative":
        r = jnp.stack([x1 * z2 + x2 * z1, y1 * z2 + y2 * z1, z1 * z2], -1)
    elif method == "reoriented":
        t = jnp.stack([x1, y1, z1 + 1], -1)
        u = jnp.stack([-x2, -y2, z2], -1)
        r = t * spread(_dot(t, u, keepdims=True)) - u * spread((z1 + 1)[..., None])
    else:  # surface_gradient
        def surfgrad(n):  # (k e_z - n) / max(eps, |k|), k = n . e_z
            k = n[..., 2:3]
            ez = jnp.zeros_like(n).at[..., 2].set(1.0)
            return (spread(k) * ez - n) / spread(jnp.maximum(_SG_EPS, jnp.abs(k)))

        ez = jnp.zeros_like(n1).at[..., 2].set(1.0)
        r = ez - surfgrad(n1) - surfgrad(n2)
    return safe_normalize(r, fallback=safe_normalize(n1))


def height_gradient(n: ArrayLike) -> Array:
    r"""The height-field gradient a tangent-space normal stands for (a derivative map texel).

    .. math::
        \nabla h = \left(-\frac{n_x}{n_z}, -\frac{n_y}{n_z}\right)

    (the slopes of the surface over the tangent plane, in the frame's units: for a map made
    by `jaxnm.maps.height_to_normal_map` with ``scale`` s, ``s`` times the height's texel
    differences.)

    **Arguments:**
    - `n`: (..., 3) tangent-space normals (need not be unit) with ``n_z > 0``.

    **Returns:** (..., 2). Where ``n_z`` is not positive (no height field has that normal)
    the gradient is zero, with a zero gradient.
    """
    (n,) = _vectors("height_gradient", n=n)
    return _height_gradient(n)


@jax.jit
def _height_gradient(n: Array) -> Array:
    z = n[..., 2:3]
    ok = z > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, z, 1.0), 0.0)
    return -n[..., :2] * jnp.concatenate([inv, inv], -1)


def normal_from_gradient(g: ArrayLike) -> Array:
    r"""The unit normal of a height field with gradient ``g``: inverse of `height_gradient`.

    .. math::
        n = \frac{(-g_x, -g_y, 1)}{\sqrt{1 + |g|^2}}

    **Arguments:**
    - `g`: (..., 2) height gradients (derivative-map texels, in the tangent frame's units).

    **Returns:** (..., 3) unit normals with ``z > 0``.
    """
    g = jnp.asarray(g)
    if not jnp.issubdtype(g.dtype, jnp.floating):
        g = g.astype(jnp.float32)
    if g.ndim < 1 or g.shape[-1] != 2:
        raise ValueError(f"normal_from_gradient: `g` must have shape (..., 2), got {g.shape}")
    return _normal_from_gradient(g)


@jax.jit
def _normal_from_gradient(g: Array) -> Array:
    return safe_normalize(jnp.concatenate([-g, jnp.ones_like(g[..., :1])], -1))
