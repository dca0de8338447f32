"""The public verbs state their array shapes with jaxtyping, and the annotations are right.

Each verb is checked by jaxtyping with beartype (``jaxtyped(typechecker=beartype)``, the
checker optimistix and equinox test with): called with the shapes a tiny scene produces it
passes and returns what the unchecked verb returns; called with an array of the wrong shape
it is refused before any work. The library itself runs unchecked: the annotations cost
nothing at run time."""

import inspect

import beartype
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import TypeCheckError, jaxtyped

import jaxnm
from jaxnm import geometry, raster
from jaxnm.procedural import plane
from jaxnm.scene import default_material

CHECK = beartype.beartype(conf=beartype.BeartypeConf(is_pep484_tower=True))

#: The verbs whose array arguments carry jaxtyping shapes.
VERBS = {
    "to_clip": jaxnm.to_clip, "rasterize": jaxnm.rasterize, "triangle_ids": raster.triangle_ids,
    "overdraw": raster.overdraw, "face_normals": geometry.face_normals,
    "vertex_normals": geometry.vertex_normals, "cotangent_frame": jaxnm.cotangent_frame,
    "perturb_normal": jaxnm.perturb_normal, "shade": jaxnm.shade,
    "build_mipmaps": jaxnm.build_mipmaps, "decode_normal_map": jaxnm.decode_normal_map,
    "encode_normal_map": jaxnm.encode_normal_map,
}
ARRAY_PARAMS = {"to_clip": ["positions"], "rasterize": ["clip", "faces"],
                "triangle_ids": ["clip", "faces"], "overdraw": ["clip", "faces"],
                "face_normals": ["positions", "faces"], "vertex_normals": ["positions", "faces"],
                "cotangent_frame": ["N", "dp1", "dp2", "duv1", "duv2"],
                "perturb_normal": ["m"], "shade": ["N", "p", "eye"], "build_mipmaps": ["tex"],
                "decode_normal_map": ["raw"], "encode_normal_map": ["n"]}


def checked(fn):
    return jaxtyped(typechecker=CHECK)(fn)


@pytest.mark.parametrize("name", list(VERBS))
def test_array_arguments_state_their_shapes(name):
    sig = inspect.signature(VERBS[name])
    for p in ARRAY_PARAMS[name]:
        ann = str(sig.parameters[p].annotation)
        assert any(k in ann for k in ("Float[", "Integer[", "Real[")), (name, p, ann)


@pytest.fixture(scope="module")
def scene():
    mesh = plane(segments=2)
    cam = jaxnm.Camera.look_at((0.3, 0.2, 2.0), (0.0, 0.0, 0.0), fov_y_deg=40)
    return mesh, cam


def _same(a, b):
    for x, y in zip(np.atleast_1d(a), np.atleast_1d(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_the_geometry_verbs_pass_with_their_shapes_and_refuse_others(scene):
    mesh, cam = scene
    pos, faces = mesh.positions, mesh.faces
    clip = checked(jaxnm.to_clip)(pos, cam)
    _same(clip, jaxnm.to_clip(pos, cam))
    assert clip.shape == (pos.shape[0], 4)
    frags = checked(jaxnm.rasterize)(clip, faces, width=8, height=6)
    _same(frags.triangle_id, jaxnm.rasterize(clip, faces, width=8, height=6).triangle_id)
    assert checked(raster.overdraw)(clip, faces, width=8, height=6).shape == (6, 8)
    ids, _ = checked(raster.triangle_ids)(clip, faces, width=8, height=6)
    _same(ids, frags.triangle_id)
    _same(checked(geometry.face_normals)(pos, faces), geometry.face_normals(pos, faces))
    _same(checked(geometry.vertex_normals)(pos, faces), geometry.vertex_normals(pos, faces))
    with pytest.raises(TypeCheckError):
        checked(jaxnm.to_clip)(pos[:, :2], cam)  # (V, 2) positions
    with pytest.raises(TypeCheckError):
        checked(jaxnm.rasterize)(clip[:, :3], faces, width=8, height=6)  # (V, 3) clip
    with pytest.raises(TypeCheckError):
        checked(jaxnm.rasterize)(clip, faces.astype(jnp.float32), width=8, height=6)
    with pytest.raises(TypeCheckError):
        checked(geometry.vertex_normals)(pos, faces[:, :2])


def test_the_shading_verbs_pass_with_their_shapes_and_refuse_others():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(5, 7, 3)).astype(np.float32)
    dp1, dp2 = (rng.normal(size=(5, 7, 3)).astype(np.float32) for _ in range(2))
    duv1, duv2 = (rng.normal(size=(5, 7, 2)).astype(np.float32) for _ in range(2))
    frame = checked(jaxnm.cotangent_frame)(n, dp1, dp2, duv1, duv2)
    _same(frame.T, jaxnm.cotangent_frame(n, dp1, dp2, duv1, duv2).T)
    m = np.broadcast_to(np.array([0.2, -0.1, 0.9], np.float32), n.shape)
    _same(checked(jaxnm.perturb_normal)(frame, m), jaxnm.perturb_normal(frame, m))
    light, mat = jaxnm.directional_light((0.3, 0.4, 1.0)), default_material()
    eye = np.array([0.0, 0.0, 3.0], np.float32)
    rgb = checked(jaxnm.shade)("blinn_phong", n, dp1, eye, light, mat)
    _same(rgb, jaxnm.shade("blinn_phong", n, dp1, eye, light, mat))
    with pytest.raises(TypeCheckError):
        checked(jaxnm.cotangent_frame)(n, dp1, dp2, duv1[..., :1], duv2)  # (..., 1) duv
    with pytest.raises(TypeCheckError):
        checked(jaxnm.perturb_normal)(frame, m[..., :2])
    with pytest.raises(TypeCheckError):
        checked(jaxnm.shade)("blinn_phong", n[..., :2], dp1, eye, light, mat)


def test_the_texture_verbs_pass_with_their_shapes_and_refuse_others():
    tex = np.random.default_rng(1).uniform(size=(8, 4, 3)).astype(np.float32)
    mips = checked(jaxnm.build_mipmaps)(tex)
    assert [m.shape for m in mips] == [(8, 4, 3), (4, 2, 3), (2, 1, 3), (1, 1, 3)]
    n = checked(jaxnm.decode_normal_map)(tex)
    _same(n, jaxnm.decode_normal_map(tex))
    two = checked(jaxnm.encode_normal_map)(n, channels=2)
    assert two.shape == (8, 4, 2)
    with pytest.raises(TypeCheckError):
        checked(jaxnm.build_mipmaps)(tex[..., 0])  # (H, W): no channel axis
    with pytest.raises(TypeCheckError):
        checked(jaxnm.encode_normal_map)(n[..., :2])
