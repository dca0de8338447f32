"""Blender as an independent reference, run as its own process (``bpy`` pins NumPy 1.x,
JAX needs 2.x, so Blender lives in a separate environment: ``JAXNM_BLENDER_PYTHON``, or
``.venv-blender/bin/python`` beside the checkout, with ``pip install bpy==5.0.1``).

    python blender_ref.py tangents IN.npz OUT.npz

``IN.npz`` holds ``positions`` (V, 3), ``faces`` (F, 3), ``uv`` (V, 2) and ``normals``
(V, 3); the mesh is built in Blender with those per-corner uvs and custom (split) normals,
and ``OUT.npz`` receives Blender's MikkTSpace tangent and sign of every face corner
(``Mesh.calc_tangents``): ``tangents`` (F, 3, 3), ``signs`` (F, 3), and the corner
normals it used, ``normals`` (F, 3, 3).

    python blender_ref.py bake SPEC.npz OUT.npz

bakes a tangent-space normal map with Cycles (selected to active) from a high-poly mesh onto
a low-poly one (both given as arrays in ``SPEC.npz``: ``hi_positions``, ``hi_faces``,
``lo_positions``, ``lo_faces``, ``lo_uv``, ``lo_normals``, ``size``, ``cage_extrusion``) and
writes the map (``image``, (size, size, 3) float in [0, 1], row 0 = top, i.e. v = 1) and the
low-poly mesh's tangents as Blender saw them.
"""

from __future__ import annotations

import sys

import bpy
import numpy as np


def _clear() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _mesh(name, positions, faces, uv=None, normals=None):
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(map(float, p)) for p in positions], [],
                   [tuple(map(int, f)) for f in faces])
    loops_v = np.array([lp.vertex_index for lp in me.loops])
    if uv is not None:
        layer = me.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", np.asarray(uv, np.float32)[loops_v].ravel())
    if normals is not None:
        for poly in me.polygons:
            poly.use_smooth = True
        me.normals_split_custom_set(
            [tuple(map(float, n)) for n in np.asarray(normals, np.float64)[loops_v]])
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _tangents(me, faces_count: int):
    """Per face corner: Blender's MikkTSpace tangent, sign, and the (custom) normal it used
    (Blender stores custom normals compressed: within about 0.03 deg of the input)."""
    me.calc_tangents(uvmap="UVMap")
    t = np.zeros(len(me.loops) * 3, np.float32)
    s = np.zeros(len(me.loops), np.float32)
    n = np.zeros(len(me.loops) * 3, np.float32)
    me.loops.foreach_get("tangent", t)
    me.loops.foreach_get("bitangent_sign", s)
    me.corner_normals.foreach_get("vector", n)
    starts = np.zeros(len(me.polygons), np.int64)
    me.polygons.foreach_get("loop_start", starts)
    idx = starts[:, None] + np.arange(3)[None]
    return (t.reshape(-1, 3)[idx].reshape(faces_count, 3, 3), s[idx],
            n.reshape(-1, 3)[idx].reshape(faces_count, 3, 3))


def tangents(src: str, dst: str) -> None:
    d = np.load(src)
    _clear()
    obj = _mesh("m", d["positions"], d["faces"], d["uv"], d["normals"])
    t, s, n = _tangents(obj.data, len(d["faces"]))
    np.savez(dst, tangents=t, signs=s, normals=n)


def bake(src: str, dst: str) -> None:
    d = np.load(src)
    size = int(d["size"])
    _clear()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    hi = _mesh("hi", d["hi_positions"], d["hi_faces"])
    for poly in hi.data.polygons:
        poly.use_smooth = True
    lo = _mesh("lo", d["lo_positions"], d["lo_faces"], d["lo_uv"], d["lo_normals"])
    image = bpy.data.images.new("bake", size, size, float_buffer=True, is_data=True)
    image.colorspace_settings.name = "Non-Color"
    mat = bpy.data.materials.new("bake")
    mat.use_nodes = True
    node = mat.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = image
    mat.node_tree.nodes.active = node
    lo.data.materials.append(mat)
    bpy.ops.object.select_all(action="DESELECT")
    hi.select_set(True)
    lo.select_set(True)
    bpy.context.view_layer.objects.active = lo
    bpy.ops.object.bake(type="NORMAL", normal_space="TANGENT", use_selected_to_active=True,
                        cage_extrusion=float(d["cage_extrusion"]), margin=4,
                        normal_r="POS_X", normal_g="POS_Y", normal_b="POS_Z")
    px = np.zeros(size * size * 4, np.float32)
    image.pixels.foreach_get(px)
    img = px.reshape(size, size, 4)[::-1, :, :3]  # Blender's rows go up: row 0 = v near 0
    t, s, n = _tangents(lo.data, len(d["lo_faces"]))
    np.savez(dst, image=img, tangents=t, signs=s, normals=n)


if __name__ == "__main__":
    {"tangents": tangents, "bake": bake}[sys.argv[1]](sys.argv[2], sys.argv[3])
