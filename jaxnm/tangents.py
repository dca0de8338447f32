"""MikkTSpace tangents: the frame most tangent-space normal maps are baked in.

Blender, Substance, xNormal, Unity and Unreal bake tangent-space normal maps in
MikkTSpace, and glTF 2.0 prescribes it for meshes that carry no tangents. To
decode such a map a renderer must rebuild the baker's frame exactly. This
module ports the algorithm of Morten S. Mikkelsen's reference implementation
(``mikktspace.c``, 2011, zlib licence; the theory is in his thesis "Simulation
of Wrinkled Surfaces Revisited", 2008) to NumPy, for triangle meshes:

1. **Welding.** Corners whose vertices have bitwise-identical position, normal
   and uv are the same vertex; nothing else is shared (so uv seams and hard
   edges split the frame).
2. **Per triangle**, the first-order derivatives of position with respect to
   ``u`` and ``v``, ``vOs = dv31 dp1 - dv21 dp2`` and
   ``vOt = -du31 dp1 + du21 dp2`` (not divided by the uv area), normalised and
   multiplied by the sign of the signed uv area (``orient``: whether the uv
   mapping preserves the orientation). A triangle with coinciding positions
   is *degenerate*; one with a zero uv area or zero derivatives "groups with
   anything" (it contributes no direction).
3. **Groups.** Around each welded vertex, the triangles reachable through
   shared edges that have the same orientation form a group (a mirror seam
   through a vertex therefore gives it two tangents, one per handedness).
   Triangles that group with anything take the orientation of the first group
   that reaches them — the one order dependency of the reference.
4. **The tangent of a corner** is the sum over its group of each triangle's
   ``vOs`` projected onto the vertex normal's tangent plane and normalised,
   weighted by the triangle's corner angle (measured between the projected
   edges), then normalised. Its sign is +1 for orientation-preserving groups,
   -1 otherwise.
5. **Degenerate triangles** copy the tangent of the first non-degenerate
   corner of the same welded vertex; corners no group reaches keep
   ``(1, 0, 0)`` and sign -1, as the reference leaves them.

The frame is reconstructed per pixel as the reference prescribes for bakers
that follow it (see `jaxnm.frames.mikktspace_frame`): the interpolated,
*unnormalised* tangent ``T`` and normal ``N``, ``B = sign * cross(N, T)``, and
the perturbed normal ``normalize(m.x T + m.y B + m.z N)``.

Quads are not handled (jaxnm meshes are triangles): a mesh baked as quads must
be triangulated before baking for the two frames to agree.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mikktspace_tangents"]

_F32_MIN = np.float32(np.finfo(np.float32).tiny)  # FLT_MIN: the reference's "not zero"


def _not_zero(x) -> np.ndarray:
    return np.abs(x) > _F32_MIN


def _normalize_rows(v: np.ndarray) -> np.ndarray:
    """Each row divided by its length where some component is not zero (else unchanged)."""
    nz = np.any(_not_zero(v), axis=-1, keepdims=True)
    length = np.sqrt(np.sum(v * v, axis=-1, keepdims=True, dtype=np.float32))
    return np.where(nz, v * (np.float32(1.0) / np.where(nz, length, 1)), v).astype(np.float32)


def _project(n: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v`` minus its component along the unit normal ``n``, normalised (rows)."""
    d = np.sum(n * v, axis=-1, keepdims=True, dtype=np.float32)
    return _normalize_rows((v - d * n).astype(np.float32))


def _weld(positions, normals, uv, faces) -> np.ndarray:
    """(F, 3) welded vertex index of every corner: equal (position, normal, uv) bits."""
    key = np.concatenate([positions, normals, uv], axis=1).astype(np.float32)
    key = np.ascontiguousarray(key).view(np.dtype((np.void, key.dtype.itemsize * 8)))[:, 0]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)][faces]  # the lowest vertex index with that key


