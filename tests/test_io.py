"""Tests of jaxnm.io against hand-written files whose content is known.

Mesh and image files are written here (as text, or byte by byte with a
reference PNG encoder written from the PNG spec), or come from
tests/data/make_assets.py (glTF, written with numpy and json only).
"""

import json
import re
import struct
import warnings
import zlib
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
import pytest
import trimesh
from PIL import Image

from jaxnm.geometry import vertex_normals
from jaxnm.io import (
    JaxnmWarning,
    check_tangent_normal_map,
    load_aovs,
    load_gltf_normal_map,
    load_image_float,
    load_json,
    load_mesh,
    load_texture,
    save_aovs,
    save_png,
)
from jaxnm.procedural import default_normal_map_texels
from jaxnm.textures import NormalMapOptions

DATA = Path(__file__).parent / "data"


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _named(path: Path) -> str:
    """Regex matching an error message that names ``path``'s file."""
    return re.escape(path.name)


def _corners(mesh):
    """Per face corner: (position, uv) as numpy arrays (F, 3, 3) and (F, 3, 2)."""
    f = np.asarray(mesh.faces)
    return np.asarray(mesh.positions)[f], np.asarray(mesh.uv)[f]


def _reference_normals(pos, faces, weighting="angle"):
    """Float64 reference: sum over faces of (corner angle * unit face normal) or of
    (face area * unit face normal), normalised."""
    pos = np.asarray(pos, np.float64)
    acc = np.zeros_like(pos)
    for tri in np.asarray(faces):
        p = pos[tri]
        n = np.cross(p[1] - p[0], p[2] - p[0])  # length: twice the area
        for i in range(3):
            e1, e2 = p[(i + 1) % 3] - p[i], p[(i + 2) % 3] - p[i]
            angle = np.arccos(np.dot(e1, e2) / np.linalg.norm(e1) / np.linalg.norm(e2))
            acc[tri[i]] += angle * n / np.linalg.norm(n) if weighting == "angle" else n
    return acc / np.linalg.norm(acc, axis=1, keepdims=True)


# ============================================================================ OBJ

QUAD_OBJ = """\
# a quad, with uv and normals; the MTL file does not exist
mtllib quad_missing.mtl
o quad
v 0 0 0
v 1 0 0
v 1 1 0.5
v 0 1 0
vt 0 0
vt 1 0
vt 1 0.75
vt 0 1
vn 0 0 1
vn 0 0.6 0.8
usemtl paint
f 1/1/1 2/2/1 3/3/2
f 1/1/1 3/3/2 4/4/1
"""


def test_obj_with_uv_and_normals_exact(tmp_path):
    m = load_mesh(_write(tmp_path / "quad.obj", QUAD_OBJ), require_uv=True)
    np.testing.assert_array_equal(
        m.positions, np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0]], np.float32))
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_array_equal(m.uv, np.array([[0, 0], [1, 0], [1, 0.75], [0, 1]], np.float32))
    np.testing.assert_allclose(m.normals, [[0, 0, 1], [0, 0, 1], [0, 0.6, 0.8], [0, 0, 1]],
                               atol=1e-7)
    assert m.positions.dtype == np.float32 and m.faces.dtype == np.int32
    assert m.uv.dtype == np.float32 and m.normals.dtype == np.float32


def test_obj_uv_seam_vertices_are_not_merged(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    vt = np.array([[0, 0], [0.5, 0], [0.5, 0.5], [0, 0.5], [0.75, 0], [1, 0.25]], np.float32)
    fv = np.array([[1, 2, 4], [2, 5, 4]])  # both faces use vertices 2 and 4 ...
    ft = np.array([[1, 2, 4], [5, 6, 3]])  # ... with different uvs: a seam
    text = "".join(f"v {x} {y} {z}\n" for x, y, z in v)
    text += "".join(f"vt {s} {t}\n" for s, t in vt)
    text += "".join("f " + " ".join(f"{a}/{b}" for a, b in zip(rv, rt)) + "\n"
                    for rv, rt in zip(fv, ft))
    path = _write(tmp_path / "seam.obj", text)
    with pytest.warns(JaxnmWarning, match="no vertex normals in the file"):
        m = load_mesh(path)
    assert m.num_vertices == 6  # distinct (v, vt) pairs
    pos, uv = _corners(m)
    np.testing.assert_array_equal(pos, v[fv - 1])
    np.testing.assert_array_equal(uv, vt[ft - 1])


def test_obj_with_uvs_on_some_faces_only_says_where_they_stop(tmp_path):
    """trimesh drops every uv (normal) of an OBJ whose faces have them only in part: a
    warning says so and names the first face without, so that the error of a caller needing
    uvs is understood."""
    text = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nvn 0 0 1\n"
            "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
            "f 1/1/1 2/2/1 3/3/1\nf 1/1/1 3/3/1 4/4/1\nf 2//1 5//1 3//1\n")
    path = _write(tmp_path / "partial.obj", text)
    with pytest.warns(JaxnmWarning, match=re.escape(
            f"{path}: only 6 of 9 face corners have texture coordinates (the first without: "
            "line 13); ignoring them all")):
        m = load_mesh(path)
    assert m.uv is None and m.num_faces == 3
    with pytest.raises(ValueError, match="no texture coordinates"), warnings.catch_warnings():
        warnings.simplefilter("ignore", JaxnmWarning)
        load_mesh(path, require_uv=True)
    # faces without uvs in a material group of their own: trimesh keeps the other group's,
    # and the one warning is about the groups
    path = _write(tmp_path / "groups.obj", text.replace("f 2//1", "usemtl b\nf 2//1"))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert load_mesh(path).uv is None
    said = [str(w.message) for w in seen if "texture coordinates" in str(w.message)]
    assert said == [f"{path}: only 1 of 2 meshes have texture coordinates; ignoring them all"]
    # normals likewise: every vertex's normal is then computed
    path = _write(tmp_path / "partial_n.obj", text.replace("f 2//1 5//1 3//1", "f 2/2 5/3 3/4"))
    with pytest.warns(JaxnmWarning, match=re.escape(
            f"{path}: only 6 of 9 face corners have normals (the first without: line 13), "
            "which were dropped; computed angle-weighted normals")):
        m = load_mesh(path)
    assert m.uv is not None
    np.testing.assert_allclose(m.normals, np.tile([0.0, 0, 1], (m.num_vertices, 1)), atol=1e-6)


