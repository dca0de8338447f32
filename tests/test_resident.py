"""The accelerators' programs (`jaxnm._exec.device.resident`), forced on the CPU: a frame, its
gradient and a fit step run with every transfer disallowed, compile to programs whose loops
all have trip counts known at compile time and that call nothing on the host, and give the
CPU path's images (visibility bit for bit).

On a GPU, XLA reads back the condition of a loop whose trip count it does not know, and the
predicate of a conditional, at every iteration; the checks below read the optimised HLO that
the CPU's compiler makes of the same program (it runs the same loop analysis, and annotates
``known_trip_count``)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm import fit as F
from jaxnm import procedural
from jaxnm._exec.device import forced, resident
from jaxnm.fit.solve import _step
from jaxnm.raster import RasterStrategy

GEOMETRY = ("mask", "triangle_id", "depth", "front_facing")
OUTPUTS = ("color",) + GEOMETRY

#: Custom-call targets and instructions that run on, or wait for, the host.
HOST = re.compile(r"callback|infeed|outfeed|\bsend\(|\brecv\(|host", re.IGNORECASE)


def hlo_report(hlo: str) -> dict:
    """The optimised HLO's loops without a known trip count, its conditionals and the
    custom calls or instructions that involve the host."""
    loops = [line for line in hlo.splitlines() if re.search(r"\bwhile\(", line)]
    targets = re.findall(r'custom_call_target="([^"]+)"', hlo)
    return {"while": len(loops),
            "unknown_trip_count": [w[:120] for w in loops if "known_trip_count" not in w],
            "conditional": len(re.findall(r"\bconditional\(", hlo)),
            "host": sorted({t for t in targets if HOST.search(t)}
                           | set(re.findall(r"\b(infeed|outfeed|send|recv)\(", hlo)))}


def test_the_hlo_report_can_fail():
    def f(x):
        y = jax.lax.while_loop(lambda c: c[0] < c[1], lambda c: (c[0] + 1, c[1]), (0, x))[0]
        return jax.pure_callback(lambda v: v, jax.ShapeDtypeStruct((), jnp.int32), y)

    bad = hlo_report(jax.jit(f).lower(3).compile().as_text())
    assert bad["unknown_trip_count"] and bad["host"], bad
    good = hlo_report(jax.jit(lambda x: jax.lax.fori_loop(0, 5, lambda i, c: c * x, x))
                      .lower(1.5).compile().as_text())
    assert good["while"] == 1 and not good["unknown_trip_count"] and not good["host"], good


def assert_resident(hlo: str, conditionals: int = 0):
    r = hlo_report(hlo)
    assert not r["unknown_trip_count"] and not r["host"], r
    assert r["conditional"] <= conditionals, r


def test_the_path_is_chosen_by_backend_or_forced():
    assert resident("gpu") and resident("tpu") and not resident("cpu")
    with forced():
        assert resident("cpu")
    with forced(False):
        assert not resident("gpu")


@pytest.fixture(scope="module")
def scene():
    return jax.device_put(procedural.default_scene(width=64, height=48))


def _frame(scene):
    return jaxnm.render(scene, outputs=OUTPUTS)


def _same_images(a: dict, b: dict):
    for n in GEOMETRY:
        np.testing.assert_array_equal(np.asarray(a[n]), np.asarray(b[n]), err_msg=n)
    # (float32 rounding: the programs fuse differently, e.g. around `materialize`)
    np.testing.assert_allclose(np.asarray(a["color"]), np.asarray(b["color"]), rtol=1e-5,
                               atol=1e-6)


def test_a_resident_frame_stays_on_the_device_and_equals_the_cpu_frame(scene):
    cpu = jax.jit(_frame)(scene)
    with forced():
        with jax.transfer_guard("disallow"):
            out = jax.jit(_frame)(scene)
            jax.block_until_ready(out)
        hlo = jax.jit(_frame).lower(scene).compile().as_text()
    # (the rasterizer's overflow: one conditional around the rounds past those a frame always
    # runs, which only a frame with more slots enters, and one in it around each such round)
    assert_resident(hlo, conditionals=2)
    assert np.asarray(cpu["mask"]).any()
    _same_images(cpu, out)


def test_the_gradient_of_a_resident_frame_stays_on_the_device(scene):
    def loss(texels, scene):
        return jnp.sum(jaxnm.render(scene.replace(normal_map=texels))["color"] ** 2)

    grad = jax.jit(jax.grad(loss))
    cpu = grad(scene.normal_map, scene)
    with forced():
        with jax.transfer_guard("disallow"):
            g = jax.block_until_ready(grad(scene.normal_map, scene))
        hlo = grad.lower(scene.normal_map, scene).compile().as_text()
    assert_resident(hlo, conditionals=2)  # (the rasterizer's overflow, as above)
    assert np.abs(np.asarray(cpu)).max() > 0
    np.testing.assert_allclose(np.asarray(g), np.asarray(cpu), rtol=1e-5,
                               atol=1e-6 * np.abs(np.asarray(cpu)).max())


def test_views_through_vmap_are_one_program_with_the_loop_s_images(scene):
    eyes = [(0.0, -2.35, 1.75), (1.5, -1.8, 1.2), (-1.2, -2.0, 2.0)]
    cams = [jaxnm.Camera.from_matrices(jaxnm.camera.look_at(e, (0.0, 0.0, -0.1), (0, 0, 1)),
                                       np.asarray(scene.camera.projection)) for e in eyes]
    stacked = jax.device_put(jax.tree_util.tree_map(lambda *x: np.stack(x), *cams))

    def frames(cameras, scene):
        return jax.vmap(lambda c: _frame(scene.replace(camera=c)))(cameras)

    with forced():
        one = jax.jit(_frame)
        loop = [one(scene.replace(camera=jax.device_put(c))) for c in cams]
        with jax.transfer_guard("disallow"):
            batch = jax.block_until_ready(jax.jit(frames)(stacked, scene))
        hlo = jax.jit(frames).lower(stacked, scene).compile().as_text()
    # under vmap a conditional becomes a select of both branches: none is left
    assert_resident(hlo, conditionals=0)
    for v, single in enumerate(loop):
        _same_images(single, {n: batch[n][v] for n in OUTPUTS})


def test_resident_rasterizer_overflow_and_passes_give_the_cpu_path_s_ids():
    # large triangles and small rounds: the slots overflow the rounds that always run
    # (and, with small passes, the passes), which then run behind conditionals
    mesh = procedural.uv_sphere(1.0, 12, 6)
    cam = procedural.default_scene(width=40, height=32).camera
    clip = jax.device_put(jaxnm.camera.to_clip(mesh.positions, cam))
    faces = jax.device_put(np.asarray(mesh.faces, np.int32))
    small = RasterStrategy(block=4, slots=64)
    passes = RasterStrategy(block=4, slots=64, pass_slots=256)

    def ids(clip, faces, strategy):
        f = jaxnm.rasterize(clip, faces, width=40, height=32, strategy=strategy)
        return f.triangle_id, f.depth, f.front_facing

    want = jax.jit(ids, static_argnums=2)(clip, faces, RasterStrategy())
    assert (np.asarray(want[0]) >= 0).mean() > 0.2
    for strategy in (small, passes):
        with forced():
            with jax.transfer_guard("disallow"):
                got = jax.block_until_ready(jax.jit(ids, static_argnums=2)(clip, faces, strategy))
        for a, b in zip(want, got):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.fixture(scope="module")
def fit_args():
    problem, _, _ = procedural.default_problem(render_size=32, map_size=16, n_lights=2, views=1)
    prep = F.prepare(problem)
    return F.ModelArgs.create(prep), F.make_solver(F.FitOptions())


def test_a_resident_fit_step_stays_on_the_device_and_equals_the_cpu_step(fit_args):
    args, solver = fit_args
    z0 = np.zeros((16, 16, 2), np.float32) + 0.05

    def run():  # two steps: the first (its damping) and an ordinary one
        z = jax.device_put(z0)
        state = F.start_state(args, solver, z)
        with jax.transfer_guard("disallow"):
            out = F.fit_step(args, solver, z, state)
            out = F.fit_step(args, solver, out.z, out.state)
            return jax.block_until_ready((out.z, out.loss))

    cpu = run()
    with forced():
        got = run()
        z = jax.device_put(z0)
        # the program `fit_step` runs: the solver's step and its bookkeeping
        lowered = _step.lower((args, solver), z, F.start_state(args, solver, z))
        hlo = lowered.compile().compiled.as_text()  # (equinox's wrapper of JAX's Compiled)
    assert_resident(hlo, conditionals=0)
    assert float(cpu[1]) > 0
    np.testing.assert_allclose(np.asarray(got[0]), np.asarray(cpu[0]), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(got[1]), float(cpu[1]), rtol=1e-6)


def test_the_cpu_keeps_its_loops():
    """Where programs are not resident, the rounds stay a loop of data-dependent trip count
    (the CPU skips the rounds a frame does not need): the switch is what the checks above
    see."""
    clip = jnp.asarray([[-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.0, 0.5, 0.0, 1.0]])
    faces = np.asarray([[0, 1, 2]], np.int32)

    def ids(clip):
        return jaxnm.rasterize(clip, faces, width=16, height=16,
                               strategy=RasterStrategy(slots=4)).triangle_id

    with forced(False):
        assert hlo_report(jax.jit(ids).lower(clip).compile().as_text())["unknown_trip_count"]
    with forced():
        assert_resident(jax.jit(ids).lower(clip).compile().as_text(), conditionals=2)


def test_the_gpu_check_script_parses_and_names_every_frame_goal():
    """`scripts/benchmarks/gpu_check.sh` is for a GPU machine: here only its shell syntax and
    its helper's goals (its --quick run on the CPU takes minutes)."""
    import subprocess
    from pathlib import Path

    from scripts.benchmarks import gpu_check

    script = Path(__file__).resolve().parents[1] / "scripts" / "benchmarks" / "gpu_check.sh"
    assert subprocess.run(["bash", "-n", str(script)]).returncode == 0
    assert set(gpu_check.GOALS_MS) == {"20k torus 512", "200k torus 1024",
                                       "64 views 20k torus 512"}
