r"""A height field as real geometry vs. the same height field as a normal map on a flat plane.

The scene: a gentle, smooth height field

.. math:: h(x, y) = \sum_k a_k \sin(2\pi (k_x x + k_y y) / L + \varphi_k)

(``L = 2``, four waves, peak |h| = 0.061, peak slope |grad h| = 0.35, i.e. 19
degrees; wavelengths 0.55 to 1.4, each wave's amplitude under 3% of its
wavelength), rendered
two ways with the same camera, lights, material and resolution (96 x 96):

(a) *geometry*: a 2.4 x 2.4 grid of 96 x 96 quads (18432 triangles, ~1.3 pixels
    per quad) displaced to ``z = h(x, y)``, with the analytic vertex normals
    ``normalize(-h_x, -h_y, 1)`` and no normal map;
(b) *normal map*: a flat 8 x 8-quad plane at ``z = 0`` with a 256 x 256
    tangent-space normal map of the same ``h`` (trilinear, cotangent frame; uv
    = the plane's (x, y) rotated by 0 or 60 degrees, 3 world units per uv unit):
    either the analytic normals stored as a float ("signed") map, or
    `jaxnm.maps.height_to_normal_map` of the heights at the texel centres,
    quantised to an 8-bit ("unsigned") map.

Two cameras: ``perspective`` (eye 5 units above the plane, tilted 7 degrees,
20 degree field of view: every view ray within 21 degrees of the vertical) and
``ortho`` (orthographic, straight down). Both see only the inside of the plane
(no silhouettes). Two directional lights at 46 and 37 degrees elevation (more
than the steepest slope) keep ``N . L > 0``: no terminator enters the comparison.
Lambert and Blinn-Phong (specular 0.25, shininess 16) are compared per pixel
and channel in linear radiance. The geometry image has values 0.66 to 1.0 with
a standard deviation of 0.065; an unperturbed plane differs from it by 0.045 on
average.

**Tolerances, and why** (all |difference| in linear radiance, mean and 95th
percentile; measured values in brackets, Lambert / Blinn-Phong):

1. *Parallax* (perspective only) dominates. The displaced point above
   ``(x, y)`` projects to where the flat plane shows ``(x, y) + h tan(alpha)``,
   ``alpha <= 21`` degrees the view angle: a shift of at most
   ``0.061 * tan 21 = 0.023`` world units, 1.3 pixels (measured from the two
   G-buffers' positions: mean 0.003, max 0.015; a pixel is 0.0185). The shading
   then comes from a normal that far away; the curvature is up to 4.3, so at the
   most curved spots the normal differs by up to ~4 degrees, on average by a few
   tenths of a degree.
   Shading both G-buffers' positions with the analytic normal isolates this
   part: [0.0009 / 0.0013 mean, 0.0035 / 0.0052 p95].
2. *Filtering* of the map (trilinear, ~1.6 texels per pixel, decoded after
   filtering) and *tessellation* of the geometry (linearly interpolated vertex
   normals over ~1-pixel triangles): second order, [~0.0002 / 0.0003 mean] each.
3. *Quantisation* of the 8-bit map: <= 1/255 per component, ~0.2 degrees:
   [0.0003 / 0.0005 mean with the ortho camera, vs 0.00013 / 0.00023 for the float map].

Asserted, about twice the measured worst case of the four maps: perspective
mean < 0.002 / 0.003 and p95 < 0.007 / 0.010; ortho (no parallax) mean <
0.0006 / 0.001 and p95 < 0.002 / 0.003 (a map shifted by half a texel fails
the ortho bound 3.5 times over). The comparison has teeth: the unperturbed plane,
the same map read with the wrong green convention (``green="down"``), and the
``axis`` frame with a uv layout it does not assume are each at least 8 times
over the mean bound. The ``axis`` frame ignores uv: it matches only when the uv
layout happens to agree with its fixed tangent (``T = N x (0, 1, 0) = -x``,
``B = -y`` for a +z normal, i.e. uv rotated by 180 degrees), while ``cotangent``
matches for every rotation.
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np
import pytest

import jaxnm
from jaxnm import frames as F
from jaxnm.gbuffer import RenderOptions, shade_gbuffer
from jaxnm.geometry import Mesh
from jaxnm.maps import height_to_normal_map
from jaxnm.render import build_gbuffer, render
from jaxnm.scene import Scene
from jaxnm.shading import DirectionalLight, Lights, Material, stack_lights
from jaxnm.textures import NormalMapOptions, encode_normal_map, quantize

SIZE = 96  # render resolution
PLANE = 2.4  # side of both meshes (the camera sees about 1.8 x 1.8 of it)
SEGMENTS = 96  # grid quads per side of the displaced mesh
MAP = 256  # normal-map texels per side
UV_SPAN = 3.0  # world units covered by the map along u and v (uv = R (x, y) / UV_SPAN + 1/2)
L = 2.0
#: (amplitude, k_x, k_y, phase) of the height field's waves
WAVES = ((0.024, 2.0, 1.0, 0.3), (0.015, 1.0, -3.0, 1.1), (0.0105, 3.0, 2.0, -0.4),
         (0.012, -1.0, 1.0, 2.0))

#: (mean, 95th percentile) bounds of |difference| per camera and shading model (see the docstring)
TOL = {"perspective": {"lambert": (0.002, 0.007), "blinn_phong": (0.003, 0.010)},
       "ortho": {"lambert": (0.0006, 0.002), "blinn_phong": (0.001, 0.003)}}


def height(x, y):
    """h and (h_x, h_y) (float64)."""
    h = np.zeros_like(x)
    hx = np.zeros_like(x)
    hy = np.zeros_like(x)
    for a, kx, ky, ph in WAVES:
        arg = 2 * np.pi * (kx * x + ky * y) / L + ph
        h += a * np.sin(arg)
        c = a * 2 * np.pi / L * np.cos(arg)
        hx += c * kx
        hy += c * ky
    return h, hx, hy


def rotation(deg: float) -> np.ndarray:
    t = np.radians(deg)
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def uv_of(xy: np.ndarray, uv_deg: float) -> np.ndarray:
    """The uv layout: the plane's (x, y) rotated by ``uv_deg``, scaled, centred on (1/2, 1/2)."""
    return xy @ rotation(uv_deg).T / UV_SPAN + 0.5


