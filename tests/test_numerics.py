"""`jaxnm.numerics`: the forms of its primitives (their values are tested where they are used)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import jaxpr_equations

from jaxnm.numerics import safe_normalize, spread


def _minor_axis_sums(closed) -> list:
    """The ``reduce_sum`` equations of a jaxpr (nested ones included) that sum over the last
    axis alone (a per-element reduction, e.g. per pixel), where it is longer than 1."""
    found = []
    for eqn in jaxpr_equations(closed):
        if eqn.primitive.name == "reduce_sum":
            shape = eqn.invars[0].aval.shape
            if len(shape) > 1 and tuple(eqn.params["axes"]) == (len(shape) - 1,) \
                    and shape[-1] > 1:
                found.append(eqn)
    return found


def test_spread_is_a_broadcast_whose_gradient_has_no_reduction():
    rng = np.random.default_rng(3)
    s = jnp.asarray(rng.normal(size=(257, 1)), jnp.float32)
    v = jnp.asarray(rng.normal(size=(257, 3)), jnp.float32)
    np.testing.assert_array_equal(spread(s), jnp.broadcast_to(s, (257, 3)))
    np.testing.assert_array_equal(spread(s, 4), jnp.broadcast_to(s, (257, 4)))

    def loss(f):
        return lambda s: jnp.sum(jnp.sin(f(s) * v))

    g = jax.grad(loss(spread))(s)
    g_ref = jax.grad(loss(lambda s: s * jnp.ones((1, 3))))(s)
    np.testing.assert_allclose(g, g_ref, rtol=1e-6, atol=1e-6)
    # the point of it: reverse mode adds the three components instead of reducing over a
    # minor axis of 3 (which XLA's CPU runs as a slow library reduction)
    assert _minor_axis_sums(jax.make_jaxpr(jax.grad(loss(lambda s: s * jnp.ones((1, 3)))))(s))
    assert not _minor_axis_sums(jax.make_jaxpr(jax.grad(loss(spread)))(s))
    # ... and so does the gradient of a normalisation through it
    assert not _minor_axis_sums(jax.make_jaxpr(
        jax.grad(lambda v: jnp.sum(safe_normalize(v)[:, 0])))(v))
    with pytest.raises(ValueError, match="last axis of 1"):
        spread(v)
