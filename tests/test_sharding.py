"""A fit spread over several devices (`jaxnm.fit.shard_views`) equals the single-device fit.

Run in a subprocess with ``--xla_force_host_platform_device_count=2``: the CPU then shows two
devices, which is how JAX tests multi-device programs without the hardware."""

import os
import subprocess
import sys

import pytest

SCRIPT = r"""
import jax, jax.numpy as jnp, numpy as np
from jaxnm import fit as F
from jaxnm.procedural import default_problem

assert len(jax.devices()) == 2, jax.devices()
problem, gt, _ = default_problem(render_size=32, map_size=16, n_lights=4, views=3)
prep = F.prepare(problem)
sharded = F.shard_views(prep)
for b in sharded.batches:  # every batch split over both devices (3 views padded to 4 once)
    assert len(b.pixels.sharding.device_set) == 2 and b.pixels.shape[0] % 2 == 0
assert sharded.num_views == prep.num_views
rng = np.random.default_rng(0)
z = jnp.asarray(rng.normal(0, 0.2, (16, 16, 2)), jnp.float32)
for reduce in (False, True):
    a, b = F.ModelArgs.create(prep, reduce=reduce), F.ModelArgs.create(sharded, reduce=reduce)
    la, ga = jax.value_and_grad(F.loss)(z, a)
    lb, gb = jax.value_and_grad(F.loss)(z, b)
    np.testing.assert_allclose(float(lb), float(la), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(gb), np.asarray(ga), rtol=1e-4,
                               atol=1e-5 * float(jnp.abs(ga).max()))
# the default solver (lm-texel); optimistix's lm was checked the same way while it was
# the default, and its step has not changed since
opts = F.FitOptions(max_steps=4, lsmr_steps=5)
one = F.fit_normal_map(problem, opts, prepared=prep, progress=False)
two = F.fit_normal_map(problem, opts, prepared=sharded, progress=False)
np.testing.assert_allclose(two.normals, one.normals, atol=2e-4)
# (the last level's step is the one compiled for `two` above)
c2f = F.fit_normal_map(problem, F.FitOptions(max_steps=2, lsmr_steps=5, coarse_to_fine=1),
                       prepared=sharded, progress=False)
assert np.isfinite(c2f.best_loss)
img_one = F.render_with_map(prep, jnp.asarray(gt))
img_two = F.render_with_map(sharded, jnp.asarray(gt))
for x, y in zip(img_one, img_two):
    np.testing.assert_allclose(y, x, atol=1e-6)
print("SHARDED-OK", [len(b.views) for b in sharded.batches])
"""


@pytest.mark.slow
def test_fit_sharded_over_two_devices_equals_one_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAXNM_COMPILATION_CACHE="off", JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0 and "SHARDED-OK" in out.stdout, out.stderr[-4000:]
