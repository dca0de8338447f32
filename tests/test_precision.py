"""Backend-independent numerics: every matrix product in the renderer and the fit asks for
full float32 precision, so a GPU's default (TF32 tensor cores, ~1e-3 relative) cannot change
GPU-faithful results; and the renderer's scatters are ones whose result does not depend on
the order of repeated indices, so deterministic GPU ops cost it nothing. Checked on the
traced programs (jaxprs)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import jaxpr_equations

import jaxnm
from jaxnm import fit as F
from jaxnm.frames import FRAMES
from jaxnm.procedural import default_problem, default_scene

HIGHEST = jax.lax.Precision.HIGHEST


def _dot_precisions(jaxpr) -> list:
    """(precision, operand dtypes) of every dot_general in ``jaxpr`` and its sub-jaxprs."""
    return [(eqn.params.get("precision"), tuple(str(v.aval.dtype) for v in eqn.invars))
            for eqn in jaxpr_equations(jaxpr) if eqn.primitive.name == "dot_general"]


def _low_precision(jaxpr) -> list:
    def full(prec):
        if prec is None:
            return False
        precs = prec if isinstance(prec, tuple) else (prec,)
        return all(p == HIGHEST for p in precs)

    return [(p, d) for p, d in _dot_precisions(jaxpr)
            if any(x.startswith("float") for x in d) and not full(p)]


def test_the_check_sees_a_default_precision_product():
    jaxpr = jax.make_jaxpr(lambda a, b: a @ b)(jnp.ones((3, 3)), jnp.ones((3, 3))).jaxpr
    assert len(_low_precision(jaxpr)) == 1


@pytest.mark.parametrize("frame", FRAMES)
def test_render_products_are_full_precision(frame):
    scene = default_scene(width=16, height=16)
    scene = scene.replace(mesh=scene.mesh.with_tangents())  # traced below: computed first

    def f(scene, nm):
        out = jaxnm.render(scene.replace(normal_map=nm), outputs=("color", "perturbed_normal"),
                           frame=frame)
        return sum(jnp.sum(v) for v in out.values())

    nm = jnp.asarray(scene.normal_map)
    grad = jax.value_and_grad(f, argnums=(0, 1), allow_int=True)  # faces are integers
    jaxpr = jax.make_jaxpr(grad)(scene, nm).jaxpr
    # the frames' products, forward and backward (the camera transform is written out term
    # by term: no product; frame "none" has none at all)
    assert len(_dot_precisions(jaxpr)) >= (0 if frame == "none" else 2)
    assert not _low_precision(jaxpr)


def test_fit_products_are_full_precision():
    problem, _, _ = default_problem(render_size=16, map_size=8, n_lights=3, views=1)
    prep = F.prepare(problem)
    z = jnp.zeros((8, 8, 2))
    for reduce in (False, True):
        args = F.ModelArgs.create(prep, reduce=reduce)

        def jtj(z, v):
            r, lin = jax.linearize(lambda q: F.residuals(q, args), z)
            return jax.linear_transpose(lin, z)(lin(v)), jax.grad(F.loss)(z, args)

        jaxpr = jax.make_jaxpr(jtj)(z, z).jaxpr
        assert _dot_precisions(jaxpr) and not _low_precision(jaxpr)


def test_results_do_not_depend_on_the_default_matmul_precision():
    """On this backend the default is already full float32; asking for bfloat16-speed
    products globally must not change a render (every product names its precision)."""
    scene = default_scene(width=24, height=24)
    a = np.asarray(jaxnm.render(scene, outputs=("position", "color"))["color"])
    with jax.default_matmul_precision("bfloat16"):
        b = np.asarray(jaxnm.render(scene, outputs=("position", "color"))["color"])
    np.testing.assert_array_equal(a, b)


def _order_dependent_scatters(jaxpr) -> list:
    """The scatters whose result may depend on the order in which repeated indices are
    applied, by XLA's rule (``IsScatterDeterministic``: unique indices, or a min / max, or an
    integer add / multiply combiner). Under ``--xla_gpu_deterministic_ops`` (the CLI's and
    the tests' default) XLA sorts or serialises each of these; on an H200 the rasterizer's
    one such scatter (an id reset by a set over repeated tiles) made visibility of the 200k
    torus at 1024^2 4.5x slower (1.4 -> 6.3 ms)."""
    bad = []
    for eqn in jaxpr_equations(jaxpr):
        name = eqn.primitive.name
        if not name.startswith("scatter") or eqn.params.get("unique_indices"):
            continue
        dtype = eqn.outvars[0].aval.dtype
        if name in ("scatter-min", "scatter-max") or (
                name in ("scatter-add", "scatter-mul") and jnp.issubdtype(dtype, jnp.integer)):
            continue
        bad.append((name, str(dtype)))
    return bad


def test_the_check_sees_an_order_dependent_scatter():
    idx = jnp.array([0, 0, 1])

    def bad(x):
        return (jnp.zeros(3).at[idx].set(x), jnp.zeros(3).at[idx].add(x))

    def good(x):
        return (jnp.zeros(3).at[idx].max(x), jnp.zeros(3, jnp.int32).at[idx].add(1),
                jnp.zeros(3).at[jnp.array([0, 1, 2])].set(x, unique_indices=True))

    x = jnp.ones(3)
    assert _order_dependent_scatters(jax.make_jaxpr(bad)(x).jaxpr) == [
        ("scatter", "float32"), ("scatter-add", "float32")]
    assert _order_dependent_scatters(jax.make_jaxpr(good)(x).jaxpr) == []


@pytest.mark.parametrize("packed", [False, True])
def test_render_forward_has_no_order_dependent_scatter(packed, monkeypatch):
    """Visibility (depth test, slot bookkeeping, compaction) and the per-pixel stages, as
    `render` runs them under a caller's jit, on the whole image and packed, and as a fit's
    `prepare` runs them; the backward's float scatter-adds (a gather's transpose) are the
    fit's (GPUs: deterministic ops)."""
    import importlib

    monkeypatch.setattr(importlib.import_module("jaxnm._exec.pixels"), "PACK_MIN_PIXELS",
                        1 if packed else 1 << 40)
    scene = default_scene(width=16, height=16)

    def f(scene):
        return jaxnm.render(scene, outputs=("color", "perturbed_normal", "dpdx"),
                            derivatives="fine")

    assert _order_dependent_scatters(jax.make_jaxpr(f)(scene).jaxpr) == []
    clip = jaxnm.to_clip(scene.mesh.positions, scene.camera)
    faces = np.asarray(scene.mesh.faces)  # checked on the host: concrete
    ids = jax.make_jaxpr(lambda c: jaxnm.rasterize(c, faces, width=16,
                                                   height=16).triangle_id)(clip)
    assert _order_dependent_scatters(ids.jaxpr) == []
