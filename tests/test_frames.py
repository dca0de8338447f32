"""Tangent frames: GLSL fidelity, analytic truth, mirrored uv, invariants, HLSL ddy,
double-sided surfaces, gradients and degenerate input.

Run with ``pytest -s`` to see the measured numbers.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compute_frame_kw
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxnm
from jaxnm import frames as F
from jaxnm.camera import Camera, look_at, orthographic, perspective, to_clip
from jaxnm.geometry import vertex_normals
from jaxnm.interpolate import triangle_corners
from jaxnm.numerics import safe_normalize

SIZE = 48
# the six constructions; the other names in F.FRAMES are variants of them (and "none")
METHODS = ("cotangent", "nonperspective", "exact", "vertex", "vertex_area", "axis")
MIRROR = np.array([-1.0, 1.0, 1.0])


# --------------------------------------------------------------------------------------
# scenes and helpers (float64 NumPy, cast to float32 for rendering)
# --------------------------------------------------------------------------------------


def grid(fn, nu, nv, u_range=(0.0, 1.0), v_range=(0.0, 1.0)):
    """A (nu x nv)-cell grid; returns positions fn(U, V), the parameters (U, V) and CCW faces."""
    us, vs = np.linspace(*u_range, nu + 1), np.linspace(*v_range, nv + 1)
    U, V = np.meshgrid(us, vs, indexing="ij")
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                            np.stack([a, c, d], -1).reshape(-1, 3)])
    return fn(U, V).reshape(-1, 3), np.stack([U, V], -1).reshape(-1, 2), faces


def camera(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), *, fov=60.0, ortho=None):
    proj = perspective(fov, 1.0, 0.05, 20.0) if ortho is None else orthographic(
        -ortho, ortho, -ortho, ortho, 0.05, 20.0)
    return Camera.from_matrices(look_at(eye, target, up), proj)


def render(pos, faces, cam, size=SIZE):
    clip = to_clip(jnp.asarray(pos, jnp.float32), cam)
    return jaxnm.rasterize(clip, jnp.asarray(faces, jnp.int32), width=size, height=size)


def procedural_map(uv):
    """A smooth tangent-space map vector field (unnormalised) with non-zero x and y."""
    u, v = uv[..., 0:1], uv[..., 1:2]
    return jnp.concatenate([0.45 * jnp.sin(9.0 * u + 0.3) + 0.15, 0.35 * jnp.cos(7.0 * v),
                            jnp.ones_like(u)], -1)


V_PAD, F_PAD = 1225, 2304  # every rendered scene is padded to one shape: one compile


def pad(scene):
    """Pad a scene with unused vertices and zero-area faces to (V_PAD, F_PAD)."""
    pos, uv, nrm, faces = scene
    nv, nf = V_PAD - len(pos), F_PAD - len(faces)
    assert nv >= 0 and nf >= 0
    return (np.concatenate([pos, np.zeros((nv, 3))]), np.concatenate([uv, np.zeros((nv, 2))]),
            np.concatenate([nrm, np.tile([0.0, 0.0, 1.0], (nv, 1))]),
            np.concatenate([faces, np.zeros((nf, 3), faces.dtype)]))


@functools.partial(jax.jit, static_argnames=("mode",))
def pipeline(frags, pos, uv, nrm, eye, noise, *, mode="fine"):
    """Frame variants on one rendered scene: {name: (T, B, N, perturbed)} plus inputs.

    ``mode="fine"`` computes every variant; other modes only the screen-space ones and
    ``exact`` (to keep the compile small).
    """
    attrs = {"p": pos, "pc": pos - eye[None], "uv": uv, "n": nrm}
    if mode == "fine":
        attrs["t"] = F.vertex_tangents(pos, nrm, uv, frags.faces)
    at = jaxnm.interpolate(attrs, frags, derivatives=mode)
    m = procedural_map(at["uv"].value) + noise
    kw = dict(N=at["n"], p_attr=at["p"], uv_attr=at["uv"], tri_p=triangle_corners(pos, frags),
              tri_uv=triangle_corners(uv, frags), tangent=at.get("t"),
              front_facing=frags.front_facing)
    variants = {name: dict(frame=name) for name in ("cotangent", "nonperspective", "exact")}
    variants["cotangent_cam"] = dict(frame="cotangent", p_attr=at["pc"])  # Schueler's -V
    variants["exact_face"] = dict(frame="exact_face")
    variants["cotangent_none"] = dict(frame="cotangent", normalize="none")
    variants["cotangent_unnormalized"] = dict(frame="cotangent_unnormalized")
    if mode == "fine":
        variants.update({name: dict(frame=name) for name in ("vertex", "vertex_area", "axis")})
        variants.update({name + "_ds": dict(frame=name, double_sided=True) for name in METHODS})
        variants["cotangent_hlsl"] = dict(frame="cotangent", ddy_sign=-1)
    out = {}
    for name, extra in variants.items():
        fr = compute_frame_kw(**{**kw, **extra})
        out[name] = (fr.T, fr.B, fr.N, F.perturb_normal(fr, m))
    out["attrs"], out["m"] = at, m
    return out


def run(scene, cam, *, noise=None, mode="fine"):
    pos, uv, nrm, faces = pad(scene)
    frags = render(pos, faces, cam, SIZE)
    if noise is None:
        noise = np.zeros((SIZE, SIZE, 3), np.float32)
    out = pipeline(frags, jnp.asarray(pos, jnp.float32), jnp.asarray(uv, jnp.float32),
                   jnp.asarray(nrm, jnp.float32), cam.eye, jnp.asarray(noise, jnp.float32),
                   mode=mode)
    return frags, jax.tree.map(np.asarray, out)


def angle_deg(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def max_normalized(T, B):
    s = np.sqrt(np.maximum((T * T).sum(-1), (B * B).sum(-1)))[..., None]
    return T / s, B / s


def glsl_perturb_normal(g_vertexnormal, dp1, dp2, duv1, duv2, mapv):
    """Float64 NumPy port of the published GLSL, line by line (dFdx/dFdy given as inputs).

    ``main``: ``N = normalize(g_vertexnormal)``; ``perturb_normal``:
    ``TBN = cotangent_frame(N, -V, texcoord)``, ``normalize(TBN * map)``.
    """
    N = g_vertexnormal / np.linalg.norm(g_vertexnormal, axis=-1, keepdims=True)
    # cotangent_frame( vec3 N, vec3 p, vec2 uv )
    dp2perp = np.cross(dp2, N)
    dp1perp = np.cross(N, dp1)
    T = dp2perp * duv1[..., 0:1] + dp1perp * duv2[..., 0:1]
    B = dp2perp * duv1[..., 1:2] + dp1perp * duv2[..., 1:2]
    invmax = 1.0 / np.sqrt(np.maximum((T * T).sum(-1), (B * B).sum(-1)))[..., None]
    T, B = T * invmax, B * invmax
    # TBN * map: mat3 columns T, B, N times a column vector
    v = T * mapv[..., 0:1] + B * mapv[..., 1:2] + N * mapv[..., 2:3]
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def torus_scene(R=1.0, r=0.42, nu=48, nv=24):
    def fn(U, V):
        a, b = 2 * np.pi * U, 2 * np.pi * V
        return np.stack([(R + r * np.cos(b)) * np.cos(a), (R + r * np.cos(b)) * np.sin(a),
                         r * np.sin(b)], -1)

    pos, uv, faces = grid(fn, nu, nv)
    a, b = 2 * np.pi * uv[:, 0], 2 * np.pi * uv[:, 1]
    nrm = np.stack([np.cos(b) * np.cos(a), np.cos(b) * np.sin(a), np.sin(b)], -1)
    return pos, uv * [3.0, 1.0], nrm, faces  # 3x tiling around the ring


def sphere_angles(p):
    """(lat, lon) of points, for p = (cos lat cos lon, sin lat, -cos lat sin lon)."""
    q = p / np.linalg.norm(p, axis=-1, keepdims=True)
    return np.arcsin(np.clip(q[..., 1], -1, 1)), np.arctan2(-q[..., 2], q[..., 0])


def sphere_scene(nu=48, nv=24):
    def fn(U, V):
        lon, lat = 2 * np.pi * U - np.pi, np.pi * (V - 0.5)
        return np.stack([np.cos(lat) * np.cos(lon), np.sin(lat), -np.cos(lat) * np.sin(lon)], -1)

    pos, uv, faces = grid(fn, nu, nv)
    return pos, uv, pos.copy(), faces


PLANE_SHEAR = np.array([[0.8, 0.5], [-0.3, 1.2]])  # uv = A (x, y) + c over the plane


def plane_scene(e1, e2, n_cells=6):
    """A square in the plane spanned by orthonormal e1, e2, sheared affine uv; also grad u, v."""
    e1, e2 = np.asarray(e1, np.float64), np.asarray(e2, np.float64)
    pos, xy, faces = grid(lambda x, y: x[..., None] * e1 + y[..., None] * e2, n_cells, n_cells,
                          (-1, 1), (-1, 1))
    uv = xy @ PLANE_SHEAR.T + [0.2, 0.1]
    nrm = np.broadcast_to(np.cross(e1, e2), pos.shape).copy()
    grad_u = PLANE_SHEAR[0, 0] * e1 + PLANE_SHEAR[0, 1] * e2
    grad_v = PLANE_SHEAR[1, 0] * e1 + PLANE_SHEAR[1, 1] * e2
    return (pos, uv, nrm, faces), grad_u, grad_v


def tilted_plane():
    t, a = 0.3, 0.9
    return plane_scene([np.cos(t), np.sin(t), 0.0],
                       [-np.sin(t) * np.cos(a), np.cos(t) * np.cos(a), -np.sin(a)])


def mirror_scene(split_seam: bool):
    """Plane z = 0, x, y in [-1, 1]; u = 1 - |x| (right half mirrors the left), v = (y + 1)/2.

    Triangulated mirror-symmetrically; the seam column x = 0 is shared by both halves,
    or duplicated (``split_seam``). Always 50 vertices (unused padding when shared).
    """
    nx, ny = 8, 4
    xs, ys = -1.0 + np.arange(nx + 1) / 4.0, -1.0 + np.arange(ny + 1) / 2.0
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pos = np.stack([X, Y, np.zeros_like(X)], -1).reshape(-1, 3)
    uv = np.stack([1.0 - np.abs(X), (Y + 1.0) / 2.0], -1).reshape(-1, 2)
    idx = np.arange(pos.shape[0]).reshape(nx + 1, ny + 1)
    right_idx = idx.copy()
    extra = pos[idx[nx // 2]], uv[idx[nx // 2]]
    right_idx[nx // 2] = pos.shape[0] + np.arange(ny + 1)
    pos, uv = np.concatenate([pos, extra[0]]), np.concatenate([uv, extra[1]])
    faces = []
    for i in range(nx):
        ids = idx if (i < nx // 2 or not split_seam) else right_idx
        for j in range(ny):
            a, b, c, d = ids[i, j], ids[i + 1, j], ids[i + 1, j + 1], ids[i, j + 1]
            faces += [[a, b, c], [a, c, d]] if i < nx // 2 else [[a, b, d], [b, c, d]]
    nrm = np.broadcast_to([0.0, 0.0, 1.0], pos.shape).copy()
    return pos, uv, nrm, np.asarray(faces)


def report(name, **numbers):
    print(f"\n[{name}] " + ", ".join(f"{k}={v:.3g}" for k, v in numbers.items()))


# --------------------------------------------------------------------------------------
# GLSL fidelity
# --------------------------------------------------------------------------------------


def test_glsl_fidelity_torus():
    """jaxnm (float32) matches a float64 port of the published GLSL fed the same derivatives."""
    scene = torus_scene()
    cam = camera((0.3, -2.1, 1.9), up=(0.0, 0.0, 1.0), fov=55.0)
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 0.6, (SIZE, SIZE, 3)) * [1.0, 1.0, 0.3]  # random map vectors
    frags, out = run(scene, cam, noise=noise)
    mask = np.asarray(frags.mask)
    assert mask.sum() > 600
    at = out["attrs"]
    f64 = lambda x: x[mask].astype(np.float64)  # noqa: E731
    ref = glsl_perturb_normal(f64(at["n"].value), f64(at["pc"].ddx), f64(at["pc"].ddy),
                              f64(at["uv"].ddx), f64(at["uv"].ddy), f64(out["m"]))
    err = angle_deg(out["cotangent"][3][mask], ref)
    # world position and camera-relative position (-V) give the same frame
    cam_err = angle_deg(out["cotangent"][3], out["cotangent_cam"][3])[mask]
    report("glsl fidelity", mean_deg=err.mean(), max_deg=err.max(), p99_deg=np.quantile(err, .99),
           world_vs_camrel_max_deg=cam_err.max())
    assert err.mean() < 0.01 and err.max() < 0.01
    assert cam_err.max() < 0.01
    np.testing.assert_allclose(out["cotangent"][0][mask], out["cotangent_cam"][0][mask], atol=1e-4)
    # the perturbation is real: the map moves the normals by tens of degrees
    assert angle_deg(out["cotangent"][3], at["n"].value)[mask].mean() > 10.0


# --------------------------------------------------------------------------------------
# analytic truth
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["analytic", "fine"])
@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_plane_frames_equal_affine_uv_gradients(mode, projection):
    """Tilted plane, sheared affine uv: cotangent and exact give grad u, grad v exactly."""
    scene, gu, gv = tilted_plane()
    cam = camera((0.3, 0.4, 1.6), fov=80.0, ortho=None if projection == "perspective" else 1.2)
    frags, out = run(scene, cam, mode=mode)
    mask = np.asarray(frags.mask)
    assert mask.sum() > 400
    t_ref, b_ref = max_normalized(gu, gv)
    errors = {}
    for name in ("cotangent", "cotangent_cam", "exact", "exact_face"):
        T, B = out[name][0][mask], out[name][1][mask]
        errors[name] = max(np.abs(T - t_ref).max(), np.abs(B - b_ref).max())
        assert errors[name] < 1e-5, name
    # normalize="none": the true gradients themselves (sign and magnitude)
    for name in ("cotangent_none",):
        T, B = out[name][0][mask], out[name][1][mask]
        rel = max(np.abs(T - gu).max(), np.abs(B - gv).max()) / np.linalg.norm(gu)
        errors[name + "_rel"] = rel
        assert rel < 2e-5, name
    # non-perspective: the pixel Jacobian is not a similarity (foreshortening), so it is wrong
    T, B = out["nonperspective"][0][mask], out["nonperspective"][1][mask]
    errors["nonperspective"] = max(np.abs(T - t_ref).max(), np.abs(B - b_ref).max())
    np_angle = angle_deg(out["nonperspective"][3], out["cotangent"][3])[mask]
    report(f"plane {projection} {mode}", **errors, nonpersp_normal_err_mean_deg=np_angle.mean(),
           nonpersp_normal_err_max_deg=np_angle.max())
    assert errors["nonperspective"] > 0.04
    assert np_angle.max() > 1.0


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_nonperspective_exact_without_foreshortening(projection):
    """Plane parallel to the image plane (rotated in-plane, sheared uv): nonperspective is right."""
    t = 0.4
    scene, gu, gv = plane_scene([np.cos(t), np.sin(t), 0.0], [-np.sin(t), np.cos(t), 0.0])
    cam = camera((0.0, 0.0, 2.0), fov=70.0, ortho=None if projection == "perspective" else 1.3)
    frags, out = run(scene, cam, mode="fine")
    mask = np.asarray(frags.mask)
    t_ref, b_ref = max_normalized(gu, gv)
    for name in ("nonperspective", "cotangent"):
        err = max(np.abs(out[name][0][mask] - t_ref).max(),
                  np.abs(out[name][1][mask] - b_ref).max())
        assert err < 1e-5, name


def test_sphere_latlong_analytic_gradients():
    """UV sphere, lat-long uv: cotangent frame vs analytic grad u, grad v of the smooth sphere."""
    scene = sphere_scene()
    cam = camera((2.6, 0.6, 0.4), fov=50.0)
    frags, out = run(scene, cam, mode="fine")
    _, out_a = run(scene, cam, mode="analytic")
    mask = np.asarray(frags.mask)
    lat, lon = sphere_angles(out["attrs"]["p"].value[mask].astype(np.float64))
    sel = (np.abs(lat) < np.radians(60)) & (np.abs(lon) < np.radians(150))
    assert sel.sum() > 500
    e_lon = np.stack([-np.sin(lon), np.zeros_like(lon), -np.cos(lon)], -1)
    e_lat = np.stack([-np.sin(lat) * np.cos(lon), np.cos(lat), np.sin(lat) * np.sin(lon)], -1)
    gu = e_lon / (2 * np.pi * np.cos(lat))[..., None]
    gv = e_lat / np.pi
    t_ref, b_ref = max_normalized(gu, gv)
    # the published frame's T, B carry sign(det[dp1, dp2, N]): negative on the silhouette's
    # back-facing triangles and where the interpolated normal faces away from the eye
    n_int = out["attrs"]["n"].value[mask].astype(np.float64)
    to_eye = np.asarray(cam.eye, np.float64) - out["attrs"]["p"].value[mask]
    facing = (n_int * to_eye).sum(-1) / np.linalg.norm(n_int, axis=-1) / np.linalg.norm(
        to_eye, axis=-1)
    front = np.asarray(frags.front_facing)[mask]
    nums = {"back_facing_px": (~front).sum()}
    for label, o in (("fine", out), ("analytic", out_a)):
        T, B = o["cotangent"][0][mask], o["cotangent"][1][mask]
        flipped = (T * gu).sum(-1) < 0
        assert not np.any(flipped & (facing > 0.0) & front & sel)
        nums[f"{label}_flipped_px"] = (flipped & sel).sum()
        ok = sel & (facing > 0.0) & front
        ang_t, ang_b = angle_deg(T, gu)[ok], angle_deg(B, gv)[ok]
        len_err = np.abs(np.linalg.norm(T, axis=-1) - np.linalg.norm(t_ref, axis=-1))[ok]
        len_err = np.maximum(len_err, np.abs(np.linalg.norm(B, axis=-1)
                                             - np.linalg.norm(b_ref, axis=-1))[ok])
        nums.update({f"{label}_T_mean_deg": ang_t.mean(), f"{label}_T_max_deg": ang_t.max(),
                     f"{label}_B_mean_deg": ang_b.mean(), f"{label}_B_max_deg": ang_b.max(),
                     f"{label}_len_mean": len_err.mean(), f"{label}_len_max": len_err.max()})
        assert ang_t.mean() < 1.0 and ang_b.mean() < 1.0
        assert ang_t.max() < 8.0 and ang_b.max() < 8.0
        assert len_err.mean() < 0.03 and len_err.max() < 0.25  # facets: |grad u| ~ 1/cos(lat)
    report("sphere lat-long", **nums)


# --------------------------------------------------------------------------------------
# mirrored uv
# --------------------------------------------------------------------------------------


def _mirror_errors(out, mask, name):
    n = out[name][3]
    both = mask & mask[:, ::-1]
    mirrored = angle_deg(n, n[:, ::-1] * MIRROR)  # vs the mirror image of the mirror pixel
    unmirrored = angle_deg(n, n[:, ::-1])
    return mirrored, unmirrored, both


def test_mirrored_uv():
    """Right half's uv mirrors the left's: which methods shade mirror-symmetrically."""
    cam = camera((0.0, -1.5, 1.6), fov=60.0)
    shared = mirror_scene(split_seam=False)
    frags, out = run(shared, cam)
    _, out_split = run(mirror_scene(split_seam=True), cam)
    mask = np.asarray(frags.mask)
    tid = np.asarray(frags.triangle_id)
    faces = shared[3]
    seam_vertices = set(np.flatnonzero(np.isclose(shared[0][:45, 0], 0.0)))
    touches_seam = np.array([len(seam_vertices & set(f)) > 0 for f in faces])[np.maximum(tid, 0)]
    left = np.zeros_like(mask)
    left[:, : SIZE // 2] = True
    nums = {}
    for name in ("cotangent", "nonperspective", "exact", "exact_face"):
        mirr, _, both = _mirror_errors(out, mask, name)
        nums[name + "_max_deg"] = mirr[both].max()
        assert mirr[both].max() < 0.01, name
    # vertex tangents with a split (duplicated) seam: symmetric
    mirr, _, both = _mirror_errors(out_split, mask, "vertex")
    nums["vertex_split_max_deg"] = mirr[both].max()
    assert mirr[both].max() < 0.01
    # shared seam vertices: the two halves' tangents (+x, -x) cancel, the vertex falls back to
    # the axis tangent (-x for N = +z), so left-half triangles touching the seam interpolate
    # +x -> -x: symmetric away from the seam, broken next to it (on the left half)
    mirr, _, both = _mirror_errors(out, mask, "vertex")
    away = both & ~touches_seam & ~touches_seam[:, ::-1]
    near_left = both & touches_seam & left
    nums["vertex_shared_away_max_deg"] = mirr[away].max()
    nums["vertex_shared_seam_mean_deg"] = mirr[near_left].mean()
    assert mirr[away].max() < 0.01
    assert mirr[near_left].mean() > 5.0
    tangents = np.asarray(jax.jit(F.vertex_tangents)(
        *[jnp.asarray(x, jnp.float32) for x in (shared[0], shared[2], shared[1])], shared[3]))
    for v in seam_vertices:
        np.testing.assert_allclose(tangents[v], [-1.0, 0.0, 0.0, -1.0], atol=1e-6)
    # axis: ignores uv; N is constant, so both halves get the *same* (unmirrored) normals
    mirr, unmirr, both = _mirror_errors(out, mask, "axis")
    nums["axis_mirror_mean_deg"] = mirr[both].mean()
    nums["axis_unmirrored_max_deg"] = unmirr[both].max()
    assert unmirr[both].max() < 1e-3
    assert mirr[both].mean() > 5.0
    report("mirrored uv", **nums)


# --------------------------------------------------------------------------------------
# invariants (hypothesis), function level
# --------------------------------------------------------------------------------------


def random_derivatives(seed, n=64):
    """Random pixel derivatives: N unit, dp1, dp2 in a plane near N's, random duv (float32)."""
    rng = np.random.default_rng(seed)
    N = rng.normal(size=(n, 3))
    N /= np.linalg.norm(N, axis=-1, keepdims=True)
    nf = N + 0.3 * rng.normal(size=(n, 3))
    nf /= np.linalg.norm(nf, axis=-1, keepdims=True)
    dp1, dp2 = (x - nf * (x * nf).sum(-1, keepdims=True) for x in rng.normal(size=(2, n, 3)))
    duv1, duv2 = rng.normal(size=(2, n, 2))
    good = (np.abs((N * np.cross(dp1, dp2)).sum(-1)) > 0.2 * np.linalg.norm(dp1, axis=-1)
            * np.linalg.norm(dp2, axis=-1)) & (np.abs(duv1[:, 0] * duv2[:, 1] - duv1[:, 1]
                                                      * duv2[:, 0]) > 0.2)
    cast = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return tuple(map(cast, (N, dp1, dp2, duv1, duv2))), good


