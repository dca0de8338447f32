"""Numerically safe primitives, forward *and* backward.

Every normalisation, division and square root in jaxnm goes through this
module. Each function is finite in value and gradient for every finite input,
including the singular points (zero vectors, zero denominators), where it
returns a documented fallback whose gradient is zero.

The pattern is the "double where": the unsafe branch is fed a harmless
substitute input where it would be singular, so that neither its value nor its
(discarded) gradient can be NaN, and the outer ``where`` selects the fallback.
A single ``where`` is not enough for reverse-mode AD: the cotangent of the
unselected branch is multiplied by zero, and ``0 * inf`` is NaN.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

__all__ = [
    "sum_last", "dot", "spread", "cross", "eps", "tiny", "safe_div", "safe_sqrt", "safe_rsqrt",
    "safe_norm", "safe_normalize", "angle_between"
]


def sum_last(x: ArrayLike, keepdims: bool = False) -> Array:
    """Sum over a short last axis (e.g. 3 vector components), written out term by term.

    XLA's CPU reduction over a minor axis of length 3 is an order of magnitude
    slower than the equivalent chain of elementwise adds, which fuse with their
    producers; every small dot product in jaxnm goes through here.
    """
    x = jnp.asarray(x)
    out = x[..., 0]
    for i in range(1, x.shape[-1]):
        out = out + x[..., i]
    return out[..., None] if keepdims else out


def dot(a: ArrayLike, b: ArrayLike, keepdims: bool = False) -> Array:
    """Dot product over the (short) last axis, see `sum_last`."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.ndim != b.ndim:  # explicit rank alignment (rank promotion may be disabled)
        n = max(a.ndim, b.ndim)
        a = a.reshape((1,) * (n - a.ndim) + a.shape)
        b = b.reshape((1,) * (n - b.ndim) + b.shape)
    return sum_last(a * b, keepdims=keepdims)


def spread(x: ArrayLike, n: int = 3) -> Array:
    """``x`` (..., 1) repeated to (..., n) along its last axis, as a concatenation.

    For a per-pixel scalar that scales a vector (a normalisation, a cosine times a
    colour): broadcasting it is free in the forward pass, but reverse mode transposes a
    broadcast into a reduction over the minor axis of ``n``, which XLA's CPU runs
    through a library call an order of magnitude slower than it should be (in a frame's
    gradient, such reductions dominated). The
    transpose of a concatenation is slices and elementwise adds, which fuse. The values
    are the same either way.
    """
    x = jnp.asarray(x)
    if x.shape[-1:] != (1,):
        raise ValueError(f"spread: expected a last axis of 1, got shape {x.shape}")
    return jnp.concatenate([x] * n, axis=-1)


def cross(a: ArrayLike, b: ArrayLike) -> Array:
    """``a x b`` over the last axis (length 3), written out (fuses better than ``jnp.cross``)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    a0, a1, a2 = a[..., 0:1], a[..., 1:2], a[..., 2:3]
    b0, b1, b2 = b[..., 0:1], b[..., 1:2], b[..., 2:3]
    return jnp.concatenate([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def eps(dtype) -> float:
    """Relative tolerance used for "numerically zero" tests, about 8 units of rounding:
    1e-6 (f32), 1e-12 (f64), 1e-3 (f16), 1e-2 (bf16)."""
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64:
        return 1e-12
    if dtype == jnp.bfloat16:
        return 1e-2
    if dtype == jnp.float16:
        return 1e-3
    return 1e-6


def tiny(dtype) -> float:
    """Smallest magnitude treated as non-zero in a denominator (well above the subnormals)."""
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64:
        return 1e-200
    if dtype in (jnp.float16, jnp.bfloat16):
        return 1e-4
    return 1e-30


def safe_div(num: ArrayLike, den: ArrayLike, fallback: ArrayLike = 0.0) -> Array:
    """``num / den`` where ``|den| > tiny``; ``fallback`` (zero gradient) elsewhere."""
    num = jnp.asarray(num)
    den = jnp.asarray(den)
    ok = jnp.abs(den) > tiny(jnp.result_type(num, den))
    den_safe = jnp.where(ok, den, jnp.ones_like(den))
    return jnp.where(ok, num / den_safe, fallback)


def safe_sqrt(x: ArrayLike) -> Array:
    """``sqrt(max(x, 0))`` with a zero (not infinite) gradient at and below zero."""
    x = jnp.asarray(x)
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, jnp.ones_like(x))), 0.0)


def safe_rsqrt(x: ArrayLike, fallback: ArrayLike = 0.0) -> Array:
    """``1/sqrt(x)`` for ``x > tiny``; ``fallback`` elsewhere (where GLSL's ``inversesqrt`` is
    undefined)."""
    x = jnp.asarray(x)
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.reciprocal(jnp.sqrt(jnp.where(ok, x, jnp.ones_like(x)))), fallback)


def safe_norm(v: ArrayLike, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm along ``axis``; gradient zero (not NaN) at the zero vector."""
    v = jnp.moveaxis(jnp.asarray(v), axis, -1)
    out = safe_sqrt(dot(v, v, keepdims=keepdims))
    return jnp.moveaxis(out, -1, axis) if keepdims else out


def safe_normalize(v: ArrayLike, axis: int = -1, fallback: ArrayLike | None = None) -> Array:
    """``v / |v|``; where ``|v|`` is (numerically) zero, returns ``fallback``.

    ``fallback`` broadcasts against ``v`` and defaults to the zero vector. Pass,
    for example, the unperturbed normal so that a degenerate input degrades
    gracefully instead of producing NaN.
    """
    v = jnp.asarray(v)
    if axis in (-1, v.ndim - 1):
        sq = dot(v, v, keepdims=True)
    else:
        sq = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = sq > tiny(v.dtype)
    inv = jnp.reciprocal(jnp.sqrt(jnp.where(ok, sq, jnp.ones_like(sq))))
    if fallback is None:
        fallback = jnp.zeros_like(v)
    if axis in (-1, v.ndim - 1):
        inv = spread(inv, v.shape[-1])
    return jnp.where(ok, v * inv, jnp.asarray(fallback, v.dtype))


def angle_between(a: ArrayLike, b: ArrayLike, axis: int = -1) -> Array:
    """Angle in radians between vectors ``a`` and ``b`` along ``axis``.

    Uses ``atan2(|a x b|, a . b)``, accurate for tiny and near-pi angles (where
    ``arccos`` of a dot product loses half the digits) and finite in gradient
    for parallel or zero vectors. Only 3-vectors are supported.
    """
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    a, b = jnp.moveaxis(a, axis, -1), jnp.moveaxis(b, axis, -1)
    y = safe_norm(cross(a, b))
    x = dot(a, b)
    ok = (y * y + x * x) > tiny(x.dtype)  # atan2's gradient is 0/0 at the origin
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)
