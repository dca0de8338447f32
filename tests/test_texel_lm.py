"""The texel-space Levenberg-Marquardt (`jaxnm.fit.texel_lm`, ``solver="lm-texel"``): its
loss, gradient and Gauss-Newton products against the residuals' own linearisation, its
fits against the known map, and its memory against the views."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxnm import fit as F
from jaxnm.fit.texel_lm import (
    TexelLM,
    _gauss_newton_parts,
    _gauss_newton_product,
    texel_sum_tables,
)
from jaxnm.procedural import default_problem


@pytest.fixture(scope="module")
def small():
    """The built-in problem, small (as test_fit's): 64x64 renders, a 32x32 map, 6 lights, 2
    views; prepared whole and in chunks of both pixel groups."""
    problem, gt, _ = default_problem(render_size=64, map_size=32, n_lights=6, views=2)
    whole = F.prepare(problem, chunk=None)
    cut = F.prepare(problem, chunk=600)
    assert min(cut.batches[0].chunks) > 1 and whole.batches[0].chunks == (1, 1)
    return problem, gt, whole, cut


@jax.jit
def _parts(z, args, v):
    f, g, factors = _gauss_newton_parts(z, args)
    return f, g, _gauss_newton_product(z, args, factors)(v)


def test_loss_gradient_and_products_are_the_residuals(small):
    """One pass over the pixels gives 0.5 |r|^2, J^T r and (from the kept factors) J^T J v of
    the full residuals (3 per target and pixel, the smoothness penalty's included: the
    pixels' share would fail it alone), with the preconditioner in, whole or in chunks."""
    smoothness = 0.02
    _, _, whole, cut = small
    rng = np.random.default_rng(3)
    z = jnp.asarray(rng.normal(0, 0.3, (32, 32, 2)), jnp.float32)
    v = jnp.asarray(rng.normal(0, 1.0, (32, 32, 2)), jnp.float32)
    args = F.ModelArgs.create(whole, scale=F.preconditioner(whole), smoothness=smoothness)
    r, lin = jax.linearize(lambda q: F.residuals(q, args), z)
    transpose = jax.linear_transpose(lin, z)
    f_ref = 0.5 * sum(float(np.sum(np.asarray(x, np.float64) ** 2)) for x in r)
    g_ref, h_ref = transpose(r)[0], transpose(lin(v))[0]
    for prep in (whole, cut):
        f, g, h = _parts(z, F.ModelArgs.create(prep, scale=args.scale, smoothness=smoothness), v)
        np.testing.assert_allclose(float(f), f_ref, rtol=1e-5)
        for got, want in ((g, g_ref), (h, h_ref)):
            # H is L L^T = B^T B + delta I per pixel (delta: 1e-6 of the trace)
            np.testing.assert_allclose(np.asarray(got), np.asarray(want),
                                       atol=1e-5 * float(jnp.max(jnp.abs(want))))


def test_texel_sums_by_tables_equal_the_scatter_adds(small):
    """With the fixed-order texel sums (`texel_sum_tables`, ``texel_sums="tables"``) a step's
    loss, gradient and Gauss-Newton products equal the scatter-adds' to float32 rounding,
    whole and in chunks (tables stacked per chunk; three levels deep here); a fit with them
    (smoothness included) takes the same steps, and two fits give the same map bit for bit."""
    problem, gt, whole, cut = small
    rng = np.random.default_rng(4)
    z = jnp.asarray(rng.normal(0, 0.3, (32, 32, 2)), jnp.float32)
    v = jnp.asarray(rng.normal(0, 1.0, (32, 32, 2)), jnp.float32)
    for prep in (whole, cut):
        sums = texel_sum_tables(prep)
        counts = [n for _, _, n, _ in prep.batches[0].pixel_groups()]
        assert [t.targets.shape[0] for t in sums[0]] == counts
        scale = F.preconditioner(prep)
        want = _parts(z, F.ModelArgs.create(prep, scale=scale, smoothness=0.01), v)
        got = _parts(z, F.ModelArgs.create(prep, scale=scale, smoothness=0.01,
                                           texel_sums=sums), v)
        np.testing.assert_allclose(float(got[0]), float(want[0]), rtol=1e-6)
        for g, w in zip(got[1:], want[1:]):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w),
                                       atol=1e-5 * float(jnp.max(jnp.abs(w))))
    opts = F.FitOptions(max_steps=4, ftol=0.0, smoothness=1e-3)
    # "auto": tables only on an accelerator with deterministic ops
    assert F.texel_sums_for(whole, opts, backend="cpu", deterministic=True) == "scatter"
    assert F.texel_sums_for(whole, opts, backend="gpu", deterministic=False) == "scatter"
    assert F.texel_sums_for(whole, opts, backend="gpu", deterministic=True) == "tables"
    assert F.texel_sums_for(whole, dataclasses.replace(opts, texel_sums="tables"),
                            backend="cpu") == "tables"
    tables = dataclasses.replace(opts, texel_sums="tables")
    a = F.fit_normal_map(problem, opts, prepared=cut, progress=False)
    b = F.fit_normal_map(problem, tables, prepared=cut, progress=False)
    c = F.fit_normal_map(problem, tables, prepared=cut, progress=False)
    np.testing.assert_array_equal(c.slopes, b.slopes)
    np.testing.assert_allclose([h["loss"] for h in b.history],
                               [h["loss"] for h in a.history], rtol=1e-3)
    np.testing.assert_allclose(b.slopes, a.slopes, atol=0.01 * np.abs(a.slopes).max())