@jax.jit
def all_frames(N, dp1, dp2, duv1, duv2, m):
    """Every method and option on pixel-level inputs: ({name: Frame}, {name: perturbed}).

    ``exact*`` and ``vertex`` use the triangle with corners ``p0, p0 + dp1, p0 + dp2``.
    """
    # an offset corner that scales with the inputs (translations cost float32 digits)
    tri_p = jnp.stack([jnp.zeros_like(dp1), dp1, dp2], -2) + (dp1 - 0.5 * dp2)[..., None, :]
    tri_uv = jnp.stack([jnp.zeros_like(duv1), duv1, duv2], -2) + (0.5 * duv1)[..., None, :]
    out = {}
    for normalize, sfx in (("max", ""), ("none", "_none")):
        for ddy_sign, hl in ((1, ""), (-1, "_hlsl")):
            kw = dict(normalize=normalize, ddy_sign=ddy_sign)
            out["cotangent" + hl + sfx] = F.cotangent_frame(N, dp1, dp2, duv1, duv2, **kw)
            out["nonperspective" + hl + sfx] = F.nonperspective_frame(N, dp1, dp2, duv1, duv2, **kw)
        out["exact" + sfx] = F.exact_frame(tri_p, tri_uv, N, normalize=normalize)
        out["exact_facen" + sfx] = F.exact_frame(tri_p, tri_uv, N, use_face_normal=True,
                                                 normalize=normalize)
        out["exact_face" + sfx] = F.exact_frame(tri_p, tri_uv, normalize=normalize)
    out["axis"] = F.axis_frame(N)
    # per-vertex tangents of the single triangle, all three vertices with normal N
    vt = jax.vmap(lambda p, n, t: F.vertex_tangents(p, jnp.stack([n] * 3), t, jnp.array(
        [[0, 1, 2]])))(tri_p, N, tri_uv)
    out["vertex"] = F.vertex_frame(vt[:, 0, :3], vt[:, 0, 3], N)
    return out, {k: F.perturb_normal(fr, m) for k, fr in out.items()}