def _neighbours(corner_w: np.ndarray, good: np.ndarray) -> np.ndarray:
    """(F, 3): the triangle across edge ``i`` (corner ``i`` to ``i + 1``), or -1.

    Edges are pairs of welded vertices; an edge is shared with a triangle that
    runs through it in the opposite direction. Where more than two triangles
    share an edge, each pairs with the first unpaired one in (edge, triangle)
    order, as the reference does.
    """
    nf = corner_w.shape[0]
    nbr = np.full((nf, 3), -1, np.int64)
    f_idx = np.repeat(np.flatnonzero(good), 3)
    e_idx = np.tile(np.arange(3), int(good.sum()))
    a = corner_w[f_idx, e_idx]
    b = corner_w[f_idx, (e_idx + 1) % 3]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((f_idx, hi, lo))
    lo, hi, a = lo[order].tolist(), hi[order].tolist(), a[order].tolist()
    slot = (3 * f_idx + e_idx)[order].tolist()  # (triangle, edge) as a flat index
    f_idx = f_idx[order].tolist()
    flat = nbr.reshape(-1).tolist()
    start = 0
    n = len(lo)
    while start < n:
        end = start + 1
        while end < n and lo[end] == lo[start] and hi[end] == hi[start]:
            end += 1
        for i in range(start, end):
            if flat[slot[i]] != -1:
                continue
            for j in range(i + 1, end):
                # the other triangle runs through the edge the other way round
                if a[j] != a[i] and flat[slot[j]] == -1:
                    flat[slot[i]] = f_idx[j]
                    flat[slot[j]] = f_idx[i]
                    break
        start = end
    return np.array(flat, np.int64).reshape(nf, 3)


def mikktspace_tangents(positions, normals, uv, faces) -> np.ndarray:
    """MikkTSpace tangents of every face corner (see the module docstring).

    **Arguments** (NumPy or JAX arrays, concrete):
    - `positions` (V, 3), `normals` (V, 3) unit vertex normals, `uv` (V, 2),
      `faces` (F, 3) counter-clockwise triangles.

    **Returns:** (F, 3, 4) float32: per corner the unit tangent (along +u on the
    surface, in the tangent plane of the vertex normal) and its sign ``w``
    (+1 or -1, the bitangent is ``w * cross(N, T)``), the values the reference
    implementation's ``setTSpaceBasic`` reports.

    Arrays of the wrong shape or dtype, non-finite values and face indices out of range
    are refused in one line (`jaxnm.geometry.check_mesh_arrays`).
    """
    from .geometry import check_mesh_arrays  # (geometry imports this module when asked)

    for name, arr in (("uv", uv), ("normals", normals)):
        if arr is None:
            raise ValueError(f"mikktspace_tangents: needs {name}, got None")
    check_mesh_arrays(positions, faces, uv, normals, source="mikktspace_tangents")
    pos = np.asarray(positions, np.float32)
    nrm = np.asarray(normals, np.float32)
    tex = np.asarray(uv, np.float32)
    faces = np.asarray(faces, np.int64)
    corner_w = _weld(pos, nrm, tex, faces)
    p = pos[corner_w]  # (F, 3, 3) per corner, through the welded vertex
    degenerate = (np.all(p[:, 0] == p[:, 1], -1) | np.all(p[:, 0] == p[:, 2], -1)
                  | np.all(p[:, 1] == p[:, 2], -1))
    v_os, v_ot, orient, any_group = _triangle_directions(p, tex[corner_w])
    nbr = _neighbours(corner_w, ~degenerate)
    groups = _groups(corner_w, nbr, ~degenerate & ~any_group, any_group, orient)
    tangent, corner_sign = _group_tangents(groups, corner_w, nrm[corner_w], p, v_os, v_ot,
                                           any_group)
    if degenerate.any():
        _copy_to_degenerate(tangent, corner_sign, corner_w, degenerate)
    return np.concatenate([tangent, corner_sign[..., None]], -1).astype(np.float32)