def test_obj_without_normals_warns_and_computes_angle_weighted(tmp_path):
    # an open pyramid: four triangles around the apex, uneven angles at the base
    text = "v 0 0 1\nv -1 -1 0\nv 2 -1 0\nv 1 1 0\nv -1 1 0\n"
    text += "f 1 2 3\nf 1 3 4\nf 1 4 5\nf 1 5 2\n"
    path = _write(tmp_path / "pyramid.obj", text)
    with pytest.warns(JaxnmWarning, match=re.escape(
            f"{path}: no vertex normals in the file; computed angle-weighted normals")):
        m = load_mesh(path)
    assert m.uv is None
    # jitted: one compilation instead of one per operation (keeps this file fast)
    want = jax.jit(vertex_normals, static_argnames="weighting")(m.positions, m.faces,
                                                                weighting="angle")
    np.testing.assert_allclose(m.normals, want, atol=1e-6)
    np.testing.assert_allclose(m.normals, _reference_normals(m.positions, m.faces),
                               atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("weighting", ["angle", "area"])
def test_normals_forced_recomputation_ignores_the_file(tmp_path, weighting):
    m = load_mesh(_write(tmp_path / "quad.obj", QUAD_OBJ), normals=weighting)  # no warning
    want = _reference_normals(m.positions, m.faces, weighting)
    assert not np.allclose(want[1], [0, 0, 1])  # differs from the file's normal
    np.testing.assert_allclose(m.normals, want, atol=1e-6)


def test_bad_normals_option(tmp_path):
    with pytest.raises(ValueError, match="normals="):
        load_mesh(_write(tmp_path / "quad.obj", QUAD_OBJ), normals="flat")


def test_obj_polygons_are_triangulated_and_degenerate_triangles_kept(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\n"
    text += "f 1 2 3 4   # a quad, with a comment that trimesh alone cannot parse\n"
    text += "f 1 2 5\n"  # collinear: zero area
    path = _write(tmp_path / "poly.obj", text)
    with pytest.warns(JaxnmWarning):
        m = load_mesh(path)
    assert m.num_faces == 3
    area = 0.5 * np.linalg.norm(np.cross(*(np.asarray(m.positions)[np.asarray(m.faces)][:, 1:]
                                           - np.asarray(m.positions)[np.asarray(m.faces)][:, :1]
                                           ).transpose(1, 0, 2)), axis=1)
    np.testing.assert_allclose(np.sort(area), [0.0, 0.5, 0.5], atol=1e-7)
    assert np.all(np.isfinite(m.normals))


def test_obj_two_materials_are_concatenated(tmp_path):
    text = QUAD_OBJ + "v 5 0 0\nvt 0.5 0.5\nvn 1 0 0\nusemtl other\nf 2/2/3 5/5/3 3/3/3\n"
    m = load_mesh(_write(tmp_path / "two.obj", text))
    pos, uv = _corners(m)
    got = sorted(tuple(np.round(np.c_[p, t], 6).ravel()) for p, t in zip(pos, uv))
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0], [5, 0, 0]])
    vt = np.array([[0, 0], [1, 0], [1, 0.75], [0, 1], [0.5, 0.5]])
    want = sorted(tuple(np.c_[v[f], vt[f]].ravel()) for f in ([0, 1, 2], [0, 2, 3], [1, 4, 2]))
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_normals_partly_in_the_file(tmp_path):
    text = ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 5 0 0\nv 6 0 0\nv 5 1 0\nvn 0 0 1\n"
            "usemtl a\nf 1//1 2//1 3//1\nusemtl b\nf 4 5 6\n")
    path = _write(tmp_path / "partial.obj", text)
    with pytest.warns(JaxnmWarning, match="for 3 of 6 vertices"):
        m = load_mesh(path)
    np.testing.assert_allclose(m.normals, np.tile([0, 0, 1], (6, 1)), atol=1e-7)


@pytest.mark.parametrize("face, what", [
    ("f 1 2 9", "vertex 9"),
    ("f 0 1 2", "vertex 0"),
    ("f -5 1 2", "vertex -5"),
    ("f 1/1 2/2 3/9", "texture coordinate 9"),
    ("f 1//1 2//1 3//4", "normal 4"),
])
def test_obj_out_of_range_face_index(tmp_path, face, what):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n" + face + "\n"
    path = _write(tmp_path / "badindex.obj", text)
    with pytest.raises(ValueError, match=_named(path) + ".*line 8.*" + what):
        load_mesh(path)


