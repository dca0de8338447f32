"""The disk cache of traced programs (`jaxnm.traced.cached_jit`): a second process (here:
the in-memory programs forgotten) calls the exported program instead of tracing again,
with the same results, and never reuses a program across other options, shapes, code or
an unreadable file; traced calls (the caller's jit, grad) stay plain `jax.jit`'s."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm.procedural import default_scene

T = importlib.import_module("jaxnm.traced")
R = importlib.import_module("jaxnm.render")

pytest.importorskip("flatbuffers")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """The traced-program cache in a fresh folder (JAX's own compilation cache stays off)."""
    folder = tmp_path / T.SUBDIR
    monkeypatch.setattr(T, "traced_cache_dir", lambda: folder)
    return folder


TRACES = []


@T.cached_jit(static_argnames=("power",))
def _poly(x, pair, *, power: int):
    TRACES.append(power)  # runs only while tracing
    return {"sum": jnp.sum(x ** power) + pair[0], "scaled": x * pair[1]}


def _args(n=5):
    x = jnp.linspace(0.5, 2.0, n, dtype=jnp.float32)
    return x, (jnp.float32(1.5), jnp.arange(n, dtype=jnp.float32))


def test_a_second_process_calls_the_exported_program(cache):
    TRACES.clear()
    _poly.clear_cache()
    x, pair = _args()
    first = _poly(x, pair, power=3)
    assert TRACES == [3] and len(list(cache.glob("*.bin"))) == 1
    _poly.clear_cache()  # as in a new process: only the file is left
    again = _poly(x, pair, power=3)
    assert TRACES == [3]  # not traced again
    want = {"sum": np.sum(np.asarray(x, np.float64) ** 3) + 1.5,
            "scaled": np.asarray(x) * np.arange(5)}
    for out in (first, again):
        assert set(out) == {"sum", "scaled"}
        np.testing.assert_allclose(out["sum"], want["sum"], rtol=1e-6)
        np.testing.assert_array_equal(out["scaled"], want["scaled"])
    assert np.array_equal(first["sum"], again["sum"])


def test_other_options_shapes_and_code_are_other_programs(cache, monkeypatch):
    TRACES.clear()
    _poly.clear_cache()
    x, pair = _args()
    _poly(x, pair, power=2)
    _poly(x, pair, power=3)  # another static option
    x7, pair7 = _args(7)
    _poly(x7, pair7, power=2)  # another shape
    _poly(x.astype(jnp.int32), pair, power=2)  # another dtype
    assert TRACES == [2, 3, 2, 2] and len(list(cache.glob("*.bin"))) == 4
    _poly.clear_cache()
    monkeypatch.setattr(T, "_code_fingerprint", lambda: "jaxnm edited")
    out = _poly(x, pair, power=2)  # the same call, but the code changed: traced again
    assert TRACES == [2, 3, 2, 2, 2] and len(list(cache.glob("*.bin"))) == 5
    np.testing.assert_allclose(out["sum"], float(jnp.sum(x ** 2)) + 1.5, rtol=1e-6)


def test_an_unreadable_entry_is_traced_again(cache):
    TRACES.clear()
    _poly.clear_cache()
    x, pair = _args()
    want = _poly(x, pair, power=2)["sum"]
    (path,) = cache.glob("*.bin")
    path.write_bytes(b"not a program")
    _poly.clear_cache()
    assert np.array_equal(_poly(x, pair, power=2)["sum"], want)
    assert TRACES == [2, 2]
    _poly.clear_cache()
    _poly(x, pair, power=2)  # the entry was written again
    assert TRACES == [2, 2]


def test_traced_calls_are_plain_jit(cache):
    TRACES.clear()
    _poly.clear_cache()
    x, pair = _args()

    def loss(x):
        return _poly(x, pair, power=2)["sum"]

    g = jax.grad(loss)(x)
    np.testing.assert_allclose(g, 2 * np.asarray(x), rtol=1e-6)
    np.testing.assert_allclose(jax.jit(loss)(x), float(jnp.sum(x ** 2)) + 1.5, rtol=1e-6)
    assert not list(cache.glob("*.bin"))  # nothing exported from inside a trace


def test_off_without_the_compilation_cache_or_by_the_switch(monkeypatch, tmp_path):
    before = jax.config.jax_compilation_cache_dir
    assert before is None  # the suite runs with the compilation cache off
    assert T.traced_cache_dir() is None
    try:  # (nothing compiles in between: JAX's cache is not started)
        jax.config.update("jax_compilation_cache_dir", str(tmp_path))
        assert T.traced_cache_dir() == tmp_path / T.SUBDIR
        monkeypatch.setenv(T.TRACED_ENV, "off")
        assert T.traced_cache_dir() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def test_render_reuses_its_exported_programs(cache, monkeypatch):
    """`render`'s visibility and frame programs, exported by one call, are called by the
    next without tracing (`to_clip` runs only while tracing visibility), and the image is
    the same bit for bit as plain `jax.jit`'s."""
    scene = default_scene(width=40, height=24)
    clips = []
    to_clip = R.to_clip
    monkeypatch.setattr(R, "to_clip", lambda *a, **k: clips.append(1) or to_clip(*a, **k))
    R._visible.clear_cache()
    R._render.clear_cache()
    first = render_color(scene)
    traced = len(clips)
    assert traced > 0 and len(list(cache.glob("*.bin"))) == 2
    R._visible.clear_cache()
    R._render.clear_cache()
    assert np.array_equal(render_color(scene), first) and len(clips) == traced
    monkeypatch.setattr(T, "traced_cache_dir", lambda: None)
    R._visible.clear_cache()
    R._render.clear_cache()
    assert np.array_equal(render_color(scene), first)  # plain jax.jit: the same image


def render_color(scene):
    return np.asarray(jaxnm.render(scene, outputs=("color",), pack=True)["color"])


FILTER_TRACES = []


@T.cached_filter_jit(donate="all-except-first")
def _update(kept, z, state):
    """An equinox-style step: ``kept = (scale, label)``, a solver-like result out."""
    import optimistix as optx

    scale, label = kept
    FILTER_TRACES.append(label)
    return z + scale, {"count": state["count"] + 1, "label": label}, optx.RESULTS.successful


def test_filter_jit_programs_come_back_from_disk_with_their_static_outputs(cache):
    import optimistix as optx

    FILTER_TRACES.clear()
    _update.clear_cache()

    def run():
        z, state = jnp.zeros(4), {"count": jnp.int32(0), "label": "a"}
        out = _update((jnp.float32(2.0), "a"), z, state)
        return out, z

    (z1, s1, r1), z_in = run()
    assert FILTER_TRACES == ["a"] and len(list(cache.glob("*.bin"))) == 1
    assert z_in.is_deleted()  # donated, as equinox.filter_jit(donate="all-except-first")
    _update.clear_cache()
    (z2, s2, r2), _ = run()
    assert FILTER_TRACES == ["a"]  # from the file: not traced
    for z, s, r in ((z1, s1, r1), (z2, s2, r2)):
        np.testing.assert_array_equal(z, np.full(4, 2.0, np.float32))
        assert int(s["count"]) == 1 and s["label"] == "a"  # a static output, as traced
        assert bool(r == optx.RESULTS.successful)
    # an option known only by its address is not written to disk
    _update.clear_cache()
    _update((jnp.float32(1.0), object()), jnp.zeros(4), {"count": jnp.int32(0), "label": "c"})
    assert len(list(cache.glob("*.bin"))) == 1


def test_a_fit_through_the_disk_cache_is_the_same_fit(cache, monkeypatch):
    """The LM step kept on disk: a second fit (the in-memory programs forgotten) traces
    nothing and ends at the same map, bit for bit, as a fit with the cache off."""
    from jaxnm import fit as F
    from jaxnm.fit.texel_lm import TexelLM
    from jaxnm.procedural import default_problem

    S = importlib.import_module("jaxnm.fit.solve")
    problem, _, _ = default_problem(render_size=48, map_size=16, n_lights=4, views=1)
    prep = F.prepare(problem, chunk=None)
    opts = F.FitOptions(max_steps=4, lsmr_steps=5, ftol=0.0)
    steps = []
    step = TexelLM.step
    monkeypatch.setattr(TexelLM, "step", lambda self, *a: steps.append(1) or step(self, *a))

    compiles, counting = [], [False]

    def listen(name, seconds, **kwargs):
        if counting[0] and name == "/jax/core/compile/backend_compile_duration":
            compiles.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(listen)  # (0.8.0: cannot unregister)

    def fit():
        S._COMPILED_AHEAD.clear()
        S._step.clear_cache()
        compiles.clear()
        counting[0] = True
        try:
            return F.fit_normal_map(problem, opts, prepared=prep, progress=False).slopes
        finally:
            counting[0] = False

    before = len(list(cache.glob("*.bin")))  # the targets' and prepare's programs
    on = fit()
    traced = len(steps)
    assert traced > 0 and len(list(cache.glob("*.bin"))) == before + 1  # the step's
    # compiled once: the first state (made on the host) and the later ones (the step's
    # outputs) are placed alike (an uncommitted first state was a second compilation)
    assert len(compiles) == 1, compiles
    again = fit()
    assert len(steps) == traced  # the step came from its file
    assert len(compiles) == 1, compiles
    monkeypatch.setattr(T, "traced_cache_dir", lambda: None)
    off = fit()
    assert len(steps) > traced
    assert np.array_equal(on, off) and np.array_equal(again, off)


@T.cached_jit
def _with_callback(x):
    return jax.pure_callback(lambda a: np.asarray(a) * 2,
                             jax.ShapeDtypeStruct(x.shape, x.dtype), x)


def test_a_program_jax_cannot_export_runs_as_plain_jit(cache):
    x = jnp.arange(3, dtype=jnp.float32)
    for _ in range(2):
        np.testing.assert_array_equal(_with_callback(x), [0.0, 2.0, 4.0])
    assert not list(cache.glob("*.bin"))