def _triangle_directions(p: np.ndarray, t: np.ndarray):
    """Per triangle, from its corners' positions ``p`` and uvs ``t``: the unit first-order
    directions of +u and +v (eqs. 18 and 19 of the reference, signed by the uv orientation),
    the orientation (uv area > 0), and whether the triangle joins any group (its uv area or
    a derivative is zero)."""
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    t21, t31 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area2 = (t21[:, 0] * t31[:, 1] - t21[:, 1] * t31[:, 0]).astype(np.float32)
    v_os = (t31[:, 1:2] * d1 - t21[:, 1:2] * d2).astype(np.float32)
    v_ot = (-t31[:, 0:1] * d1 + t21[:, 0:1] * d2).astype(np.float32)
    orient = area2 > 0
    sign = np.where(orient, np.float32(1), np.float32(-1))[:, None]
    len_os = np.sqrt(np.sum(v_os * v_os, -1, dtype=np.float32))
    len_ot = np.sqrt(np.sum(v_ot * v_ot, -1, dtype=np.float32))
    has_area = _not_zero(area2)
    abs_area = np.where(has_area, np.abs(area2), 1)
    v_os = np.where((has_area & _not_zero(len_os))[:, None],
                    v_os * (sign / np.where(_not_zero(len_os), len_os, 1)[:, None]), 0)
    v_ot = np.where((has_area & _not_zero(len_ot))[:, None],
                    v_ot * (sign / np.where(_not_zero(len_ot), len_ot, 1)[:, None]), 0)
    mag_s = np.where(has_area, len_os / abs_area, 0)
    mag_t = np.where(has_area, len_ot / abs_area, 0)
    any_group = ~(has_area & _not_zero(mag_s) & _not_zero(mag_t))
    return v_os.astype(np.float32), v_ot.astype(np.float32), orient, any_group


def _groups(corner_w: np.ndarray, nbr: np.ndarray, seeds: np.ndarray, any_group: np.ndarray,
            orient: np.ndarray) -> list[tuple[int, bool, list]]:
    """The groups of triangles around each welded vertex, connected through shared edges,
    of one orientation: ``(vertex, orientation, member triangles)``, grown depth first
    (left edge before right edge, as the reference recurses) from the ``seeds``. A triangle
    that joins any group takes the orientation of the first group that reaches it."""
    cw, nb, ag = corner_w.tolist(), nbr.tolist(), any_group.tolist()
    orient = orient.tolist()
    assigned = [[-1, -1, -1] for _ in cw]
    groups = []
    for f in np.flatnonzero(seeds).tolist():
        for i in range(3):
            if assigned[f][i] != -1:
                continue
            g, rep, g_orient = len(groups), cw[f][i], orient[f]
            members = [f]
            assigned[f][i] = g
            stack = [nb[f][(i + 2) % 3], nb[f][i]]  # popped: left (edge i) first
            while stack:
                t_ = stack.pop()
                if t_ < 0:
                    continue
                j = cw[t_].index(rep)
                if assigned[t_][j] != -1:
                    continue
                if ag[t_] and assigned[t_] == [-1, -1, -1]:
                    orient[t_] = g_orient  # the first group to reach it decides
                if orient[t_] != g_orient:
                    continue
                members.append(t_)
                assigned[t_][j] = g
                stack += [nb[t_][(j + 2) % 3], nb[t_][j]]
            groups.append((rep, g_orient, members))
    return groups