def random_map(seed, n=64):
    m = np.random.default_rng(seed).normal(size=(n, 3)) * 0.5
    m[:, 2] = np.abs(m[:, 2]) + 0.5
    return jnp.asarray(m, jnp.float32)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), s_uv=st.floats(1e-3, 1e3), s_p=st.floats(1e-3, 1e3))
def test_frames_scale_invariant(seed, s_uv, s_p):
    """normalize='max': invariant to scaling uv and world space; 'none' scales as s_uv / s_p."""
    (N, dp1, dp2, duv1, duv2), good = random_derivatives(seed)
    m = random_map(seed)
    base, _ = all_frames(N, dp1, dp2, duv1, duv2, m)
    scaled, _ = all_frames(N, dp1 * s_p, dp2 * s_p, duv1 * s_uv, duv2 * s_uv, m)
    for name in ("cotangent", "nonperspective", "exact", "exact_face", "vertex", "axis"):
        for a, b in ((base[name].T, scaled[name].T), (base[name].B, scaled[name].B)):
            np.testing.assert_allclose(np.asarray(a)[good], np.asarray(b)[good], atol=2e-5,
                                       err_msg=name)
    for name in ("cotangent_none", "exact_none", "exact_face_none"):
        np.testing.assert_allclose(np.asarray(scaled[name].T)[good],
                                   np.asarray(base[name].T)[good] * (s_uv / s_p), rtol=1e-3,
                                   atol=1e-4 * s_uv / s_p, err_msg=name)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_frames_orthogonal_to_N_and_handedness(seed):
    """T, B _|_ N (cotangent, exact); u -> -u flips det[T, B, N] for every uv-aware method."""
    (N, dp1, dp2, duv1, duv2), good = random_derivatives(seed)
    m = random_map(seed)
    base, _ = all_frames(N, dp1, dp2, duv1, duv2, m)
    for name in ("cotangent", "cotangent_none", "exact", "exact_none", "vertex", "axis"):
        for v in (base[name].T, base[name].B):
            v = np.asarray(v)
            # relative to |v|: the unnormalised ("none") frames are true gradients, not unit
            rel = np.abs((v * np.asarray(N)).sum(-1)) / np.maximum(1.0, np.linalg.norm(v, axis=-1))
            assert rel[good].max() < 1e-5, name
    flip = jnp.asarray([[-1.0, 1.0]], jnp.float32)
    mirrored, _ = all_frames(N, dp1, dp2, duv1 * flip, duv2 * flip, m)
    for name in ("cotangent", "cotangent_none", "nonperspective", "exact", "exact_face",
                 "vertex"):
        h0 = np.asarray(base[name].handedness)[good]
        h1 = np.asarray(mirrored[name].handedness)[good]
        # the non-perspective frame J J^T grad u can be nearly singular for very oblique
        # random projections: compare signs where the handedness is clear of rounding
        clear = np.abs(h0) > 1e-3
        assert clear.mean() > (0.5 if name == "nonperspective" else 0.999), name
        assert np.all(np.sign(h0[clear]) == -np.sign(h1[clear])), name
        # only T changes, and it is negated (B is the same covector)
        np.testing.assert_allclose(np.asarray(mirrored[name].B)[good],
                                   np.asarray(base[name].B)[good], atol=2e-5, err_msg=name)
    np.testing.assert_array_equal(np.asarray(mirrored["axis"].T), np.asarray(base["axis"].T))