def grid(segments: int, uv_deg: float, displaced: bool) -> Mesh:
    """A PLANE x PLANE grid in z = 0 facing +z (CCW), optionally displaced to z = h(x, y)."""
    t = np.linspace(-PLANE / 2, PLANE / 2, segments + 1)
    x, y = np.meshgrid(t, t, indexing="xy")
    x, y = x.ravel(), y.ravel()
    if displaced:
        z, hx, hy = height(x, y)
        n = np.stack([-hx, -hy, np.ones_like(x)], 1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    else:
        z, n = np.zeros_like(x), np.tile([0.0, 0.0, 1.0], (x.size, 1))
    pos = np.stack([x, y, z], 1)
    k = segments + 1
    ii, jj = np.meshgrid(np.arange(segments), np.arange(segments), indexing="xy")
    a = (jj * k + ii).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + k + 1], 1), np.stack([a, a + k + 1, a + k], 1)])
    return Mesh(jnp.asarray(pos, jnp.float32), jnp.asarray(faces, jnp.int32),
                jnp.asarray(uv_of(pos[:, :2], uv_deg), jnp.float32), jnp.asarray(n, jnp.float32))


def texel_points(uv_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """World (x, y) at the map's texel centres (GL convention, uv origin bottom-left)."""
    c = (np.arange(MAP) + 0.5) / MAP
    u, v = np.meshgrid(c, 1.0 - c, indexing="xy")  # row 0 = top = v near 1
    uv = np.stack([u, v], -1) - 0.5
    xy = UV_SPAN * uv @ rotation(uv_deg)  # inverse of uv_of: R^T (uv - 1/2) * span
    return xy[..., 0], xy[..., 1]


def analytic_map(uv_deg: float) -> np.ndarray:
    """Signed (decoded) tangent-space map: the world normal in the frame (grad u, grad v, z)."""
    x, y = texel_points(uv_deg)
    _, hx, hy = height(x, y)
    g = np.stack([hx, hy], -1) @ rotation(uv_deg).T  # the slope along the (unit) T and B
    n = np.concatenate([-g, np.ones_like(x)[..., None]], -1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def converted_map(uv_deg: float) -> np.ndarray:
    """8-bit unsigned map from `height_to_normal_map` of the heights sampled at texel centres."""
    x, y = texel_points(uv_deg)
    h, _, _ = height(x, y)
    # scale = height units per texel step: the map's texels are UV_SPAN / MAP world units apart
    n = np.asarray(height_to_normal_map(jnp.asarray(h, jnp.float32), scale=MAP / UV_SPAN,
                                        wrap="clamp"))
    return np.asarray(quantize(encode_normal_map(jnp.asarray(n)), 8))


def camera(kind: str = "perspective") -> jaxnm.Camera:
    """``perspective``: tilted 7 degrees, 20 degree fov; ``ortho``: straight down, no parallax."""
    if kind == "ortho":
        return jaxnm.Camera.from_matrices(
            jaxnm.look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
            jaxnm.orthographic(-0.9, 0.9, -0.9, 0.9, 1.0, 20.0))
    return jaxnm.Camera.look_at((0.35, -0.5, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                fov_y_deg=20.0, near=1.0, far=20.0)


def lights() -> Lights:
    d = np.array([[0.6, 0.35, 0.72], [-0.75, 0.25, 0.6]])  # 46 and 37 degrees elevation
    colors = ([1.0, 0.95, 0.9], [0.5, 0.6, 0.8])
    return Lights(directional=stack_lights([
        DirectionalLight(jnp.asarray(di / np.linalg.norm(di), jnp.float32), jnp.asarray(c),
                         jnp.asarray(1.0)) for di, c in zip(d, colors)]))


MATERIAL = Material(diffuse=jnp.ones(3), specular=jnp.full((3,), 0.25),
                    shininess=jnp.asarray(16.0), ambient=jnp.full((3,), 0.03))


def scene(mesh: Mesh, normal_map=None, nm_opts=NormalMapOptions(), cam: str = "perspective"
          ) -> Scene:
    return Scene(mesh=mesh, camera=camera(cam), width=SIZE, height=SIZE, normal_map=normal_map,
                 normal_map_options=nm_opts, albedo=np.array([0.8, 0.8, 0.8], np.float32),
                 lights=lights(), material=MATERIAL, source="<height field>").replace()


def shade_all(sc: Scene, *, frame: str = "cotangent", nm_opts=None) -> dict[str, np.ndarray]:
    """Colour per shading model (and the mask): one G-buffer, shaded by each model.

    ``frame="axis"`` is built here with `jaxnm.frames.compute_frame` and put into the
    cotangent G-buffer (which has the uv sample plan): see `test_render_axis_frame_uses_map`.
    ``nm_opts`` overrides the decode options (same texels, same sample plan).
    """
    opts = RenderOptions.of(sc, outputs=("color",), frame="cotangent")
    gb = build_gbuffer(sc.mesh, sc.camera, jnp.asarray(sc.albedo), opts=opts)
    if frame == "axis":
        gb = dataclasses.replace(gb, frame=F.compute_frame(
            "axis", gb.normal, inputs=F.FrameInputs(front_facing=gb.front_facing),
            options=F.FrameOptions(double_sided=True)))
    elif frame != "cotangent":
        raise ValueError(frame)
    if nm_opts is not None:
        opts = dataclasses.replace(opts, normal_map=nm_opts)
    nm = None if sc.normal_map is None else jnp.asarray(sc.normal_map)
    out = {"mask": np.asarray(gb.mask), "position": np.asarray(gb.position)}
    for model in ("lambert", "blinn_phong"):
        o = dataclasses.replace(opts, shading=model)
        out[model] = np.asarray(shade_gbuffer(gb, nm, sc.lights, sc.material, opts=o)["color"])
    return out


def diff_stats(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mean, 95th percentile) of |a - b| over pixels and channels."""
    d = np.abs(a - b)
    return float(d.mean()), float(np.percentile(d, 95))


@functools.cache
def geometry_image(cam: str = "perspective") -> dict[str, np.ndarray]:
    return shade_all(scene(grid(SEGMENTS, 0.0, displaced=True), cam=cam))


@functools.cache
def plane_scene(uv_deg: float, source: str, cam: str = "perspective") -> Scene:
    mesh = grid(8, uv_deg, displaced=False)
    if source == "analytic":
        return scene(mesh, analytic_map(uv_deg), NormalMapOptions(encoding="signed"), cam=cam)
    return scene(mesh, converted_map(uv_deg), NormalMapOptions(encoding="unsigned"), cam=cam)


def report(name: str, **nums) -> None:
    print(f"[heightfield] {name}: " + ", ".join(f"{k}={v:.4g}" for k, v in nums.items()))


# --------------------------------------------------------------------------------------


def test_setup_is_as_documented():
    """The numbers the docstring's tolerance argument rests on."""
    x, y = texel_points(0.0)  # a 3 x 3 square around the origin, 256 x 256 points
    h, hx, hy = height(x, y)
    slope_deg = np.degrees(np.arctan(np.hypot(hx, hy).max()))
    assert np.abs(h).max() < 0.062 and slope_deg < 19.5
    elevation = np.degrees(np.arcsin(lights().directional.direction[:, 2]))
    assert elevation.min() > slope_deg + 15  # N . L > 0 everywhere
    geo = geometry_image()
    assert geo["mask"].all()  # the plane fills the image: no silhouettes
    assert geo["lambert"].std() > 0.05  # there is shading to compare
    # every view ray within 21 degrees of the vertical
    cam = camera()
    inv = np.linalg.inv(np.asarray(cam.view_projection, np.float64))
    corners = np.array([[sx, sy, 1.0, 1.0] for sx in (-1, 1) for sy in (-1, 1)])
    far = corners @ inv.T
    d = far[:, :3] / far[:, 3:] - np.asarray(cam.eye, np.float64)
    max_angle = np.degrees(np.arccos(-d[:, 2] / np.linalg.norm(d, axis=1))).max()
    assert max_angle < 21.0
    # the parallax shift between what the two renders show at the same pixel
    flat = shade_all(scene(grid(8, 0.0, displaced=False)))
    shift = np.linalg.norm(geo["position"][..., :2] - flat["position"][..., :2], axis=-1)
    report("parallax shift (world units)", mean=shift.mean(), max=shift.max(),
           bound=np.abs(h).max() * np.tan(np.radians(max_angle)))
    assert shift.max() <= np.abs(h).max() * np.tan(np.radians(max_angle)) + 1e-4
    assert shift.mean() < 0.004
    ortho = shade_all(scene(grid(SEGMENTS, 0.0, displaced=True), cam="ortho"))
    flat_o = shade_all(scene(grid(8, 0.0, displaced=False), cam="ortho"))
    np.testing.assert_allclose(ortho["position"][..., :2], flat_o["position"][..., :2],
                               atol=1e-5)


@pytest.mark.parametrize("cam", ["perspective", "ortho"])
@pytest.mark.parametrize("source", ["analytic", "height_to_normal_map"])
@pytest.mark.parametrize("uv_deg", [0.0, 60.0])
def test_normal_map_matches_displaced_geometry(cam, source, uv_deg):
    geo = geometry_image(cam)
    mapped = shade_all(plane_scene(uv_deg, source, cam))
    flat = shade_all(scene(grid(8, uv_deg, displaced=False), cam=cam))
    assert geo["mask"].all() and mapped["mask"].all()  # no silhouettes
    for model, (tol_mean, tol_p95) in TOL[cam].items():
        mean, p95 = diff_stats(mapped[model], geo[model])
        flat_mean, _ = diff_stats(flat[model], geo[model])
        report(f"{cam} {source} uv {uv_deg:g} deg {model}", mean=mean, p95=p95,
               flat_mean=flat_mean)
        assert mean < tol_mean, (model, mean)
        assert p95 < tol_p95, (model, p95)
        assert flat_mean > 8 * TOL["perspective"][model][0]  # the map does the work


@pytest.mark.parametrize("uv_deg", [0.0, 60.0])
def test_wrong_green_convention_is_caught(uv_deg):
    """The same texels decoded as a DirectX ("green down") map: y is mirrored."""
    geo = geometry_image()
    sc = plane_scene(uv_deg, "height_to_normal_map")
    right = shade_all(sc)
    wrong = shade_all(sc, nm_opts=dataclasses.replace(sc.normal_map_options, green="down"))
    for model, (tol_mean, tol_p95) in TOL["perspective"].items():
        mean_r, _ = diff_stats(right[model], geo[model])
        mean_w, p95_w = diff_stats(wrong[model], geo[model])
        report(f"green down, uv {uv_deg:g} deg {model}", mean=mean_w, p95=p95_w, right=mean_r)
        assert mean_r < tol_mean
        assert mean_w > 8 * tol_mean and p95_w > 3 * tol_p95


def test_half_texel_shift_is_caught():
    """Without parallax the comparison resolves a map shifted by half a texel (0.006 units)."""
    geo = geometry_image("ortho")
    sc = plane_scene(60.0, "analytic", "ortho")
    shifted = sc.replace(mesh=dataclasses.replace(sc.mesh, uv=sc.mesh.uv + 0.5 / MAP))
    out = shade_all(shifted)
    for model, (tol_mean, _) in TOL["ortho"].items():
        mean, p95 = diff_stats(out[model], geo[model])
        report(f"ortho, map shifted by half a texel, {model}", mean=mean, p95=p95)
        assert mean > 2.5 * tol_mean


def test_axis_frame_ignores_uv_orientation():
    """The fixed-axis frame is right only for one uv orientation; cotangent for every one."""
    geo = geometry_image()
    errors = {}
    for uv_deg in (0.0, 60.0, 180.0):
        sc = plane_scene(uv_deg, "analytic")
        for frame in ("cotangent", "axis"):
            errors[frame, uv_deg] = diff_stats(shade_all(sc, frame=frame)["lambert"],
                                               geo["lambert"])[0]
    report("axis vs cotangent (lambert mean |diff|)",
           **{f"{f}_{d:g}": v for (f, d), v in errors.items()})
    tol_mean = TOL["perspective"]["lambert"][0]
    for uv_deg in (0.0, 60.0, 180.0):
        assert errors["cotangent", uv_deg] < tol_mean
    # with N = +z the axis frame is T = N x (0, 1, 0) = -x, B = N x T = -y: the uv layout
    # rotated by 180 degrees
    assert errors["axis", 180.0] < tol_mean
    for uv_deg in (0.0, 60.0):
        assert errors["axis", uv_deg] > 8 * tol_mean
        assert errors["axis", uv_deg] > 10 * errors["cotangent", uv_deg]


def test_render_axis_frame_uses_map():
    """`render(frame="axis")` should perturb the normal like the frames-level axis frame."""
    sc = plane_scene(180.0, "analytic")
    out = render(sc, outputs=("color",), frame="axis")["color"]
    ref = shade_all(sc, frame="axis")["blinn_phong"]
    np.testing.assert_allclose(out, ref, atol=1e-5)
