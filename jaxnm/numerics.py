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
    "eps",
    "tiny",
    "safe_div",
    "safe_sqrt",
    "safe_rsqrt",
    "safe_norm",
    "safe_normalize",
    "angle_between",
]


def eps(dtype) -> float:
    """Relative tolerance used for "numerically zero" tests: 1e-6 (f32), 1e-12 (f64), 1e-3 (f16)."""
    dtype = jnp.dtype(dtype)
    if dtype == jnp.float64:
        return 1e-12
    if dtype in (jnp.float16, jnp.bfloat16):
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
    """``1/sqrt(x)`` for ``x > tiny``; ``fallback`` elsewhere (GLSL ``inversesqrt`` is undefined there)."""
    x = jnp.asarray(x)
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.reciprocal(jnp.sqrt(jnp.where(ok, x, jnp.ones_like(x)))), fallback)


def safe_norm(v: ArrayLike, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm along ``axis``; gradient zero (not NaN) at the zero vector."""
    v = jnp.asarray(v)
    return safe_sqrt(jnp.sum(v * v, axis=axis, keepdims=keepdims))


def safe_normalize(v: ArrayLike, axis: int = -1, fallback: ArrayLike | None = None) -> Array:
    """``v / |v|``; where ``|v|`` is (numerically) zero, returns ``fallback``.

    ``fallback`` broadcasts against ``v`` and defaults to the zero vector. Pass,
    for example, the unperturbed normal so that a degenerate input degrades
    gracefully instead of producing NaN.
    """
    v = jnp.asarray(v)
    sq = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = sq > tiny(v.dtype)
    inv = jnp.reciprocal(jnp.sqrt(jnp.where(ok, sq, jnp.ones_like(sq))))
    if fallback is None:
        fallback = jnp.zeros_like(v)
    return jnp.where(ok, v * inv, jnp.asarray(fallback, v.dtype))


def angle_between(a: ArrayLike, b: ArrayLike, axis: int = -1) -> Array:
    """Angle in radians between vectors ``a`` and ``b`` along ``axis``.

    Uses ``atan2(|a x b|, a . b)``, accurate for tiny and near-pi angles (where
    ``arccos`` of a dot product loses half the digits) and finite in gradient
    for parallel or zero vectors. Only 3-vectors are supported.
    """
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    y = safe_norm(jnp.cross(a, b, axis=axis), axis=axis)
    x = jnp.sum(a * b, axis=axis)
    ok = (y * y + x * x) > tiny(x.dtype)  # atan2's gradient is 0/0 at the origin
    return jnp.where(ok, jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0)), 0.0)