def test_frames_broadcast_batch_shapes():
    (N, dp1, dp2, duv1, duv2), _ = random_derivatives(1, n=24)
    r = lambda x: x.reshape(2, 3, 4, -1)  # noqa: E731
    cot = jax.jit(F.cotangent_frame)
    flat = cot(N, dp1, dp2, duv1, duv2)
    shaped = cot(r(N), r(dp1), r(dp2), r(duv1), r(duv2))
    assert shaped.T.shape == (2, 3, 4, 3) and shaped.handedness.shape == (2, 3, 4)
    np.testing.assert_allclose(np.asarray(shaped.T).reshape(-1, 3), np.asarray(flat.T), atol=1e-6)


# --------------------------------------------------------------------------------------
# HLSL ddy
# --------------------------------------------------------------------------------------


def test_hlsl_ddy_sign():
    """ddy_sign=-1: cotangent 'max' -> (-T, -B, N), same handedness; 'none', nonperspective same."""
    (N, dp1, dp2, duv1, duv2), good = random_derivatives(7)
    m = random_map(3)
    fr, nrm = all_frames(N, dp1, dp2, duv1, duv2, m)
    gl, hl = fr["cotangent"], fr["cotangent_hlsl"]
    np.testing.assert_allclose(hl.T, -gl.T, atol=1e-6)
    np.testing.assert_allclose(hl.B, -gl.B, atol=1e-6)
    np.testing.assert_array_equal(hl.N, gl.N)
    np.testing.assert_allclose(hl.handedness, gl.handedness, atol=1e-5)
    # the map's tangential part is negated (180 degree rotation about N): bumps read as dents
    _, nrm_flipped = all_frames(N, dp1, dp2, duv1, duv2, m * jnp.asarray([[-1.0, -1.0, 1.0]]))
    np.testing.assert_allclose(nrm["cotangent_hlsl"], nrm_flipped["cotangent"], atol=1e-5)
    for a, b in ((fr["cotangent_none"], fr["cotangent_hlsl_none"]),
                 (fr["nonperspective"], fr["nonperspective_hlsl"]),
                 (fr["nonperspective_none"], fr["nonperspective_hlsl_none"])):
        for x, y in ((a.T, b.T), (a.B, b.B)):
            np.testing.assert_allclose(np.asarray(y)[good], np.asarray(x)[good], rtol=1e-5,
                                       atol=1e-5)
    # Schueler's advice: with N = the face normal from the same derivatives, T and B do not
    # depend on the convention (the face normal flips instead)
    nf = lambda a, b: safe_normalize(jnp.cross(a, b))  # noqa: E731
    a, _ = all_frames(nf(dp1, dp2), dp1, dp2, duv1, duv2, m)
    b, _ = all_frames(nf(dp1, -dp2), dp1, -dp2, duv1, -duv2, m)
    np.testing.assert_allclose(b["cotangent"].T, a["cotangent"].T, atol=1e-6)
    np.testing.assert_allclose(b["cotangent"].N, -a["cotangent"].N, atol=1e-6)
    with pytest.raises(ValueError, match="ddy_sign"):
        F.cotangent_frame(N, dp1, dp2, duv1, duv2, ddy_sign=0)


