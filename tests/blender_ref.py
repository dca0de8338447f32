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

    python blender_ref.py transfer SPEC.npz OUT.npz

the same Cycles bake with every setting exposed: ``lo_positions`` (V, 3) and ``lo_faces``
(F, 3) with a uv per face corner, ``lo_corner_uv`` (F, 3, 2) (so the low-poly mesh is welded as
a modeller's is, its normals Blender's own smooth ones), ``samples``, ``cage_extrusion``,
``max_ray_distance``, optional ``cage_positions`` (V, 3) (a cage object with the low-poly
mesh's triangles) and ``margins`` (one bake per margin). ``OUT.npz`` gets ``images`` (one per
margin, (size, size, 3), row 0 = top, -1 where the bake wrote nothing), ``bake_seconds`` (the
``bpy.ops.object.bake`` calls), ``peak_rss_kib`` (the process's peak resident memory) and the
tangents.

    python blender_ref.py suzanne LEVELS OUT.npz

writes Blender's Suzanne (``primitive_monkey_add`` with its uvs, triangulated): ``positions``,
``faces``, ``corner_uv``, and the same mesh subdivided ``LEVELS`` times (Catmull-Clark) and
triangulated: ``sub_positions``, ``sub_faces``.
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


def _corner_uv_mesh(name, positions, faces, corner_uv):
    """A smooth mesh with a uv per face corner and no custom normals."""
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(map(float, p)) for p in positions], [],
                   [tuple(map(int, f)) for f in faces])
    layer = me.uv_layers.new(name="UVMap")
    starts = np.zeros(len(me.polygons), np.int64)
    me.polygons.foreach_get("loop_start", starts)
    uv = np.zeros((len(me.loops), 2), np.float32)
    uv[starts[:, None] + np.arange(3)[None]] = np.asarray(corner_uv, np.float32)
    layer.data.foreach_set("uv", uv.ravel())
    for poly in me.polygons:
        poly.use_smooth = True
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _bake_image(lo, size, d, margin):
    """One selected-to-active tangent-space bake into a new float image that starts at -1."""
    import time

    image = bpy.data.images.new(f"bake{margin}", size, size, float_buffer=True, is_data=True)
    image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(np.tile(np.float32([-1, -1, -1, 1]), size * size))
    mat = lo.data.materials[0]
    mat.node_tree.nodes.active.image = image
    cage = {}
    if "cage_positions" in d:
        cage = dict(use_cage=True, cage_object="cage")
    t = time.perf_counter()
    bpy.ops.object.bake(type="NORMAL", normal_space="TANGENT", use_selected_to_active=True,
                        cage_extrusion=float(d["cage_extrusion"]),
                        max_ray_distance=float(d["max_ray_distance"]), margin=int(margin),
                        normal_r="POS_X", normal_g="POS_Y", normal_b="POS_Z", use_clear=False,
                        **cage)
    seconds = time.perf_counter() - t
    px = np.zeros(size * size * 4, np.float32)
    image.pixels.foreach_get(px)
    return px.reshape(size, size, 4)[::-1, :, :3], seconds  # Blender's rows go up


def transfer(src: str, dst: str) -> None:
    d = np.load(src)
    size = int(d["size"])
    _clear()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(d["samples"])
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    hi = _mesh("hi", d["hi_positions"], d["hi_faces"])
    for poly in hi.data.polygons:
        poly.use_smooth = True
    lo = _corner_uv_mesh("lo", d["lo_positions"], d["lo_faces"], d["lo_corner_uv"])
    if "cage_positions" in d:
        _corner_uv_mesh("cage", d["cage_positions"], d["lo_faces"], d["lo_corner_uv"])
    mat = bpy.data.materials.new("bake")
    mat.use_nodes = True
    mat.node_tree.nodes.active = mat.node_tree.nodes.new("ShaderNodeTexImage")
    lo.data.materials.append(mat)
    bpy.ops.object.select_all(action="DESELECT")
    hi.select_set(True)
    lo.select_set(True)
    bpy.context.view_layer.objects.active = lo
    images, seconds = [], []
    for margin in np.atleast_1d(d["margins"]):
        img, sec = _bake_image(lo, size, d, margin)
        images.append(img)
        seconds.append(sec)
    t, s, n = _tangents(lo.data, len(d["lo_faces"]))
    np.savez(dst, images=np.stack(images), bake_seconds=np.array(seconds), tangents=t, signs=s,
             normals=n, peak_rss_kib=_peak_rss_kib())


def _peak_rss_kib() -> int:
    """This process's peak resident set (Linux's VmHWM), or -1 where /proc has none."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration):
        return -1


def _triangulated(me):
    import bmesh

    bm = bmesh.new()
    bm.from_mesh(me)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])
    bm.to_mesh(me)
    bm.free()
    pos = np.zeros(len(me.vertices) * 3, np.float64)
    me.vertices.foreach_get("co", pos)
    corners = np.zeros(len(me.loops), np.int64)
    me.loops.foreach_get("vertex_index", corners)
    return pos.reshape(-1, 3), corners.reshape(-1, 3)


def suzanne(levels: str, dst: str) -> None:
    _clear()
    bpy.ops.mesh.primitive_monkey_add(size=2.0, calc_uvs=True)
    obj = bpy.context.active_object
    sub = obj.modifiers.new("sub", "SUBSURF")
    sub.levels = sub.render_levels = int(levels)
    deps = bpy.context.evaluated_depsgraph_get()
    hi = bpy.data.meshes.new_from_object(obj.evaluated_get(deps))
    obj.modifiers.remove(sub)
    lo = obj.data
    pos, faces = _triangulated(lo)
    uv = np.zeros(len(lo.loops) * 2, np.float32)
    lo.uv_layers.active.data.foreach_get("uv", uv)
    sub_pos, sub_faces = _triangulated(hi)
    np.savez(dst, positions=pos, faces=faces, corner_uv=uv.reshape(-1, 3, 2),
             sub_positions=sub_pos, sub_faces=sub_faces)


if __name__ == "__main__":
    {"tangents": tangents, "bake": bake, "transfer": transfer,
     "suzanne": suzanne}[sys.argv[1]](sys.argv[2], sys.argv[3])