@pytest.mark.parametrize("line", ["v 1 0 zz", "v 1 0", "vt 0.5 x"])
def test_obj_malformed_line_is_named(tmp_path, line):
    text = "v 0 0 0\nvt 0 0\n" + line + "\nv 0 1 0\nv 1 1 0\nvt 1 1\nf 1/1 2/2 3/1\n"
    path = _write(tmp_path / "malformed.obj", text)
    kind, form = ("v", "x y z") if line.startswith("v ") else ("vt", "u [v [w]]")
    with pytest.raises(ValueError, match="^" + re.escape(
            f"{path}: line 3: {line!r}: a '{kind}' line holds {form} (numbers)") + "$"):
        load_mesh(path)


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_obj_non_finite_positions(tmp_path, value):
    path = _write(tmp_path / "nanpos.obj", f"v {value} 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=_named(path) + ".*NaN or infinite"):
        load_mesh(path)


def test_obj_nan_uv(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt nan 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
    path = _write(tmp_path / "nanuv.obj", text)
    with pytest.raises(ValueError, match=_named(path) + ".*uv"):
        load_mesh(path)


def test_require_uv(tmp_path):
    path = _write(tmp_path / "nouv.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\n")
    assert load_mesh(path).uv is None
    with pytest.raises(ValueError, match=re.escape(
            f"{path}: the mesh has no texture coordinates (uv)")):
        load_mesh(path, require_uv=True)


def test_obj_without_faces(tmp_path):
    path = _write(tmp_path / "points.obj", "v 0 0 0\nv 1 0 0\n")
    with pytest.raises(ValueError, match=_named(path) + ".*no faces"):
        load_mesh(path)


# ============================================================================ PLY, STL, OFF

PLY_HEADER = """\
ply
format ascii 1.0
element vertex {nv}
property float x
property float y
property float z
{props}element face {nf}
property list uchar int vertex_indices
end_header
"""


def _ply(path, vertices, faces, props=""):
    text = PLY_HEADER.format(nv=len(vertices), nf=len(faces), props=props)
    text += "".join(" ".join(map(str, v)) + "\n" for v in vertices)
    text += "".join(f"{len(f)} " + " ".join(map(str, f)) + "\n" for f in faces)
    return _write(path, text)


UV_NORMAL_PROPS = "".join(f"property float {p}\n" for p in ("nx", "ny", "nz", "s", "t"))


def test_ply_with_uv_and_normals_exact(tmp_path):
    verts = [[0, 0, 0, 0, 0, 2, 0, 0],  # a non-unit normal: renormalised
             [1, 0, 0, 0, 0.6, 0.8, 1, 0],
             [0, 1, 0, 0, 0, 1, 0.25, 1]]
    m = load_mesh(_ply(tmp_path / "tri.ply", verts, [[0, 1, 2]], UV_NORMAL_PROPS))
    v = np.array(verts, np.float32)
    np.testing.assert_array_equal(m.positions, v[:, :3])
    np.testing.assert_array_equal(m.faces, [[0, 1, 2]])
    np.testing.assert_array_equal(m.uv, v[:, 6:])
    np.testing.assert_allclose(m.normals, [[0, 0, 1], [0, 0.6, 0.8], [0, 0, 1]], atol=1e-7)


@pytest.mark.parametrize("normal", [[0, 0, 0], ["nan", 0, 0]])
def test_unusable_file_normal_is_replaced(tmp_path, normal):
    verts = [[0, 0, 0, *normal, 0, 0], [1, 0, 0, 1, 0, 0, 1, 0], [0, 1, 0, 1, 0, 0, 0, 1]]
    path = _ply(tmp_path / "zeronormal.ply", verts, [[0, 1, 2]], UV_NORMAL_PROPS)
    with pytest.warns(JaxnmWarning, match=_named(path) + ".*1 vertex normals.*zero-length or "
                      "not finite"):
        m = load_mesh(path)
    np.testing.assert_allclose(m.normals, [[0, 0, 1], [1, 0, 0], [1, 0, 0]], atol=1e-7)


@pytest.mark.parametrize("face", [[0, 1, 7], [0, 1, -1]])
def test_ply_out_of_range_face_index(tmp_path, face):
    path = _ply(tmp_path / "badindex.ply", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [face])
    with pytest.raises(ValueError, match=_named(path) + ".*face indices"):
        load_mesh(path)


def test_ply_point_cloud_has_no_faces(tmp_path):
    text = PLY_HEADER.split("element face")[0].format(nv=2, props="") + "end_header\n0 0 0\n1 0 0\n"
    path = _write(tmp_path / "cloud.ply", text)
    with pytest.raises(ValueError, match=_named(path) + ".*no faces"):
        load_mesh(path)


def test_stl_and_off(tmp_path):
    stl = _write(tmp_path / "tri.stl", "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n"
                 "vertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n")
    off = _write(tmp_path / "quad.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    for path, nf in ((stl, 1), (off, 2)):
        with pytest.warns(JaxnmWarning, match="no vertex normals"):
            m = load_mesh(path)
        assert m.uv is None and m.num_faces == nf
        np.testing.assert_allclose(m.normals, np.tile([0, 0, 1], (m.num_vertices, 1)), atol=1e-7)
    with pytest.raises(ValueError, match=_named(stl) + ".*no texture coordinates.*STL"):
        load_mesh(stl, require_uv=True)


def test_computed_normals_join_the_vertices_at_one_position(tmp_path):
    """An STL's triangles each have their own vertices, and an OBJ's uv seam splits its
    vertices: normals computed for them are the surface's, not each triangle's. On an
    icosphere every vertex normal then lies within a degree of the radius (a face's normal
    is 10 degrees off on average); across a seam on a roof's ridge, both copies of a ridge
    vertex get the mean of the two slopes' normals."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    sphere.export(tmp_path / "sphere.stl")
    with pytest.warns(JaxnmWarning, match="no vertex normals"):
        m = load_mesh(tmp_path / "sphere.stl")
    assert m.num_vertices == 3 * m.num_faces  # still unmerged
    p, n = np.asarray(m.positions, np.float64), np.asarray(m.normals, np.float64)
    radial = p / np.linalg.norm(p, axis=1, keepdims=True)
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(n, radial), axis=1),
                                  np.sum(n * radial, axis=1)))
    assert angle.max() < 1.0, angle.max()
    # a roof: two slopes at 45 degrees meeting along the ridge x = 0, uvs split at the ridge
    text = ("v -1 0 0\nv 0 0 1\nv 0 1 1\nv -1 1 0\nv 1 0 0\nv 1 1 0\n"
            "vt 0 0\nvt 0.5 0\nvt 0.5 1\nvt 0 1\nvt 0.6 0\nvt 0.6 1\nvt 1 0\nvt 1 1\n"
            "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\nf 2/5 5/7 6/8\nf 2/5 6/8 3/6\n")
    with pytest.warns(JaxnmWarning, match="no vertex normals"):
        roof = load_mesh(_write(tmp_path / "roof.obj", text))
    p, n = np.asarray(roof.positions), np.asarray(roof.normals)
    on_ridge = p[:, 0] == 0
    assert on_ridge.sum() == 4  # two ridge vertices, each split in two by the uvs
    np.testing.assert_allclose(n[on_ridge], np.tile([0, 0, 1], (4, 1)), atol=1e-6)


# ============================================================================ glTF


def _gltf_accessor(gltf_path: Path, attribute: str) -> np.ndarray:
    """Read a float accessor of the first primitive straight from the .bin."""
    tree = json.loads(gltf_path.read_text())
    acc = tree["accessors"][tree["meshes"][0]["primitives"][0]["attributes"][attribute]]
    view = tree["bufferViews"][acc["bufferView"]]
    blob = (gltf_path.parent / tree["buffers"][0]["uri"]).read_bytes()
    n = {"VEC2": 2, "VEC3": 3}[acc["type"]]
    start = view["byteOffset"] + acc.get("byteOffset", 0)
    return np.frombuffer(blob, "<f4", acc["count"] * n, start).reshape(-1, n)


def test_gltf_uv_origin_is_flipped_to_bottom_left():
    path = DATA / "tri_uv.gltf"
    raw_uv = _gltf_accessor(path, "TEXCOORD_0")  # glTF: origin at the TOP-left
    np.testing.assert_array_equal(raw_uv, [[0.25, 0.125], [0.75, 0.125], [0.25, 0.625]])
    m = load_mesh(path, require_uv=True)  # file normals: no warning
    np.testing.assert_array_equal(m.uv, np.c_[raw_uv[:, 0], 1 - raw_uv[:, 1]])
    np.testing.assert_array_equal(m.positions, _gltf_accessor(path, "POSITION"))
    np.testing.assert_allclose(m.normals, _gltf_accessor(path, "NORMAL"), atol=1e-7)


def test_trimesh_gltf_behaviour_that_load_mesh_corrects():
    """Pins trimesh's glTF loader: it flips v (1 - v) for primitives with a material,
    drops TEXCOORD_0 of primitives without one, and exposes file normals only
    through its cache (the `vertex_normals` property computes them otherwise)."""
    raw_uv = _gltf_accessor(DATA / "tri_uv.gltf", "TEXCOORD_0")
    (tri,) = trimesh.load_scene(DATA / "tri_uv.gltf", process=False).geometry.values()
    np.testing.assert_allclose(tri.visual.uv, np.c_[raw_uv[:, 0], 1 - raw_uv[:, 1]])
    assert "vertex_normals" in tri._cache
    (two,) = trimesh.load_scene(DATA / "two_nodes.glb", process=False).geometry.values()
    assert getattr(two.visual, "uv", None) is None  # no material: uvs dropped
    assert "vertex_normals" not in two._cache


def _rotations(tri):
    return [np.roll(tri, k, axis=0) for k in range(3)]


def test_glb_scene_nodes_are_concatenated_with_transforms():
    path = DATA / "two_nodes.glb"
    with pytest.warns(JaxnmWarning, match="no vertex normals in the file"):
        m = load_mesh(path, require_uv=True)  # no material in the file: uvs kept anyway
    p = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0]], np.float32)
    uv = np.array([[0.25, 0.875], [0.75, 0.875], [0.25, 0.375]], np.float32)
    want = [  # node 0: translated; node 1: mirrored in x, so its winding is reversed
        np.c_[p + [10, 0, 0], uv],
        np.c_[p * [-1, 2, 1] + [0, 0, 5], uv][::-1],
    ]
    assert m.num_faces == 2 and m.num_vertices == 6
    pos, tex = _corners(m)
    for got in (np.c_[pos[i], tex[i]] for i in range(2)):
        assert sum(any(np.allclose(r, w) for r in _rotations(got)) for w in want) == 1
    # both instances face +z (the mirrored one thanks to the reversed winding)
    np.testing.assert_allclose(m.normals, np.tile([0, 0, 1], (6, 1)), atol=1e-6)


def test_gltf_errors(tmp_path):
    tree = json.loads((DATA / "tri_uv.gltf").read_text())
    lonely = tmp_path / "no_bin.gltf"
    lonely.write_text(json.dumps(tree))  # its .bin is not beside it
    with pytest.raises(ValueError, match=_named(lonely) + ".*cannot parse"):
        load_mesh(lonely)
    tree["buffers"][0]["uri"] = str(DATA / "tri_uv.bin")
    tree["accessors"][1]["componentType"] = 5123  # TEXCOORD_0 as normalized uint16
    quant = _write(tmp_path / "quantized.gltf", json.dumps(tree))
    with pytest.raises(ValueError, match=_named(quant) + ".*TEXCOORD_0.*componentType 5123"):
        load_mesh(quant)
    broken = _write(tmp_path / "broken.gltf", '{"asset": {"version": "2.0"},\n  "meshes": [}')
    with pytest.raises(ValueError, match=_named(broken) + ".*line 2, column 14"):
        load_mesh(broken)
    notglb = tmp_path / "not.glb"
    notglb.write_bytes(b"PK\x03\x04" + bytes(40))
    with pytest.raises(ValueError, match=_named(notglb) + ".*not a GLB"):
        load_mesh(notglb)


# ============================================================================ mesh file errors


def test_mesh_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.obj"):
        load_mesh(tmp_path / "nothere.obj")
    xyz = _write(tmp_path / "cloud.xyz", "0 0 0\n")
    with pytest.raises(ValueError, match=_named(xyz) + r".*'\.xyz'.*\.obj, \.ply, \.gltf"):
        load_mesh(xyz)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x00\x01 not a ply file")
    with pytest.raises(ValueError, match=_named(junk) + ".*cannot parse this PLY"):
        load_mesh(junk)
    with pytest.raises(ValueError, match="not a regular file"):
        load_mesh(tmp_path)


# ============================================================================ PNG

def _paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else (b if pb <= pc else c)


def _reference_png16(pixels: np.ndarray, filters) -> bytes:
    """A 16-bit PNG of uint16 (H, W, C) ``pixels``, row y filtered with
    ``filters[y % len(filters)]``, written from the PNG specification byte by byte."""
    h, w, c = pixels.shape
    bpp = 2 * c
    lines = [list(row.astype(">u2").tobytes()) for row in pixels]
    out = bytearray()
    for y, line in enumerate(lines):
        prior = lines[y - 1] if y else [0] * len(line)
        ft = filters[y % len(filters)]
        out.append(ft)
        for i, x in enumerate(line):
            a = line[i - bpp] if i >= bpp else 0
            cc = prior[i - bpp] if i >= bpp else 0
            pred = (0, a, prior[i], (a + prior[i]) // 2, _paeth(a, prior[i], cc))[ft]
            out.append((x - pred) % 256)

    def chunk(kind, data):
        crc = struct.pack(">I", zlib.crc32(kind + data))
        return struct.pack(">I", len(data)) + kind + data + crc

    ihdr = struct.pack(">IIBBBBB", w, h, 16, {1: 0, 2: 4, 3: 2, 4: 6}[c], 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(out)))
            + chunk(b"IEND", b""))


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("filters", [[0, 1, 2, 3, 4], [2, 1, 0]])
def test_png16_every_row_filter(tmp_path, channels, filters):
    rng = np.random.default_rng(channels)
    pixels = rng.integers(0, 65536, (6, 5, channels)).astype(np.uint16)
    pixels[2] = pixels[1]  # repeated rows and columns exercise the predictors
    pixels[:, 3] = 65535
    path = tmp_path / f"filters{channels}.png"
    path.write_bytes(_reference_png16(pixels, filters))
    image, bits = load_texture(path)
    assert bits == 16 and image.dtype == np.float32 and image.shape == pixels.shape
    np.testing.assert_array_equal(np.round(image * 65535).astype(np.uint16), pixels)


def test_imageio_reads_16bit_grey_but_reduces_16bit_colour_to_8bit(tmp_path):
    """Why jaxnm decodes 16-bit PNGs itself: imageio (Pillow) returns uint16 only for grey."""
    rng = np.random.default_rng(1)
    grey = rng.integers(0, 65536, (3, 4, 1)).astype(np.uint16)
    rgb = rng.integers(0, 65536, (3, 4, 3)).astype(np.uint16)
    (tmp_path / "g16.png").write_bytes(_reference_png16(grey, [4]))
    (tmp_path / "c16.png").write_bytes(_reference_png16(rgb, [4]))
    g = iio.imread(tmp_path / "g16.png", plugin="pillow")
    assert g.dtype == np.uint16 and np.array_equal(g, grey[:, :, 0])
    c = iio.imread(tmp_path / "c16.png", plugin="pillow")
    assert c.dtype == np.uint8 and np.array_equal(c, rgb >> 8)
    image, bits = load_texture(tmp_path / "c16.png")
    assert bits == 16 and np.array_equal(np.round(image * 65535), rgb)


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 1), (5, 7, 2), (5, 7, 3), (5, 7, 4)])
@pytest.mark.parametrize("bits", [8, 16])
def test_png_round_trip(tmp_path, shape, bits):
    maxv = 2**bits - 1
    q = np.random.default_rng(bits).integers(0, maxv + 1, shape)
    path = tmp_path / "sub" / "dir" / f"rt{bits}.png"  # parents are created
    save_png(path, (q / maxv).astype(np.float32), bits=bits)
    image, got_bits = load_texture(path)
    assert got_bits == bits and image.shape == (5, 7, shape[2] if len(shape) == 3 else 1)
    np.testing.assert_array_equal(image, (q.reshape(image.shape) / maxv).astype(np.float32))
    if bits == 8 or len(shape) == 2 or shape[2] == 1:  # Pillow reads these correctly
        raw = np.asarray(Image.open(path))
        np.testing.assert_array_equal(raw, q.reshape(raw.shape))


def test_png_quantisation_levels(tmp_path):
    x = np.array([[0.0, 0.49 / 255, 0.51 / 255, 1 / 255, 0.5, 254.49 / 255, 254.51 / 255, 1.0,
                   -0.5, 1.5, np.inf, -np.inf]])
    save_png(tmp_path / "q8.png", x)
    assert np.asarray(Image.open(tmp_path / "q8.png")).tolist() == [
        [0, 0, 1, 1, 128, 254, 255, 255, 0, 255, 255, 0]]
    save_png(tmp_path / "q16.png", np.array([[0.4 / 65535, 0.6 / 65535, 0.5, 1.0]]), bits=16)
    assert np.asarray(Image.open(tmp_path / "q16.png")).tolist() == [[0, 1, 32768, 65535]]
    levels = np.arange(256, dtype=np.float32)[None, :] / 255
    save_png(tmp_path / "levels.png", levels)
    np.testing.assert_array_equal(load_texture(tmp_path / "levels.png")[0][:, :, 0], levels)


def test_png_layout_row_zero_is_the_top_row(tmp_path):
    image = np.zeros((4, 3, 3), np.float32)
    image[0, 0] = [1, 0, 0]  # top-left red
    image[3, 2] = [0, 0, 1]  # bottom-right blue
    save_png(tmp_path / "layout.png", image)
    pil = Image.open(tmp_path / "layout.png")
    assert pil.getpixel((0, 0)) == (255, 0, 0) and pil.getpixel((2, 3)) == (0, 0, 255)
    np.testing.assert_array_equal(load_texture(tmp_path / "layout.png")[0], image)


def test_save_png_errors(tmp_path):
    with pytest.raises(ValueError, match="nan.png.*NaN"):
        save_png(tmp_path / "nan.png", np.array([[0.5, np.nan]]))
    with pytest.raises(ValueError, match="int.png.*float"):
        save_png(tmp_path / "int.png", np.zeros((2, 2), np.uint8))
    with pytest.raises(ValueError, match="shape.png.*shape"):
        save_png(tmp_path / "shape.png", np.zeros((2, 2, 5)))
    with pytest.raises(ValueError, match=r"image.jpg.*\.png"):
        save_png(tmp_path / "image.jpg", np.zeros((2, 2)))
    with pytest.raises(ValueError, match="bits"):
        save_png(tmp_path / "b.png", np.zeros((2, 2)), bits=12)
    assert not any(tmp_path.iterdir())


def test_writers_refuse_what_they_could_not_write_or_read_back(tmp_path):
    """Each ``save_*`` names the file in one line and writes nothing: a folder as the name, a
    file where a parent folder should be, a name its readers would not take, normals that
    `load_texture` would refuse to read back."""
    from jaxnm import io

    (tmp_path / "folder.json").mkdir()
    (tmp_path / "file").write_text("x")
    unit = np.zeros((4, 4, 3), np.float32)
    unit[..., 2] = 1
    cases = [
        (lambda p: io.save_json(p, {}), "folder.json", IsADirectoryError,
         "folder.json: is a folder"),
        (lambda p: io.save_normal_map_npz(p, unit), "folder.json", ValueError, r"\.npz"),
        (lambda p: io.save_normal_map_npz(p, unit), "new/m.npz", None, None),
        (lambda p: io.save_json(p, {}), "file/r.json", NotADirectoryError,
         "file is a file, not a folder"),
        (lambda p: io.save_png(p, unit), "file/a/b.png", NotADirectoryError,
         "file is a file, not a folder"),
        (lambda p: io.save_json(p, {}), "r.txt", ValueError, r"save_json.*end in \.json"),
        (lambda p: io.save_normal_map_npz(p, unit), "m.txt", ValueError, r"end in \.npz"),
        (lambda p: io.save_normal_map_npz(p, unit[..., :2]), "m.npz", ValueError,
         r"\(h, w, 3\), got \(4, 4, 2\)"),
        (lambda p: io.save_normal_map_npz(p, np.where(unit == 1, np.nan, unit)), "m.npz",
         ValueError, "NaN or infinite"),
        (lambda p: io.save_loss_plot(p, [{"loss": 1.0}]), "loss.jpg", ValueError,
         r"end in \.png"),
        (lambda p: io.save_figure_grid(p, [[unit]], titles=["a"], row_labels=["b"]),
         "grid.svg", ValueError, r"end in \.png"),
    ]
    for write, name, error, match in cases:
        before = sorted(tmp_path.rglob("*"))
        path = tmp_path / name
        if error is None:  # a folder in the name that does not exist yet is made
            write(path)
            assert path.is_file()
            continue
        with pytest.raises(error, match=match) as ei:
            write(path)
        assert str(path) in str(ei.value) and "\n" not in str(ei.value)
        assert sorted(tmp_path.rglob("*")) == before, name
    # what the writers write reads back
    io.save_normal_map_npz(tmp_path / "ok.npz", unit)
    np.testing.assert_array_equal(io.load_texture(tmp_path / "ok.npz")[0], unit)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_writable_tries_the_folder_it_would_write_in(tmp_path):
    """A folder that takes no new file is named before the work (Linux's /proc refuses even
    root); a writable one is left as it was."""
    from jaxnm import io

    for path, folder in (("/proc/jaxnm/out", True), ("/proc/jaxnm.png", False)):
        with pytest.raises(OSError, match=f"^{path}: cannot write in /proc: "):
            io.writable(path, folder=folder)
    assert io.writable(tmp_path / "new" / "x.png") == tmp_path / "new" / "x.png"
    assert io.writable(tmp_path, folder=True) == tmp_path
    assert list(tmp_path.iterdir()) == []


# ============================================================================ textures


def test_palette_grey_alpha_and_jpeg(tmp_path):
    rgb = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], np.uint8)
    Image.fromarray(rgb).convert("P").save(tmp_path / "palette.png")
    image, bits = load_texture(tmp_path / "palette.png", channels=3)
    assert bits == 8 and np.array_equal(image * 255, rgb)
    la = np.dstack([np.full((2, 3), 10), np.full((2, 3), 200)]).astype(np.uint8)
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    assert np.array_equal(load_texture(tmp_path / "la.png")[0] * 255, la)
    iio.imwrite(tmp_path / "flat.jpg", np.full((8, 8, 3), [200, 100, 50], np.uint8))
    image, bits = load_texture(tmp_path / "flat.jpg")
    assert bits == 8 and image.shape == (8, 8, 3)
    want = np.broadcast_to(np.array([200, 100, 50]) / 255, image.shape)
    np.testing.assert_allclose(image, want, atol=3 / 255)


def _grey_rgb_rgba(tmp_path):
    rng = np.random.default_rng(2)
    grey, rgb, rgba = (rng.random((3, 4, c)).astype(np.float32) for c in (1, 3, 4))
    for name, image in (("grey", grey), ("rgb", rgb), ("rgba", rgba)):
        save_png(tmp_path / f"{name}.png", image)
    return (tmp_path / "grey.png", tmp_path / "rgb.png", tmp_path / "rgba.png")


def test_channels(tmp_path):
    grey, rgb, rgba = _grey_rgb_rgba(tmp_path)
    full = load_texture(rgba)[0]
    assert np.array_equal(load_texture(rgba, channels=3)[0], full[:, :, :3])
    assert load_texture(rgb, channels=3)[0].shape == (3, 4, 3)
    assert np.array_equal(load_texture(rgb, channels=2)[0], load_texture(rgb)[0][:, :, :2])
    assert load_texture(grey, channels=1)[0].shape == (3, 4, 1)
    with pytest.warns(JaxnmWarning, match=_named(rgb) + ".*first \\(red\\) channel"):
        red = load_texture(rgb, channels=1)[0]
    assert np.array_equal(red, load_texture(rgb)[0][:, :, :1])
    with pytest.raises(ValueError, match=re.escape(
            f"{grey}: a normal map needs 3 channels (RGB), got 1 (grayscale)")):
        load_texture(grey, channels=3)
    with pytest.raises(ValueError, match=_named(grey) + ".*2 channels"):
        load_texture(grey, channels=2)
    with pytest.raises(ValueError, match="channels must be"):
        load_texture(rgb, channels=4)


def test_npy_and_npz(tmp_path):
    hdr = np.array([[[0.5, 2.0, -1.0]]], np.float64)  # float arrays are taken as they are
    np.save(tmp_path / "hdr.npy", hdr)
    image, bits = load_texture(tmp_path / "hdr.npy")
    assert bits == 32 and image.dtype == np.float32 and np.array_equal(image, hdr)
    np.save(tmp_path / "u16.npy", np.array([[0, 65535]], np.uint16))
    image, bits = load_texture(tmp_path / "u16.npy")
    assert bits == 16 and image.shape == (1, 2, 1) and image.ravel().tolist() == [0, 1]
    np.savez(tmp_path / "one.npz", anything=hdr)
    assert np.array_equal(load_texture(tmp_path / "one.npz")[0], hdr)
    np.savez(tmp_path / "named.npz", image=hdr, mask=np.ones((1, 1)))
    assert np.array_equal(load_texture(tmp_path / "named.npz")[0], hdr)
    np.savez(tmp_path / "two.npz", a=hdr, b=hdr)
    with pytest.raises(ValueError, match="two.npz.*one array or one named 'image'"):
        load_texture(tmp_path / "two.npz")
    np.save(tmp_path / "nan.npy", np.array([[0.0, np.nan]], np.float32))
    with pytest.raises(ValueError, match="nan.npy.*NaN"):
        load_texture(tmp_path / "nan.npy")
    np.save(tmp_path / "empty.npy", np.zeros((0, 4, 3), np.float32))
    with pytest.raises(ValueError, match="empty.npy.*empty"):
        load_texture(tmp_path / "empty.npy")
    np.save(tmp_path / "ints.npy", np.zeros((2, 2), np.int64))
    with pytest.raises(ValueError, match="ints.npy.*int64"):
        load_texture(tmp_path / "ints.npy")


def test_texture_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.png"):
        load_texture(tmp_path / "missing.png")
    text = _write(tmp_path / "text.png", "not an image at all")
    with pytest.raises(ValueError, match=_named(text) + ".*not an image"):
        load_texture(text)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="empty.png.*empty"):
        load_texture(tmp_path / "empty.png")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(_reference_png16(np.zeros((4, 4, 3), np.uint16), [0])[:45])
    with pytest.raises(ValueError, match=_named(truncated) + ".*corrupt"):
        load_texture(truncated)
    bmp = _write(tmp_path / "image.bmp", "")
    with pytest.raises(ValueError, match=_named(bmp) + r".*\.png, \.jpg"):
        load_texture(bmp)
    exr = _write(tmp_path / "image.exr", "")
    with pytest.raises(ValueError, match=_named(exr) + ".*unsupported"):
        load_texture(exr)  # EXR only through load_image_float


def test_load_image_float(tmp_path):
    _, rgb, _ = _grey_rgb_rgba(tmp_path)
    assert np.array_equal(load_image_float(rgb)[0], load_texture(rgb)[0])
    bad = tmp_path / "broken.exr"
    bad.write_bytes(b"\x76\x2f\x31\x01" + bytes(60))
    with pytest.raises(ValueError, match=_named(bad)):
        load_image_float(bad)


@pytest.mark.parametrize("channels", ["RGB", "RGBA", "Y"])
def test_exr_round_trip(tmp_path, channels):
    """Float targets as OpenEXR (linear, unclipped, half or float): written with the OpenEXR
    bindings independently of jaxnm, read back exactly."""
    import OpenEXR

    rng = np.random.default_rng(1)
    shape = {"RGB": (5, 7, 3), "RGBA": (5, 7, 4), "Y": (5, 7)}[channels]
    img = (rng.random(shape) * 4.0).astype(np.float32)  # HDR: values above 1 are kept
    p = tmp_path / f"t_{channels}.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION,
                       "type": OpenEXR.scanlineimage}, {channels: img}) as f:
        f.write(str(p))
    got, bits = load_image_float(p)
    assert bits == 32 and got.dtype == np.float32
    np.testing.assert_array_equal(got, img if img.ndim == 3 else img[..., None])


# ============================================================================ AOVs and JSON


def test_aovs_round_trip(tmp_path):
    aovs = {"depth": np.arange(6, dtype=np.float64).reshape(2, 3),
            "mask": np.array([[True, False, True], [False, True, False]]),
            "triangle_id": np.array([[0, 1, 2], [3, 4, -1]], np.int32),
            "normal": np.ones((2, 3, 3), np.float32)}
    path = tmp_path / "out" / "frame.npz"
    save_aovs(path, aovs)
    got = load_aovs(path)
    assert sorted(got) == sorted(aovs)
    for name, value in aovs.items():
        assert got[name].dtype == np.float32 and got[name].ndim == 3
        np.testing.assert_array_equal(got[name], np.asarray(value, np.float32).reshape(
            got[name].shape))
    with pytest.raises(ValueError, match="frame.aov.*npz"):
        save_aovs(tmp_path / "frame.aov", aovs)
    with pytest.raises(ValueError, match="bad.npz.*'bad'.*shape"):
        save_aovs(tmp_path / "bad.npz", {"bad": np.zeros(3)})
    np.save(tmp_path / "single.npy", np.zeros(3))
    with pytest.raises(ValueError, match="single.npy.*npz"):
        load_aovs(tmp_path / "single.npy")
    with pytest.raises(ValueError, match="garbage.npz"):
        load_aovs(_write(tmp_path / "garbage.npz", "garbage"))


def test_load_json(tmp_path):
    assert load_json(_write(tmp_path / "ok.json", '{"a": [1, 2]}')) == {"a": [1, 2]}
    bad = _write(tmp_path / "bad.json", '{\n  "a": 1,\n  "b": }\n')
    with pytest.raises(ValueError, match=re.escape(f"{bad}: invalid JSON at line 3, column 8")):
        load_json(bad)
    with pytest.raises(ValueError, match="list.json.*JSON object"):
        load_json(_write(tmp_path / "list.json", "[1, 2]"))
    with pytest.raises(FileNotFoundError, match="none.json"):
        load_json(tmp_path / "none.json")


def _gltf_quad_with_tangents(tmp_path, tangent):
    """A unit quad (2 triangles) in z = 0 with NORMAL, TEXCOORD_0 and one TANGENT for all four
    vertices, as a self-contained .gltf (base64 buffer)."""
    import base64
    import json as _json

    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (4, 1))
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)  # glTF: top-left origin
    tan = np.tile(np.asarray(tangent, np.float32), (4, 1))
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob, views, acc = b"", [], []
    for a, kind, ctype in ((pos, "VEC3", 5126), (nrm, "VEC3", 5126), (uv, "VEC2", 5126),
                           (tan, "VEC4", 5126), (idx, "SCALAR", 5123)):
        data = a.tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob += data + b"\0" * (-len(data) % 4)
        entry = {"bufferView": len(views) - 1, "componentType": ctype, "count": len(a),
                 "type": kind}
        if a is pos:
            entry.update(min=[0, 0, 0], max=[1, 1, 0])
        acc.append(entry)
    tree = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1,
                                                       "TEXCOORD_0": 2, "TANGENT": 3},
                                        "indices": 4}]}],
            "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                         + base64.b64encode(blob).decode()}],
            "bufferViews": views, "accessors": acc}
    path = tmp_path / "quad.gltf"
    path.write_text(_json.dumps(tree))
    return path


def test_gltf_tangent_attribute_is_used_as_the_vertex_frame(tmp_path):
    """A glTF TANGENT (here rotated 30 deg from dp/du, left-handed) becomes the mesh's
    per-corner tangents and the "vertex" frame decodes with it; the scene key
    tangents="mikktspace" recomputes them instead."""
    import json as _json

    import jaxnm
    from jaxnm.config import load_scene

    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    path = _gltf_quad_with_tangents(tmp_path, [c, s, 0.0, -1.0])
    mesh = load_mesh(path)
    assert mesh.tangent_source == "file" and mesh.tangents.shape == (2, 3, 4)
    np.testing.assert_allclose(np.asarray(mesh.tangents), np.tile([c, s, 0, -1], (2, 3, 1)),
                               atol=1e-6)
    scene = {"mesh": "quad.gltf", "width": 24, "height": 24, "frame": "vertex",
             "camera": {"eye": [0.5, 0.5, 2], "target": [0.5, 0.5, 0], "up": [0, 1, 0]}}
    (tmp_path / "s.json").write_text(_json.dumps(scene))
    (tmp_path / "m.json").write_text(_json.dumps({**scene, "tangents": "mikktspace"}))
    out = {}
    for name in ("s", "m"):
        sc = load_scene(tmp_path / f"{name}.json")
        out[name] = (sc.mesh.tangent_source,
                     jaxnm.render(sc, outputs=("tangent", "bitangent", "mask")))
    src, o = out["s"]
    m = np.asarray(o["mask"])[..., 0] > 0
    assert src == "file"
    np.testing.assert_allclose(np.asarray(o["tangent"])[m], np.tile([c, s, 0], (m.sum(), 1)),
                               atol=1e-5)
    # B = w cross(N, T) with w = -1
    np.testing.assert_allclose(np.asarray(o["bitangent"])[m],
                               np.tile([s, -c, 0], (m.sum(), 1)), atol=1e-5)
    src, o = out["m"]
    assert src == "mikktspace"  # dp/du = +x, and uv (after the glTF flip) is right-handed
    np.testing.assert_allclose(np.asarray(o["tangent"])[m], np.tile([1, 0, 0], (m.sum(), 1)),
                               atol=1e-5)
    np.testing.assert_allclose(np.asarray(o["bitangent"])[m], np.tile([0, 1, 0], (m.sum(), 1)),
                               atol=1e-5)


def _sphere_normals(h: int, w: int) -> np.ndarray:
    """Unit normals of a sphere over a latitude-longitude grid: an object-space map's."""
    u, v = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
    theta, phi = 2 * np.pi * u, np.pi * v
    return np.stack([np.sin(phi) * np.cos(theta), np.sin(phi) * np.sin(theta),
                     np.cos(phi)], -1).astype(np.float32)


def _warned(raw, **kw) -> list[str]:
    kw.setdefault("hint", 'a scene file\'s normal_map takes "space": "object"')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_tangent_normal_map(raw, source="m.png", **kw)
    assert all(issubclass(w.category, JaxnmWarning) for w in caught)
    return [str(w.message) for w in caught]


def test_a_map_of_another_kind_given_as_tangent_space_is_named():
    """An object-space map (half its normals have z < 0) or a black image warns; tangent-space
    maps do not, with a black background around their islands, and nor does a map with a
    few texels tilted past the horizon."""
    sphere = _sphere_normals(32, 64)
    said = _warned(sphere * 0.5 + 0.5)
    share = np.mean(sphere[..., 2] < -0.05)  # the 15 rows of 32 below the equator's band
    assert said == [f"m.png: {share:.0%} of its texels point into the surface (z < 0 once "
                    "decoded), where a tangent-space map's point out of it; is it an "
                    "object-space map? (a scene file's normal_map takes \"space\": "
                    "\"object\")"], said
    assert len(_warned(sphere, encoding="signed")) == 1
    assert _warned(sphere * 0.5 + 0.5, hint="")[0].endswith("is it an object-space map?")
    assert _warned(np.zeros((4, 4, 3), np.float32)) == [
        "m.png: every texel is black (0, 0, 0), which is no normal"]
    rivets = np.asarray(default_normal_map_texels(64), np.float32)
    assert _warned(rivets) == []
    islands = rivets.copy()
    islands[:, 40:] = 0.0  # a baker's black background
    assert _warned(islands) == []
    tilted = rivets.copy()
    tilted[0, :8] = [1.0, 0.5, 0.3]  # 8 of 4,096 texels point inwards (z = -0.4)
    assert _warned(tilted) == []
    assert _warned(sphere[..., :2] * 0.5 + 0.5, channels=2) == []  # z rebuilt, >= 0


def _glb_with_normal_texture(path, images):
    """A GLB of one box per image, each with a material whose normal texture is that image
    (written by trimesh: the images in the binary chunk, through buffer views)."""
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    scene = trimesh.Scene()
    for k, img in enumerate(images):
        box = trimesh.creation.box()
        uv = np.random.default_rng(k).random((len(box.vertices), 2))
        box.visual = TextureVisuals(uv=uv, material=PBRMaterial(
            normalTexture=None if img is None else Image.fromarray(img)))
        scene.add_geometry(box, geom_name=f"box{k}")
    scene.export(path)
    return path


def test_a_glb_files_normal_map_is_read_from_its_binary_chunk(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (6, 10, 3), dtype=np.uint8)
    texels, opts = load_gltf_normal_map(_glb_with_normal_texture(tmp_path / "b.glb", [img]))
    assert opts == NormalMapOptions(encoding="unsigned", channels=3, green="up", strength=1.0,
                                    space="tangent", bits=8, wrap="repeat", filter="trilinear")
    np.testing.assert_array_equal(texels, img / np.float32(255))


@pytest.mark.parametrize("sampler,wrap,filter", [
    (None, "repeat", "trilinear"),  # no sampler: repeat, and the viewer's filter
    ({"wrapS": 33071, "wrapT": 33071, "minFilter": 9728, "magFilter": 9728}, "clamp", "nearest"),
    ({"wrapS": 33648, "wrapT": 33648, "minFilter": 9729}, "mirror", "bilinear"),
    ({"minFilter": 9987}, "repeat", "trilinear"),
])
def test_a_gltf_normal_maps_sampler_and_scale_become_its_options(tmp_path, sampler, wrap,
                                                                  filter):
    save_png(tmp_path / "n.png", np.full((4, 4, 3), [0.5, 0.5, 1.0], np.float32), bits=16)
    tree = {"asset": {"version": "2.0"},
            "materials": [{"normalTexture": {"index": 0, "scale": 0.25}}],
            "meshes": [{"primitives": [{"attributes": {}, "material": 0}]}],
            "textures": [{"source": 0}], "images": [{"uri": "n.png"}]}
    if sampler is not None:
        tree["samplers"], tree["textures"][0]["sampler"] = [sampler], 0
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(tree))
    texels, opts = load_gltf_normal_map(path)
    assert texels.shape == (4, 4, 3)
    assert (opts.wrap, opts.filter, opts.strength, opts.bits) == (wrap, filter, 0.25, 16)
    if sampler is None:  # (once) axes wrapped differently: u's wrap, said; an unknown one
        tree["samplers"], tree["textures"][0]["sampler"] = [{"wrapS": 33071, "wrapT": 10497}], 0
        path.write_text(json.dumps(tree))
        with pytest.warns(JaxnmWarning, match=re.escape(
                f"{path}: the normal texture wraps u clamp and v repeat; jaxnm wraps both as u "
                "does")):
            assert load_gltf_normal_map(path)[1].wrap == "clamp"
        tree["samplers"] = [{"wrapS": 1}]
        path.write_text(json.dumps(tree))
        with pytest.raises(ValueError, match=re.escape(
                f"{path}: the normal texture's sampler has an unknown wrap (1, 10497)")):
            load_gltf_normal_map(path)


@pytest.mark.parametrize("images,why", [
    ("two", "its primitives use 2 normal textures (or some none)"),
    ("one and none", "its primitives use 2 normal textures (or some none)"),
])
def test_a_glb_whose_primitives_differ_in_normal_map_has_none(tmp_path, images, why):
    """jaxnm renders a scene with one map: several, or a map on part of the mesh, give None
    and say why."""
    rng = np.random.default_rng(1)
    a, b = (rng.integers(0, 256, (4, 4, 3), dtype=np.uint8) for _ in range(2))
    path = _glb_with_normal_texture(tmp_path / "m.glb", [a, b] if images == "two" else [a, None])
    with pytest.warns(JaxnmWarning, match=re.escape(f"{path}: {why}; jaxnm renders a scene "
                                                    "with one map, so it is not used")):
        assert load_gltf_normal_map(path) is None


def test_a_gltf_normal_map_through_another_uv_set_or_missing_is_named(tmp_path):
    tree = {"asset": {"version": "2.0"}, "materials": [{"normalTexture": {"index": 0}}],
            "meshes": [{"primitives": [{"attributes": {}, "material": 0}]}],
            "textures": [{"source": 0}], "images": [{"uri": "n.png"}]}
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(tree))
    with pytest.raises(ValueError, match=re.escape(f"{path}: the normal texture 'n.png' is not "
                                                   f"beside it ({tmp_path / 'n.png'})")):
        load_gltf_normal_map(path)
    tree["materials"][0]["normalTexture"]["texCoord"] = 1
    path.write_text(json.dumps(tree))
    with pytest.warns(JaxnmWarning, match="read through TEXCOORD_1; jaxnm reads TEXCOORD_0 only, "
                                          "so it is not used"):
        assert load_gltf_normal_map(path) is None
    tree["materials"][0]["normalTexture"] = {"index": 0, "extensions": {
        "KHR_texture_transform": {"offset": [0.5, 0]}}}
    path.write_text(json.dumps(tree))
    with pytest.warns(JaxnmWarning, match="moved by KHR_texture_transform, which jaxnm does "
                                          "not apply, so it is not used"):
        assert load_gltf_normal_map(path) is None
    tree["textures"] = [{"extensions": {"KHR_texture_basisu": {"source": 0}}}]
    tree["materials"][0]["normalTexture"] = {"index": 0}
    path.write_text(json.dumps(tree))
    with pytest.raises(ValueError, match=re.escape(
            f"{path}: the normal texture is stored only through the extensions "
            "['KHR_texture_basisu']; jaxnm reads PNG and JPEG images")):
        load_gltf_normal_map(path)
    tree["materials"] = [{}]
    path.write_text(json.dumps(tree))
    assert load_gltf_normal_map(path) is None


def _glb_accessors(path: Path) -> dict:
    """Every attribute of a GLB's first primitive, read straight from its binary chunk."""
    data = path.read_bytes()
    n = struct.unpack_from("<I", data, 12)[0]
    tree = json.loads(data[20:20 + n])
    blob = data[28 + n:28 + n + struct.unpack_from("<I", data, 20 + n)[0]]
    out = {}
    for name, k in tree["meshes"][0]["primitives"][0]["attributes"].items():
        acc = tree["accessors"][k]
        view = tree["bufferViews"][acc["bufferView"]]
        width = {"VEC2": 2, "VEC3": 3}[acc["type"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        out[name] = np.frombuffer(blob, "<f4", acc["count"] * width, start).reshape(-1, width)
    return out


def test_save_glb_writes_what_gltf_says_and_reads_back(tmp_path):
    """`save_glb`: positions, normals and uvs as glTF stores them (uv origin at the image's
    top left: v written as 1 - v), read straight from the file; the normal map back through
    `load_gltf_normal_map` as the 8-bit codes of `encode_normal_map`, and the mesh through
    `load_mesh`."""
    from jaxnm.io import save_glb
    from jaxnm.procedural import uv_sphere
    from jaxnm.textures import encode_normal_map, quantize

    mesh = uv_sphere(1.0, 8, 6)
    rng = np.random.default_rng(0)
    n = rng.normal(0, 0.3, (6, 10, 3)) + [0, 0, 1]
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    save_glb(tmp_path / "s.glb", mesh, n)
    raw = _glb_accessors(tmp_path / "s.glb")
    np.testing.assert_array_equal(raw["POSITION"], mesh.positions)
    np.testing.assert_allclose(raw["NORMAL"], mesh.normals, atol=1e-7)
    uv = np.asarray(mesh.uv)
    np.testing.assert_allclose(raw["TEXCOORD_0"], np.c_[uv[:, 0], 1 - uv[:, 1]], atol=1e-7)
    texels, opts = load_gltf_normal_map(tmp_path / "s.glb")
    codes = quantize(encode_normal_map(n, encoding="unsigned", green="up", bits=8), 8)
    np.testing.assert_array_equal(np.round(texels * 255), np.round(np.asarray(codes) * 255))
    assert (opts.encoding, opts.green, opts.bits) == ("unsigned", "up", 8)
    back = load_mesh(tmp_path / "s.glb")
    np.testing.assert_array_equal(back.positions, mesh.positions)
    np.testing.assert_allclose(back.uv, mesh.uv, atol=1e-7)
    with pytest.raises(ValueError, match="save_glb writes GLB files; the name must end in .glb"):
        save_glb(tmp_path / "s.gltf", mesh)