def test_hlsl_ddy_sign_rendered_plane():
    scene, gu, gv = tilted_plane()
    cam = camera((0.3, 0.4, 1.6), fov=80.0)
    frags, out = run(scene, cam)
    mask = np.asarray(frags.mask)
    t_ref, b_ref = max_normalized(gu, gv)
    T, B = out["cotangent_hlsl"][0][mask], out["cotangent_hlsl"][1][mask]
    np.testing.assert_allclose(T, np.broadcast_to(-t_ref, T.shape), atol=1e-5)
    np.testing.assert_allclose(B, np.broadcast_to(-b_ref, B.shape), atol=1e-5)


# --------------------------------------------------------------------------------------
# double-sided
# --------------------------------------------------------------------------------------


def test_face_forward_flips_all_three():
    (N, dp1, dp2, duv1, duv2), _ = random_derivatives(2)
    m = random_map(2)
    fr = all_frames(N, dp1, dp2, duv1, duv2, m)[0]["cotangent"]
    front = jnp.asarray([True, False] * 32)
    ff = F.face_forward(fr, front)
    s = np.where(np.asarray(front), 1.0, -1.0)[:, None]
    for a, b in ((ff.T, fr.T), (ff.B, fr.B), (ff.N, fr.N)):
        np.testing.assert_array_equal(a, np.asarray(b) * s)
    # the published cotangent frame is linear in N: flipping the frame == building it from -N
    # except for N itself (that is why compute_frame re-orients it before face_forward)
    flipped_n = all_frames(-N, dp1, dp2, duv1, duv2, m)[0]["cotangent"]
    np.testing.assert_allclose(flipped_n.T, -np.asarray(fr.T), atol=1e-6)