def _group_tangents(groups, corner_w, n_c, p, v_os, v_ot, any_group):
    """Each corner's tangent and sign: the angle-weighted average of its (sub)group's
    members' directions, projected onto the tangent plane of the corner's (welded) vertex
    normal ``n_c`` (F, 3, 3); corners in no group keep +x and -1."""
    nf = corner_w.shape[0]
    os_c = _project(n_c, np.broadcast_to(v_os[:, None], n_c.shape))
    ot_c = _project(n_c, np.broadcast_to(v_ot[:, None], n_c.shape))
    e1 = _project(n_c, np.roll(p, 1, axis=1) - p)  # towards the previous corner
    e2 = _project(n_c, np.roll(p, -1, axis=1) - p)  # towards the next corner
    angle_c = np.arccos(np.clip(np.sum(e1 * e2, -1, dtype=np.float32), -1, 1)).astype(np.float32)
    tangent = np.zeros((nf, 3, 3), np.float32)
    tangent[..., 0] = 1.0
    corner_sign = np.full((nf, 3), -1.0, np.float32)
    if not groups:
        return tangent, corner_sign
    sizes = np.array([len(m) for _, _, m in groups])
    gid = np.repeat(np.arange(len(groups)), sizes)
    mem = np.concatenate([m for _, _, m in groups]).astype(np.int64)
    rep = np.array([r for r, _, _ in groups])[gid]
    corner = np.argmax(corner_w[mem] == rep[:, None], axis=1)  # first matching corner
    os_m, ot_m = os_c[mem, corner], ot_c[mem, corner]
    gwa = any_group[mem]
    weight = np.where(gwa, 0, angle_c[mem, corner])[:, None]  # only good ones contribute
    starts = np.cumsum(sizes) - sizes
    whole = _whole_groups(gid, sizes, starts, os_m, ot_m, gwa)
    tangent[mem, corner] = _normalize_rows(_sums_in_order(weight * os_m, starts, sizes))[gid]
    corner_sign[mem, corner] = np.where([o for _, o, _ in groups], 1.0, -1.0)[gid]
    for g in np.flatnonzero(~whole):  # groups whose members split into subgroups
        k = slice(starts[g], starts[g] + sizes[g])
        tangent[mem[k], corner[k]] = _subgroup_tangents(os_m[k], ot_m[k], gwa[k], weight[k])
    return tangent, corner_sign


#: The default 180 degree threshold of the reference (members whose directions are further
#: apart than this do not share a tangent).
_THRES_COS = np.float32(np.cos(np.float32(np.pi)))


def _sums_in_order(x, starts, sizes):
    """Per group of consecutive rows of ``x``, their sum, added one row after the other
    (in the order, and so with the rounding, of ``np.sum`` over a group's rows)."""
    acc = x[starts].copy()
    for k in range(1, int(sizes.max())):
        more = np.flatnonzero(sizes > k)
        acc[more] += x[starts[more] + k]
    return acc


def _whole_groups(gid, sizes, starts, os_m, ot_m, gwa):
    """Per group (members in order, ``gid`` the group of each), whether every pair of its
    members is within the angle threshold (or groups with anything): one tangent for all."""
    n = sizes[gid]  # each member against every member of its group
    a = np.repeat(np.arange(len(gid)), n)
    b = starts[gid][a] + np.arange(a.size) - np.repeat(np.cumsum(n) - n, n)
    ok = ((np.sum(os_m[a] * os_m[b], -1, dtype=np.float32) > _THRES_COS)
          & (np.sum(ot_m[a] * ot_m[b], -1, dtype=np.float32) > _THRES_COS)
          | gwa[a] | gwa[b] | (a == b))
    whole = np.ones(len(sizes), bool)
    whole[gid[a[~ok]]] = False
    return whole


def _subgroup_tangents(os_m, ot_m, gwa, weight):
    """The tangents of a group's members where the threshold splits it: each member's
    average over the members within the threshold of it."""
    keep = (((os_m @ os_m.T > _THRES_COS) & (ot_m @ ot_m.T > _THRES_COS))
            | gwa[:, None] | gwa[None, :] | np.eye(len(gwa), dtype=bool))
    rows, which = np.unique(keep, axis=0, return_inverse=True)  # the distinct subgroups
    sums = [_normalize_rows(np.sum(weight[r] * os_m[r], axis=0, dtype=np.float32)[None])[0]
            for r in rows]
    return np.asarray(sums)[which.reshape(-1)]


def _copy_to_degenerate(tangent, corner_sign, corner_w, degenerate) -> None:
    """Degenerate triangles' corners take the tangent and sign of the first good corner of
    the same welded vertex (in place)."""
    good_corners = np.flatnonzero(np.repeat(~degenerate, 3))
    first = {}
    for c in good_corners[::-1]:
        first[corner_w.reshape(-1)[c]] = c
    flat_t, flat_s = tangent.reshape(-1, 3), corner_sign.reshape(-1)
    for c in np.flatnonzero(np.repeat(degenerate, 3)):
        src = first.get(corner_w.reshape(-1)[c])
        if src is not None:
            flat_t[c], flat_s[c] = flat_t[src], flat_s[src]
