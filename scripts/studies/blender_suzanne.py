"""A real asset for the frame study: Blender's Suzanne with its hand-made uv layout and a
tangent-space normal map baked by Cycles from a sculpted (subdivided, displaced) copy.

    .venv-blender/bin/python scripts/studies/blender_suzanne.py OUT.npz [--size 512]

Run in Blender's environment (``bpy``; see ``tests/blender_ref.py``). Writes ``positions``
(V, 3), ``faces`` (F, 3), ``uv`` (V, 2), ``normals`` (V, 3) of the low-poly, smooth-shaded
Suzanne (vertices split where the uv or the normal is split), the baked map ``image``
((size, size, 3) in [0, 1], row 0 = top, v = 1; MikkTSpace, OpenGL green) and Blender's own
MikkTSpace ``tangents`` (F, 3, 3) and ``signs`` (F, 3) of every face corner. The generated
asset is not committed: the study calls this script when it runs.
"""

from __future__ import annotations

import argparse

import bpy
import numpy as np


def _clear() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _suzanne(name: str):
    bpy.ops.mesh.primitive_monkey_add(size=2.0, calc_uvs=True)
    obj = bpy.context.active_object
    obj.name = name
    for poly in obj.data.polygons:
        poly.use_smooth = True
    return obj


def _apply(obj, kind: str, **kw):
    bpy.context.view_layer.objects.active = obj
    mod = obj.modifiers.new(kind.lower(), kind)
    for k, v in kw.items():
        setattr(mod, k, v)
    bpy.ops.object.modifier_apply(modifier=mod.name)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args()
    _clear()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1

    lo = _suzanne("lo")
    _apply(lo, "TRIANGULATE")
    hi = _suzanne("hi")
    _apply(hi, "SUBSURF", levels=3, render_levels=3)
    tex = bpy.data.textures.new("detail", "VORONOI")
    tex.noise_scale = 0.18
    _apply(hi, "DISPLACE", texture=tex, strength=0.035, mid_level=0.5)
    # a second, smoother layer so that the map has broad slopes as well as cells
    tex2 = bpy.data.textures.new("waves", "CLOUDS")
    tex2.noise_scale = 0.35
    _apply(hi, "DISPLACE", texture=tex2, strength=0.04, mid_level=0.5)

    image = bpy.data.images.new("bake", args.size, args.size, float_buffer=True, is_data=True)
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
                        cage_extrusion=0.08, margin=8, normal_r="POS_X", normal_g="POS_Y",
                        normal_b="POS_Z")
    px = np.zeros(args.size * args.size * 4, np.float32)
    image.pixels.foreach_get(px)
    img = px.reshape(args.size, args.size, 4)[::-1, :, :3]

    me = lo.data
    me.calc_tangents()
    nl = len(me.loops)
    vidx = np.zeros(nl, np.int64)
    me.loops.foreach_get("vertex_index", vidx)
    uv = np.zeros(nl * 2, np.float64)
    me.uv_layers.active.data.foreach_get("uv", uv)
    uv = uv.reshape(-1, 2)
    nrm = np.zeros(nl * 3, np.float64)
    me.corner_normals.foreach_get("vector", nrm) if hasattr(me, "corner_normals") else \
        me.loops.foreach_get("normal", nrm)
    nrm = nrm.reshape(-1, 3)
    tan = np.zeros(nl * 3, np.float64)
    me.loops.foreach_get("tangent", tan)
    sign = np.zeros(nl, np.float64)
    me.loops.foreach_get("bitangent_sign", sign)
    co = np.zeros(len(me.vertices) * 3, np.float64)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    loops = np.array([list(p.loop_indices) for p in me.polygons], np.int64)  # (F, 3)
    # weld corners that share the vertex, the uv and the normal
    key = np.concatenate([vidx[:, None], np.round(uv * 1e6), np.round(nrm * 1e5)], 1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    np.savez(args.out, positions=co[vidx[first]], faces=inverse.reshape(-1)[loops],
             uv=uv[first], normals=nrm[first], image=img,
             tangents=tan.reshape(-1, 3)[loops], signs=sign[loops])
    print(f"{args.out}: {len(first)} vertices, {len(loops)} triangles, map {args.size}^2")


if __name__ == "__main__":
    main()