def test_double_sided_thin_sheet():
    """Seen from behind, every method gives exactly the negated front-side perturbed normal."""
    scene, _, _ = plane_scene([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], n_cells=4)
    pos, uv, _, faces = scene
    nrm = np.concatenate([0.3 * pos[:, :2], np.ones((len(pos), 1))], 1)  # smooth, non-constant
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    scene = (pos, uv, nrm, faces)
    eye = np.array([0.4, -1.0, 1.7])
    front_cam, back_cam = camera(eye, fov=70.0), camera(eye * [1, 1, -1], fov=70.0)
    fr_front, out_f = run(scene, front_cam)
    fr_back, out_b = run(scene, back_cam)
    mf, mb = np.asarray(fr_front.mask), np.asarray(fr_back.mask)[:, ::-1]
    assert np.all(np.asarray(fr_front.front_facing)[mf])
    assert not np.any(np.asarray(fr_back.front_facing)[mb[:, ::-1]])
    both = mf & mb
    assert both.sum() > 800
    nums = {}
    for name in METHODS:
        nf, nb = out_f[name + "_ds"][3], out_b[name + "_ds"][3][:, ::-1]
        np.testing.assert_allclose(nf[mf], out_f[name][3][mf], atol=1e-6)  # front: no change
        err = angle_deg(nb, -nf)[both]
        nums[name + "_max_deg"] = err.max()
        assert err.max() < 0.01, name
        np.testing.assert_allclose(out_b[name + "_ds"][2][:, ::-1][both],
                                   -out_f[name + "_ds"][2][both], atol=1e-6)
    # without double-sided handling the published frame has T, B = -(front) and N unflipped
    T1, B1, N1 = (x[:, ::-1][both] for x in out_b["cotangent"][:3])
    np.testing.assert_allclose(T1, -out_f["cotangent"][0][both], atol=1e-5)
    np.testing.assert_allclose(B1, -out_f["cotangent"][1][both], atol=1e-5)
    np.testing.assert_allclose(N1, out_f["cotangent"][2][both], atol=1e-6)
    # ... so flipping all three of it (plain face_forward) would keep the bump a bump
    m = out_b["m"][:, ::-1][both]
    naive = -(T1 * m[:, :1] + B1 * m[:, 1:2] + N1 * m[:, 2:])
    nums["naive_cotangent_mean_deg"] = angle_deg(naive, -out_f["cotangent"][3][both]).mean()
    assert nums["naive_cotangent_mean_deg"] > 5.0
    report("double-sided", **nums)


# --------------------------------------------------------------------------------------
# degenerate input: values and gradients finite
# --------------------------------------------------------------------------------------


