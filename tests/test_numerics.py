"""jaxnm.numerics helpers that the stages share."""

import re

import jax
import jax.numpy as jnp
import numpy as np

from jaxnm.numerics import materialize


def _while_carry_types(hlo: str) -> list[str]:
    """The element types of every array in the carried tuples of the compiled while loops."""
    out = []
    for m in re.finditer(r"= \(([^)]*)\) while\(", hlo):
        out += re.findall(r"(f32|s32|pred)\[\d", m.group(1))
    return out


def test_materialize_is_an_identity_that_keeps_every_leaf_in_its_own_buffer():
    x = jnp.linspace(-2.0, 3.0, 64)

    def f(x):
        a, i, b = x * 2.0, jnp.arange(64, dtype=jnp.int32) * 3, x > 0.5
        a, i, b = materialize((a, i, b))
        return a[:, None] + i[:, None] + b[:, None] * jnp.arange(4.0)[None, :]

    def g(x):
        return (x * 2.0)[:, None] + (jnp.arange(64) * 3)[:, None] + (x > 0.5)[:, None] \
            * jnp.arange(4.0)[None, :]

    np.testing.assert_array_equal(jax.jit(f)(x), g(x))
    np.testing.assert_array_equal(jax.grad(lambda x: f(x).sum())(x),
                                  jax.grad(lambda x: g(x).sum())(x))
    # Each kind of leaf (float, int, bool) goes through the loop: a leaf the loop leaves
    # untouched would be hoisted out of it and fused (recomputed) into every consumer.
    kinds = _while_carry_types(jax.jit(f).lower(x).compile().as_text())
    assert {"f32", "s32", "pred"} <= set(kinds), kinds