def test_texel_sums_option_is_checked():
    with pytest.raises(ValueError, match="unknown texel_sums 'atomic'"):
        F.FitOptions(texel_sums="atomic")
    with pytest.raises(ValueError, match="'lm-texel' solver, not 'lm'"):
        F.FitOptions(solver="lm", texel_sums="tables")
    assert F.TEXEL_SUMS == ("auto", "scatter", "tables")


def test_fits_the_known_map_monotonically(small):
    """From a flat start, lm-texel recovers the map (< 1 deg mean over the seen texels) in as
    few steps as optimistix's LM needs; the recorded loss (the accepted point's) never
    rises; the result is deterministic."""
    problem, gt, whole, _ = small
    seen = F.seen_texels(whole, problem.map_size)
    opts = F.FitOptions(solver="lm-texel", max_steps=15, ftol=0.0)
    res = F.fit_normal_map(problem, opts, ground_truth=gt, prepared=whole, progress=False)
    ref = F.fit_normal_map(problem, F.FitOptions(solver="lm", max_steps=15, ftol=0.0),
                           ground_truth=gt, prepared=whole, progress=False)
    err = F.error_report(res.normals, gt, seen)["mean_deg"]
    err_ref = F.error_report(ref.normals, gt, seen)["mean_deg"]
    assert err < 1.0 and err < 1.5 * err_ref, (err, err_ref)
    loss = np.array([h["loss"] for h in res.history])
    assert loss[-1] < 1e-5 * loss[0]
    assert np.all(np.diff(loss) <= 0), loss
    again = F.fit_normal_map(problem, opts, ground_truth=gt, prepared=whole, progress=False)
    np.testing.assert_array_equal(again.slopes, res.slopes)


def test_chunked_fit_follows_the_whole_one(small):
    """The step on a chunked problem takes the steps of the whole one, smoothness included
    (float32 rounding, summed in another order, grows over steps on a few texels:
    optimistix's LM differs 6% between the two after such steps). Coarse-to-fine levels
    with this solver: test_fit's ``test_coarse_to_fine_and_smoothness`` (the default)."""
    problem, gt, whole, cut = small
    opts = F.FitOptions(solver="lm-texel", max_steps=6, ftol=0.0, smoothness=1e-3)
    a = F.fit_normal_map(problem, opts, prepared=whole, progress=False)
    b = F.fit_normal_map(problem, opts, prepared=cut, progress=False)
    np.testing.assert_allclose(b.slopes, a.slopes, atol=0.03 * np.abs(a.slopes).max())
    np.testing.assert_allclose([h["loss"] for h in b.history],
                               [h["loss"] for h in a.history], rtol=1e-3)


def test_damping_rises_after_a_rejected_step(small):
    """The predicted decrease is the Gauss-Newton model's. A proposed move that increases
    the loss (a short step up the gradient) is rejected: the point and its loss stay, the
    damping grows 4x and the next proposal is shorter."""
    _, _, whole, _ = small
    args = F.ModelArgs.create(whole, scale=F.preconditioner(whole))
    solver = TexelLM(cg_steps=10)
    z = jnp.zeros((32, 32, 2), jnp.float32)
    step = jax.jit(solver.step)
    z, state, *_ = step(z, solver.init(z, args), args)
    # the predicted decrease (from the CG identity d.(H + lam I) d = -g.d) is the model's
    product = _gauss_newton_product(z, args, state.factors)
    d, g = state.delta, state.g
    model = -(jnp.sum(g * d) + 0.5 * jnp.sum(d * product(d)))
    assert float(state.predicted) == pytest.approx(float(model), rel=1e-3)
    uphill = 0.01 * state.g / jnp.max(jnp.abs(state.g))
    assert float(F.loss(z + uphill, args)) > float(state.f)
    bad = state.__class__(**{**vars(state), "delta": uphill})
    z2, state2, done, _, f2 = step(z, bad, args)
    np.testing.assert_array_equal(np.asarray(z2), np.asarray(z))
    assert float(f2) == float(state.f) and not bool(done)
    assert float(state2.lam) == pytest.approx(4 * float(state.lam), rel=1e-6)
    assert float(jnp.linalg.norm(state2.delta)) < float(jnp.linalg.norm(state.delta))


@pytest.mark.parametrize("scale", [1.0, 1e-4])
def test_conjugate_gradient_solves_at_any_scale(scale):
    """`conjugate_gradient` solves an SPD system to its tolerance in at most n steps, at
    any scale of the operator (lineax's CG reports a breakdown where p.Ap is small in
    absolute terms); a few steps lower the quadratic it minimises."""
    from jaxnm.fit.texel_lm import conjugate_gradient

    rng = np.random.default_rng(0)
    n = 40
    q = rng.normal(size=(n, n))
    a = scale * (q @ q.T / n + 0.1 * np.eye(n))
    b = rng.normal(size=n)
    def op(x):
        return jnp.asarray(a, jnp.float32) @ x

    x = conjugate_gradient(op, jnp.asarray(b, jnp.float32), max_steps=n, rtol=1e-5)
    want = np.linalg.solve(a, b)
    np.testing.assert_allclose(np.asarray(x), want, rtol=0, atol=1e-3 * np.abs(want).max())
    # a few steps only: the iterate is not the solution yet, but it lowers the quadratic
    x3 = np.asarray(conjugate_gradient(op, jnp.asarray(b, jnp.float32), max_steps=3),
                    np.float64)
    quad = lambda y: 0.5 * y @ a @ y - b @ y  # noqa: E731
    assert quad(want) < quad(x3) < quad(np.zeros(n))