def degenerate_cases():
    """Pixel-level inputs: ok, zero duv, zero N, flipped N, grazing, background, collinear uv."""
    (N, dp1, dp2, duv1, duv2), _ = random_derivatives(5, n=8)
    N, dp1, dp2, duv1, duv2 = (np.array(x) for x in (N, dp1, dp2, duv1, duv2))
    duv1[1] = duv2[1] = 0.0  # degenerate uv mapping
    N[2] = 0.0  # zero-length normal
    N[3] = -N[3]  # back face (N away from the viewer)
    dp2[4] = 2.0 * dp1[4]  # grazing: the pixel footprint collapses to a line
    N[5] = dp1[5] = dp2[5] = duv1[5] = duv2[5] = 0.0  # background / helper pixel
    duv2[6] = 3.0 * duv1[6]  # collinear uv derivatives
    N[7] = dp1[7] / np.linalg.norm(dp1[7])  # N in the face plane: det[dp1, dp2, N] = 0
    return tuple(jnp.asarray(x, jnp.float32) for x in (N, dp1, dp2, duv1, duv2))


def _degenerate_loss(N, dp1, dp2, duv1, duv2, m):
    tri_p = jnp.stack([jnp.zeros_like(dp1), dp1, dp2], -2)
    tri_uv = jnp.stack([jnp.zeros_like(duv1), duv1, duv2], -2)
    vt = jax.vmap(lambda p, n, t: F.vertex_tangents(p, jnp.stack([n] * 3), t, jnp.array(
        [[0, 1, 2]])))(tri_p, N, tri_uv)
    frames = {
        "cotangent_none": F.cotangent_frame(N, dp1, dp2, duv1, duv2, normalize="none",
                                            ddy_sign=-1),
        "nonperspective_none": F.nonperspective_frame(N, dp1, dp2, duv1, duv2, normalize="none"),
        "exact_face_none": F.exact_frame(tri_p, tri_uv, normalize="none"),
    }
    attr = lambda v, dx, dy: jaxnm.Attribute(v, dx, dy)  # noqa: E731
    for name in METHODS:  # the dispatcher, double-sided, odd cases back-facing
        frames[name] = compute_frame_kw(
            name, N=N, p_attr=attr(tri_p[:, 0], dp1, dp2), uv_attr=attr(tri_uv[:, 0], duv1, duv2),
            tri_p=tri_p, tri_uv=tri_uv, tangent=vt[:, 0], double_sided=True,
            front_facing=jnp.arange(N.shape[0]) % 2 == 0)
    names = sorted(frames)
    out = jnp.stack([F.perturb_normal(frames[k], m) for k in names])
    return jnp.sum(out * jnp.asarray([[[0.3, -0.7, 0.5]]])), dict(zip(names, out))


def test_degenerate_inputs_finite():
    """Zero uv derivatives, zero N, back face, grazing, background: finite values and gradients."""
    args = degenerate_cases()
    fn = jax.jit(jax.value_and_grad(_degenerate_loss, argnums=tuple(range(6)), has_aux=True))
    (_, out), grads = fn(*args, random_map(0, n=8))
    out = {k: np.asarray(v) for k, v in out.items()}  # name -> (case, 3)
    for k, v in out.items():
        assert np.all(np.isfinite(v)), k
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))
    n_unit = np.asarray(safe_normalize(args[0]))
    for k, v in out.items():
        # zero uv derivatives (case 1, back-facing): T = B = 0 -> the unperturbed (flipped) N
        if k in ("cotangent", "nonperspective", "exact"):
            np.testing.assert_allclose(v[1], -n_unit[1], atol=1e-6, err_msg=k)
        if k in ("cotangent_none", "nonperspective_none"):
            np.testing.assert_allclose(v[1], n_unit[1], atol=1e-6, err_msg=k)
        # zero N (case 2) through the dispatcher: no frame at all -> zero normal
        if k in METHODS:
            np.testing.assert_array_equal(v[2], 0.0, err_msg=k)
        # zero N and no derivatives (background): a zero, not NaN, normal
        np.testing.assert_array_equal(v[5], 0.0, err_msg=k)
        # unit normals for the ordinary case, back face, collinear uv and N in the face plane
        np.testing.assert_allclose(np.linalg.norm(v[[0, 3, 6, 7]], axis=-1), 1.0, atol=1e-5,
                                   err_msg=k)
    # grazing (dp1 || dp2): 'none' has no determinant -> unperturbed
    np.testing.assert_allclose(out["cotangent_none"][4], n_unit[4], atol=1e-6)
    # degenerate uv: vertex tangents fall back to the axis frame
    np.testing.assert_allclose(out["vertex"][1], out["axis"][1], atol=1e-6)
    assert np.abs(out["vertex"][1] - n_unit[1]).max() > 0.1  # (the map does perturb it)


def degenerate_scene():
    """12 vertices, 4 triangles: constant uv, back-facing (CW), grazing, ordinary."""
    pos = np.array([[-1.0, -1.0, 0.0], [0.0, -1.0, 0.0], [-0.5, -0.1, 0.0],  # constant uv
                    [0.1, -1.0, 0.0], [1.0, -0.1, 0.0], [1.0, -1.0, 0.0],  # back-facing (CW)
                    [-1.3, 0.1, 1.0], [1.3, 0.1, 1.0], [0.0, 2.0, -6.0],  # grazing
                    [-0.6, 0.65, 0.2], [0.9, 0.6, 0.1], [0.0, 1.2, 0.3]])  # ordinary
    uv = np.array([[0.5, 0.5]] * 3 + [[0, 0], [1, 1], [1, 0], [0, 0], [1, 0], [0.5, 1],
                                      [0, 0], [1, 0], [0, 1]])
    faces = np.arange(12).reshape(4, 3)
    return pos, uv, np.asarray(vertex_normals(jnp.asarray(pos), faces)), faces


@jax.jit
def _shade_all(frags, cam, nrm, pos, uv, m):
    """Perturbed normals from differentiable pos, uv, m: every method + unnormalised cotangent."""
    fr = dataclasses.replace(frags, clip=to_clip(pos, cam))
    tangent = F.vertex_tangents(pos, nrm, uv, fr.faces)
    at = jaxnm.interpolate({"p": pos, "uv": uv, "n": nrm, "t": tangent}, fr)
    kw = dict(N=at["n"], p_attr=at["p"], uv_attr=at["uv"], tri_p=triangle_corners(pos, fr),
              tri_uv=triangle_corners(uv, fr), tangent=at["t"], front_facing=fr.front_facing)
    outs = [F.perturb_normal(compute_frame_kw(name, **kw), m) for name in METHODS]
    outs.append(F.perturb_normal(compute_frame_kw("cotangent", normalize="none", **kw), m))
    return jnp.stack(outs)


def _f64_scene(scene, eye):
    """Rasterize (float32, the shared padded shape), then float64 inputs for `_shade_all`."""
    pos, uv, nrm, faces = pad(scene)
    cam = camera(eye, fov=55.0)
    frags = render(pos, faces, cam)
    m = np.random.default_rng(0).normal(size=(SIZE, SIZE, 3)) * [0.4, 0.4, 0.1] + [0, 0, 1]
    return frags, cam, nrm, pos, uv, m


def test_gradients_check_grads_float64():
    """check_grads (order 1, fwd and rev) w.r.t. the map, vertex positions and uvs, every method."""
    pos = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.3], [1.0, 1.0, 0.0], [-1.0, 1.0, -0.2]])
    uv = np.array([[0.0, 0.0], [1.1, 0.15], [1.3, 0.7], [0.1, 0.6]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])  # two triangles, non-planar
    nrm = np.asarray(vertex_normals(jnp.asarray(pos), faces))
    smooth = _f64_scene((pos, uv, nrm, faces), (0.2, 0.3, 2.6))
    degenerate = _f64_scene(degenerate_scene(), (0.0, 0.0, 2.5))
    with jax.enable_x64(True):
        frags, cam, nrm, *args = smooth
        shade = functools.partial(_shade_all, frags, cam, jnp.asarray(nrm))
        args = tuple(jnp.asarray(x, jnp.float64) for x in args)
        assert np.asarray(frags.mask).sum() > 500
        out = shade(*args)
        assert out.dtype == jnp.float64 and np.all(np.isfinite(np.asarray(out)))
        check_grads(shade, args, order=1, modes=("fwd", "rev"), eps=1e-6)

        # the same compiled functions on the degenerate scene: finite values and gradients
        frags, cam, nrm, *args = degenerate
        shade = functools.partial(_shade_all, frags, cam, jnp.asarray(nrm))
        args = tuple(jnp.asarray(x, jnp.float64) for x in args)
        tid = np.asarray(frags.triangle_id)
        assert all((tid == k).sum() > 10 for k in range(4))
        assert not np.asarray(frags.front_facing)[tid == 1].any()
        out, vjp = jax.vjp(shade, *args)
        out = np.asarray(out)
        assert np.all(np.isfinite(out))
        grads = vjp(jnp.asarray(np.random.default_rng(1).normal(size=out.shape)))
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
        assert np.abs(np.asarray(grads[0])).max() > 0
        _, tangents = jax.jvp(shade, args, tuple(jnp.ones_like(x) for x in args))
        assert np.all(np.isfinite(np.asarray(tangents)))
        # constant uv: the uv-based frames fall back to the unperturbed normal there
        n0 = nrm[0] / np.linalg.norm(nrm[0])
        sel = tid == 0
        for k in (0, 1, 2, len(METHODS)):  # cotangent, nonperspective, exact, cotangent 'none'
            np.testing.assert_allclose(out[k][sel], np.broadcast_to(n0, (sel.sum(), 3)),
                                       atol=1e-6)


# --------------------------------------------------------------------------------------
# API
# --------------------------------------------------------------------------------------


def test_compute_frame_errors():
    N = jnp.zeros((4, 3))
    with pytest.raises(ValueError, match="unknown frame"):
        F.compute_frame("tangent", N)
    with pytest.raises(ValueError, match="p_attr"):
        F.compute_frame("cotangent", N)
    with pytest.raises(ValueError, match="tri_p"):
        F.compute_frame("exact", N)
    with pytest.raises(ValueError, match="tangent"):
        F.compute_frame("vertex", N)
    with pytest.raises(ValueError, match="front_facing"):
        F.compute_frame("axis", N, options=F.FrameOptions(double_sided=True))
    with pytest.raises(ValueError, match="normalize"):
        F.FrameOptions(normalize="unit")
    with pytest.raises(ValueError, match="ddy_sign"):
        F.FrameOptions(ddy_sign=0)


def test_frame_names_are_the_documented_variants():
    """`compute_frame` takes every name in `FRAMES`: the variants are their base method with
    the documented option, and "none" leaves the normal unperturbed."""
    rng = np.random.default_rng(3)
    n = 16
    tri_p = jnp.asarray(rng.normal(size=(n, 3, 3)), jnp.float32)
    tri_uv = jnp.asarray(rng.uniform(size=(n, 3, 2)), jnp.float32)
    N = safe_normalize(jnp.cross(tri_p[:, 1] - tri_p[:, 0], tri_p[:, 2] - tri_p[:, 0])
                       + 0.2 * jnp.asarray(rng.normal(size=(n, 3)), jnp.float32))
    dp1, dp2 = tri_p[:, 1] - tri_p[:, 0], tri_p[:, 2] - tri_p[:, 0]
    duv1, duv2 = tri_uv[:, 1] - tri_uv[:, 0], tri_uv[:, 2] - tri_uv[:, 0]
    kw = dict(N=N, p_attr=jaxnm.Attribute(tri_p[:, 0], dp1, dp2),
              uv_attr=jaxnm.Attribute(tri_uv[:, 0], duv1, duv2), tri_p=tri_p, tri_uv=tri_uv)
    assert set(F.FRAMES) >= set(METHODS) | {"cotangent_unnormalized", "exact_face", "none"}
    pairs = [(compute_frame_kw("cotangent_unnormalized", **kw),
              F.cotangent_frame(N, dp1, dp2, duv1, duv2, normalize="none")),
             (compute_frame_kw("exact_face", **kw),
              F.exact_frame(tri_p, tri_uv, N, use_face_normal=True))]
    for a, b in pairs:
        for x, y in zip((a.T, a.B, a.N), (b.T, b.B, b.N)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7)
    none = compute_frame_kw("none", **kw)
    assert not np.any(np.asarray(none.T)) and not np.any(np.asarray(none.B))
    m = jnp.asarray(rng.normal(size=(n, 3)), jnp.float32).at[:, 2].set(1.0)
    np.testing.assert_allclose(np.asarray(F.perturb_normal(none, m)), np.asarray(N), atol=1e-6)
