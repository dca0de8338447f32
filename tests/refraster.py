"""Independent float64 NumPy reference rasterizer for jaxnm tests.

Slow, deliberately simple, written from first principles so that it shares
no formulation with the JAX rasterizer:

1. each triangle is clipped in homogeneous clip space against the near
   (``z >= -w``) and far (``z <= w``) planes with Sutherland-Hodgman (no
   division happens before clipping, so ``w <= 0`` is never divided by);
2. the clipped convex polygon is divided by ``w`` and mapped to window
   coordinates (OpenGL viewport covering the whole image, window y UP,
   depth range [0, 1]);
3. the polygon is fan-triangulated and every sub-triangle is scan-tested at
   pixel centres with plain 2D edge functions in float64, using a tie rule
   for centres lying exactly on an edge;
4. depth (affine in window space) is tested with LESS, ties to the lower
   triangle index;
5. perspective-correct barycentrics of the ORIGINAL triangle are obtained by
   solving the 3x3 system of the view ray through the pixel centre
   intersected with the triangle's plane (``np.linalg.solve``).

Conventions: window pixel ``(i, j)`` has its centre at ``(i + 0.5, j + 0.5)``
with window y pointing up.  Every returned image uses IMAGE layout: row
``r = 0`` is the top row, i.e. row ``r`` holds window row
``j = height - 1 - r`` and column ``c`` is window ``i``.

Edge functions are evaluated in a canonical way (the two endpoints of an edge
are put in lexicographic order before evaluation and the result is negated if
needed), and clip-plane intersections are likewise computed from canonically
ordered endpoints, so two triangles (or two fan sub-triangles) sharing an edge
see bit-exactly opposite edge-function values.  In addition, the SIGN of every
edge function used for coverage is exact: values within a (generous) rounding
bound of zero are re-evaluated in rational arithmetic (``fractions``) on the
float64 window coordinates.  Coverage is therefore the exact coverage of the
float64 window-space polygons: with the tie rule, every pixel centre on a
shared edge or shared vertex is covered exactly once.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

__all__ = [
    "rasterize_ref",
    "bary_at",
    "bary_and_derivs_at",
    "interpolate_ref",
    "perspective",
    "look_at",
    "to_clip",
    "TIE_RULES",
]

TIE_RULES = ("left_top_yup", "left_bottom_yup")


# ---------------------------------------------------------------------------
# Camera helpers (standard gluPerspective / gluLookAt, column-vector
# convention: clip = P @ V @ M @ [p, 1]).
# ---------------------------------------------------------------------------


def perspective(fov_y_deg, aspect, near, far) -> np.ndarray:
    """OpenGL ``gluPerspective`` projection matrix (4x4 float64)."""
    f = 1.0 / np.tan(np.deg2rad(float(fov_y_deg)) / 2.0)
    near = float(near)
    far = float(far)
    m = np.zeros((4, 4), dtype=np.float64)
    m[0, 0] = f / float(aspect)
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def look_at(eye, target, up) -> np.ndarray:
    """OpenGL ``gluLookAt`` view matrix (4x4 float64, camera looks down -z)."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    f = target - eye
    f = f / np.linalg.norm(f)
    s = np.cross(f, up)
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4, dtype=np.float64)
    m[0, :3] = s
    m[1, :3] = u
    m[2, :3] = -f
    m[0, 3] = -s @ eye
    m[1, 3] = -u @ eye
    m[2, 3] = f @ eye
    return m


def to_clip(positions, mvp) -> np.ndarray:
    """Map (V, 3) positions (or (V, 4) homogeneous points) to (V, 4) clip
    coordinates ``mvp @ [p, 1]`` (float64)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.shape[-1] == 3:
        p = np.concatenate([p, np.ones(p.shape[:-1] + (1,), dtype=np.float64)], axis=-1)
    return p @ np.asarray(mvp, dtype=np.float64).T


# ---------------------------------------------------------------------------
# Geometry: clipping, projection, edge functions
# ---------------------------------------------------------------------------


def _plane_dist(v, plane):
    # Signed "inside" distance; >= 0 means inside.
    if plane == "near":  # z >= -w
        return v[2] + v[3]
    return v[3] - v[2]  # far: z <= w


def _intersect(a, b, da, db):
    """Intersection of segment a-b with the plane (da, db of opposite strict
    sign).  Computed from canonically ordered endpoints so that the result
    does not depend on the direction in which the edge is traversed."""
    if tuple(a) > tuple(b):
        a, b, da, db = b, a, db, da
    t = da / (da - db)
    return a + t * (b - a)


def _clip_polygon(verts):
    """Sutherland-Hodgman clip of a (3, 4) clip-space triangle against the
    near and far planes.  Returns a list of (4,) vertices (possibly empty).
    Vertices exactly on a plane are kept and do not generate duplicates."""
    poly = [np.asarray(v, dtype=np.float64) for v in verts]
    for plane in ("near", "far"):
        if not poly:
            break
        out = []
        n = len(poly)
        for k in range(n):
            cur = poly[k]
            nxt = poly[(k + 1) % n]
            dc = _plane_dist(cur, plane)
            dn = _plane_dist(nxt, plane)
            if dc >= 0:
                out.append(cur)
            if (dc > 0 and dn < 0) or (dc < 0 and dn > 0):
                out.append(_intersect(cur, nxt, dc, dn))
        poly = out
    return poly


def _prepare(clip, faces, width, height, subpixel_bits=None):
    """Clip and project every triangle.

    Returns a list with, per triangle, either None (nothing visible, or a
    degenerate clipped vertex with w <= 0, which can only happen for
    z = w = 0) or a dict with
      ``win``   (n, 3) window coordinates (x, y, depth) of the clipped polygon,
      ``area2`` twice the signed window-space area (y up) of the polygon.
    """
    clip = np.asarray(clip, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    out = []
    for t in range(faces.shape[0]):
        poly = _clip_polygon(clip[faces[t]])
        if len(poly) < 3:
            out.append(None)
            continue
        P = np.stack(poly)
        w = P[:, 3]
        if np.any(w <= 0):  # only possible for z = w = 0 (point at infinity)
            out.append(None)
            continue
        win = np.empty((P.shape[0], 3), dtype=np.float64)
        win[:, 0] = (P[:, 0] / w + 1.0) * 0.5 * width
        win[:, 1] = (P[:, 1] / w + 1.0) * 0.5 * height
        win[:, 2] = (P[:, 2] / w + 1.0) * 0.5
        unsnapped = win.copy()
        if subpixel_bits is not None:  # GPU vertex snapping (coverage only)
            q = float(2**subpixel_bits)
            win[:, :2] = np.round(win[:, :2] * q) / q
        # Twice the signed area (shoelace), evaluated exactly so that its
        # sign (facing, culling, zero area) is never a rounding artefact.
        xs = [Fraction(float(v)) for v in win[:, 0]]
        ys = [Fraction(float(v)) for v in win[:, 1]]
        n = len(xs)
        area2 = float(sum(xs[k] * ys[(k + 1) % n] - xs[(k + 1) % n] * ys[k] for k in range(n)))
        out.append({"win": win, "area2": area2, "unsnapped": unsnapped})
    return out


def _edge_value(a, b, px, py):
    """2D edge function of the directed edge a->b at points (px, py):
    ``(b - a) x (p - a)``, > 0 to the LEFT of a->b (y up).  Evaluated with the
    endpoints in canonical (lexicographic) order and negated if needed, so
    E(a->b) == -E(b->a) bit-exactly."""
    if (a[0], a[1]) > (b[0], b[1]):
        return -_edge_value(b, a, px, py)
    return (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])


def _orient_exact(ax, ay, bx, by, px, py):
    """Exact sign (-1, 0, 1) of ``(b - a) x (p - a)`` for float inputs
    (rational arithmetic on the exact float64 values)."""
    F = Fraction
    v = (F(bx) - F(ax)) * (F(py) - F(ay)) - (F(by) - F(ay)) * (F(px) - F(ax))
    return (v > 0) - (v < 0)


def _edge_sign(a, b, px, py):
    """Float edge function (see :func:`_edge_value`) and its EXACT sign.

    The float value is trusted where it exceeds a (generous, ~30x
    Shewchuk's orient2d bound) rounding-error bound; the remaining, nearly
    on-edge points are re-evaluated in exact rational arithmetic.  Coverage
    is thus the exact coverage of the float64 window-space polygon: no
    rounding-induced double hits or holes where several edges meet."""
    E = _edge_value(a, b, px, py)
    t1 = (b[0] - a[0]) * (py - a[1])
    t2 = (b[1] - a[1]) * (px - a[0])
    sgn = np.sign(E).astype(np.int64)
    unsure = np.abs(E) <= 1e-14 * (np.abs(t1) + np.abs(t2))
    if unsure.any():
        for idx in zip(*np.nonzero(unsure)):
            sgn[idx] = _orient_exact(a[0], a[1], b[0], b[1], float(px[idx]), float(py[idx]))
    return E, sgn


def _tie_ok(nx, ny, tie_rule):
    """Does an edge with inward normal (nx, ny) own centres lying on it?"""
    if tie_rule == "left_top_yup":
        return nx > 0 or (nx == 0 and ny < 0)
    if tie_rule == "left_bottom_yup":
        return nx > 0 or (nx == 0 and ny > 0)
    raise ValueError(f"unknown tie_rule {tie_rule!r}; expected one of {TIE_RULES}")


def _fragments(prep_t, width, height, *, tie_rule="left_top_yup"):
    """Yield the fragments of one prepared (clipped, projected) triangle, one
    fan sub-triangle at a time, as tuples
    ``(k, i, j, depth, edge_dist)`` where ``k`` is the sub-triangle index
    (fan (0, k+1, k+2)), ``i``/``j`` are int arrays of window pixel indices,
    ``depth`` the window depth and ``edge_dist`` the distance (pixels) from
    the centre to the nearest edge line of the sub-triangle.

    Orientation: the sub-triangles are put in counter-clockwise (y up) order
    using the sign of the whole polygon's area; a sub-triangle whose own
    (exact) area is then not strictly positive (degenerate, or a rounding
    sliver of a clipped polygon) is skipped.  Zero-area polygons yield
    nothing.  Inside tests use exact edge-function signs (_edge_sign).
    """
    win = prep_t["win"]
    s = np.sign(prep_t["area2"])
    if s == 0:
        return
    n = win.shape[0]
    for k in range(n - 2):
        idx = [0, k + 1, k + 2] if s > 0 else [0, k + 2, k + 1]
        v = win[idx]  # (3, 3), counter-clockwise
        p0, p1, p2 = v[0, :2], v[1, :2], v[2, :2]
        if _orient_exact(p0[0], p0[1], p1[0], p1[1], p2[0], p2[1]) <= 0:
            continue
        # Pixel range whose centres lie in the bounding box, clipped to image.
        xmin, xmax = v[:, 0].min(), v[:, 0].max()
        ymin, ymax = v[:, 1].min(), v[:, 1].max()
        i0 = int(np.ceil(np.clip(xmin - 0.5, -1.0, width)))
        i1 = int(np.floor(np.clip(xmax - 0.5, -1.0, width)))
        j0 = int(np.ceil(np.clip(ymin - 0.5, -1.0, height)))
        j1 = int(np.floor(np.clip(ymax - 0.5, -1.0, height)))
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, width - 1), min(j1, height - 1)
        if i1 < i0 or j1 < j0:
            continue
        jj, ii = np.meshgrid(np.arange(j0, j1 + 1), np.arange(i0, i1 + 1), indexing="ij")
        px = ii + 0.5
        py = jj + 0.5
        inside = np.ones(px.shape, dtype=bool)
        E = []
        dist = np.full(px.shape, np.inf)
        # Edge e is opposite vertex e: edge (e+1) -> (e+2).
        for e in range(3):
            a = v[(e + 1) % 3, :2]
            b = v[(e + 2) % 3, :2]
            Ee, sg = _edge_sign(a, b, px, py)
            nx, ny = -(b[1] - a[1]), (b[0] - a[0])  # inward (left) normal
            if _tie_ok(nx, ny, tie_rule):
                inside &= sg >= 0
            else:
                inside &= sg > 0
            E.append(Ee)
            dist = np.minimum(dist, np.abs(Ee) / np.hypot(nx, ny))
        if not inside.any():
            continue
        # depth from the UNSNAPPED positions (GPUs snap for coverage only)
        u = prep_t.get("unsnapped", win)[idx]
        px_in, py_in = px[inside], py[inside]
        E = [(u[(e + 2) % 3, 0] - u[(e + 1) % 3, 0]) * (py_in - u[(e + 1) % 3, 1])
             - (u[(e + 2) % 3, 1] - u[(e + 1) % 3, 1]) * (px_in - u[(e + 1) % 3, 0])
             for e in range(3)]
        Esum = E[0] + E[1] + E[2]
        depth = (E[0] * u[0, 2] + E[1] * u[1, 2] + E[2] * u[2, 2]) / Esum
        yield k, ii[inside], jj[inside], depth, dist[inside]


def _segment_distance(a, b, px, py):
    """Euclidean distance from points (px, py) to the segment a-b."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    L2 = dx * dx + dy * dy
    rx, ry = px - a[0], py - a[1]
    if L2 == 0:
        return np.hypot(rx, ry)
    t = np.clip((rx * dx + ry * dy) / L2, 0.0, 1.0)
    return np.hypot(rx - t * dx, ry - t * dy)


def _any_edge_distance(prep, width, height):
    """(height, width) window-layout array: distance from each pixel centre to
    the nearest boundary edge (segment) of ANY clipped triangle polygon
    (including culled and zero-area ones) whose bounding box is within 1 px
    of the centre; inf if none."""
    out = np.full((height, width), np.inf)
    for p in prep:
        if p is None:
            continue
        win = p["win"]
        xmin, xmax = win[:, 0].min() - 1.0, win[:, 0].max() + 1.0
        ymin, ymax = win[:, 1].min() - 1.0, win[:, 1].max() + 1.0
        i0 = max(int(np.ceil(np.clip(xmin - 0.5, -1.0, width))), 0)
        i1 = min(int(np.floor(np.clip(xmax - 0.5, -1.0, width))), width - 1)
        j0 = max(int(np.ceil(np.clip(ymin - 0.5, -1.0, height))), 0)
        j1 = min(int(np.floor(np.clip(ymax - 0.5, -1.0, height))), height - 1)
        if i1 < i0 or j1 < j0:
            continue
        jj, ii = np.meshgrid(np.arange(j0, j1 + 1), np.arange(i0, i1 + 1), indexing="ij")
        px, py = ii + 0.5, jj + 0.5
        d = np.full(px.shape, np.inf)
        n = win.shape[0]
        for k in range(n):
            d = np.minimum(d, _segment_distance(win[k, :2], win[(k + 1) % n, :2], px, py))
        blk = out[j0 : j1 + 1, i0 : i1 + 1]
        np.minimum(blk, d, out=blk)
    return out


# ---------------------------------------------------------------------------
# Perspective-correct barycentrics
# ---------------------------------------------------------------------------


def _solve(A, rhs):
    """Batched solve A x = rhs for (..., 3, 3) A and (..., 3) rhs; NaN where A
    is exactly singular (e.g. view ray parallel to the triangle plane)."""
    A = np.asarray(A, dtype=np.float64)
    rhs = np.broadcast_to(np.asarray(rhs, dtype=np.float64), A.shape[:-1])
    out = np.full(A.shape[:-1], np.nan)
    if A.size == 0:
        return out
    det = np.linalg.det(A)
    ok = np.isfinite(det) & (det != 0)
    if ok.any():
        try:
            out[ok] = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
        except np.linalg.LinAlgError:  # pragma: no cover - extreme conditioning
            Ao, ro = A[ok], rhs[ok]
            res = np.full(ro.shape, np.nan)
            for n in range(Ao.shape[0]):
                try:
                    res[n] = np.linalg.solve(Ao[n], ro[n])
                except np.linalg.LinAlgError:
                    pass
            out[ok] = res
    return out


def _bary_system(clip, faces, tri, xw, yw, width, height):
    clip = np.asarray(clip, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    tri, xw, yw = np.broadcast_arrays(
        np.asarray(tri, dtype=np.int64),
        np.asarray(xw, dtype=np.float64),
        np.asarray(yw, dtype=np.float64),
    )
    C = clip[faces[tri]]  # (..., 3 vertices, 4)
    X, Y, W = C[..., 0], C[..., 1], C[..., 3]
    xn = 2.0 * xw / width - 1.0
    yn = 2.0 * yw / height - 1.0
    A = np.empty(tri.shape + (3, 3), dtype=np.float64)
    A[..., 0, :] = X - xn[..., None] * W
    A[..., 1, :] = Y - yn[..., None] * W
    A[..., 2, :] = 1.0
    return A, W


def bary_at(clip, faces, tri, xw, yw, width, height) -> np.ndarray:
    """Perspective-correct barycentrics (..., 3) of the ORIGINAL triangle(s)
    ``tri`` (int or int array, broadcast with ``xw``, ``yw``) at window
    coordinates ``(xw, yw)`` (y up, any position, also outside the triangle
    or the image).  Solves ``sum_i b_i (X_i - xn W_i) = 0``,
    ``sum_i b_i (Y_i - yn W_i) = 0``, ``sum_i b_i = 1`` with ``xn, yn`` the
    NDC of the window position.  NaN where the system is exactly singular.
    ``width``/``height`` define the viewport (window -> NDC)."""
    A, _ = _bary_system(clip, faces, tri, xw, yw, width, height)
    return _solve(A, np.array([0.0, 0.0, 1.0]))


def bary_and_derivs_at(clip, faces, tri, xw, yw, width, height):
    """Like :func:`bary_at` but also returns the exact analytic derivatives
    ``(b, db/dx_window, db/dy_window)`` (each (..., 3), window y up), from
    ``db = -A^{-1} (dA) b``:  dA/dxn has row 0 equal to ``-W`` and zeros
    elsewhere (likewise row 1 for yn), and ``dxn/dxw = 2/width``,
    ``dyn/dyw = 2/height``."""
    A, W = _bary_system(clip, faces, tri, xw, yw, width, height)
    b = _solve(A, np.array([0.0, 0.0, 1.0]))
    wb = np.sum(W * b, axis=-1)  # interpolated clip w (up to scale)
    z = np.zeros_like(wb)
    rx = np.stack([wb, z, z], axis=-1)  # -dA/dxn @ b
    ry = np.stack([z, wb, z], axis=-1)  # -dA/dyn @ b
    dbx = _solve(A, rx) * (2.0 / width)
    dby = _solve(A, ry) * (2.0 / height)
    return b, dbx, dby


# ---------------------------------------------------------------------------
# Rasterization
# ---------------------------------------------------------------------------


def rasterize_ref(clip, faces, width, height, *, cull_back=False, tie_rule="left_bottom_yup",
                  subpixel_bits=None) -> dict:
    """Rasterize triangles given by clip-space vertices ``clip`` (V, 4) and
    ``faces`` (F, 3) into a ``height`` x ``width`` image (OpenGL conventions,
    see module docstring).

    Returns a dict of IMAGE-layout arrays (row 0 = top):
      ``triangle_id``  (H, W) int64, -1 on background;
      ``depth``        (H, W) float64 window depth in [0, 1], inf on background;
      ``bary``         (H, W, 3) perspective-correct barycentrics of the
                       original triangle (0 on background);
      ``front_facing`` (H, W) bool, clipped polygon's window-space signed area
                       (y up) > 0;
      ``edge_distance``(H, W) float64: covered pixel -> distance to the nearest
                       edge line of the covering (clipped, fan) sub-triangle;
                       background -> ``any_edge_distance``;
      ``any_edge_distance`` (H, W) float64: distance to the nearest boundary
                       segment of any clipped triangle polygon (culled and
                       zero-area ones included) whose bounding box is within
                       1 px, inf if none.  Useful to mask covered pixels that
                       lie close to ANOTHER triangle's edge.
    ``tie_rule``: "left_top_yup" (centre on an edge is inside iff the inward
    normal n has n.x > 0 or (n.x == 0 and n.y < 0)) or "left_bottom_yup"
    (n.x > 0 or (n.x == 0 and n.y > 0)).  ``cull_back`` skips triangles whose
    clipped window-space signed area is negative (clockwise, y up).
    Depth test LESS, equal depths go to the lower triangle index.
    ``subpixel_bits``: snap the clipped polygon's window x, y to a grid of
    1/2**bits pixel before the edge tests, as GPUs do (llvmpipe: 8 bits);
    depth and barycentrics still use the unsnapped positions.  The default
    tie rule is llvmpipe's (measured, see tests/glref.py).
    """
    if tie_rule not in TIE_RULES:
        raise ValueError(f"unknown tie_rule {tie_rule!r}; expected one of {TIE_RULES}")
    clip = np.asarray(clip, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    H, W = int(height), int(width)
    prep = _prepare(clip, faces, W, H, subpixel_bits)

    # Window layout (row = window j) during rasterization; flipped at the end.
    tid = np.full((H, W), -1, dtype=np.int64)
    depth = np.full((H, W), np.inf)
    ff = np.zeros((H, W), dtype=bool)
    edist = np.full((H, W), np.inf)

    for t, p in enumerate(prep):
        if p is None or p["area2"] == 0:
            continue
        if cull_back and p["area2"] < 0:
            continue
        front = p["area2"] > 0
        for _k, ii, jj, z, d in _fragments(p, W, H, tie_rule=tie_rule):
            win = z < depth[jj, ii]  # strict: earlier (lower) index keeps ties
            ii, jj = ii[win], jj[win]
            tid[jj, ii] = t
            depth[jj, ii] = z[win]
            ff[jj, ii] = front
            edist[jj, ii] = d[win]

    any_d = _any_edge_distance(prep, W, H)
    covered = tid >= 0
    edist = np.where(covered, edist, any_d)

    bary = np.zeros((H, W, 3))
    if covered.any():
        jj, ii = np.nonzero(covered)
        bary[jj, ii] = bary_at(clip, faces, tid[jj, ii], ii + 0.5, jj + 0.5, W, H)

    flip = lambda a: np.ascontiguousarray(a[::-1])  # noqa: E731
    return {
        "triangle_id": flip(tid),
        "depth": flip(depth),
        "bary": flip(bary),
        "front_facing": flip(ff),
        "edge_distance": flip(edist),
        "any_edge_distance": flip(any_d),
    }


def interpolate_ref(attr, faces, rast, clip, width, height, *, derivatives="analytic"):
    """Perspective-correct interpolation of per-vertex ``attr`` (V, C) (a 1-D
    ``attr`` is treated as C = 1) over the output ``rast`` of
    :func:`rasterize_ref`.  Returns ``(value, ddx, ddy)``, each (H, W, C) in
    image layout, zero on background.  ``ddx``/``ddy`` are derivatives with
    respect to window x / window y (y UP: ddy points towards the top row):

    * ``"analytic"``: exact derivatives at the pixel centre;
    * ``"fine"``: GLSL dFdxFine/dFdyFine with helper-pixel semantics on 2x2
      quads aligned to even WINDOW coordinates:
      ``ddx = f_t(i_even + 1, j) - f_t(i_even, j)``,
      ``ddy = f_t(i, j_even + 1) - f_t(i, j_even)``;
    * ``"coarse"``: one value per quad,
      ``ddx = f_t(i_even + 1, j_even) - f_t(i_even, j_even)``,
      ``ddy = f_t(i_even, j_even + 1) - f_t(i_even, j_even)``;
    * ``None``: ddx = ddy = 0.

    ``f_t(i, j)`` is the pixel's own triangle's interpolant evaluated at the
    centre (i + 0.5, j + 0.5), whether or not that centre is covered by t or
    lies inside the image.
    """
    attr = np.asarray(attr, dtype=np.float64)
    if attr.ndim == 1:
        attr = attr[:, None]
    faces = np.asarray(faces, dtype=np.int64)
    H, W = int(height), int(width)
    C = attr.shape[1]
    tid = np.asarray(rast["triangle_id"])
    value = np.zeros((H, W, C))
    ddx = np.zeros((H, W, C))
    ddy = np.zeros((H, W, C))
    mask = tid >= 0
    if not mask.any():
        return value, ddx, ddy
    rr, cc = np.nonzero(mask)
    t = tid[rr, cc]
    Av = attr[faces[t]]  # (N, 3, C)
    b = np.asarray(rast["bary"])[rr, cc]
    value[rr, cc] = np.einsum("ni,nic->nc", b, Av)

    i = cc
    j = H - 1 - rr  # window row
    ie = i & ~1
    je = j & ~1

    def f(ip, jp):
        bb = bary_at(clip, faces, t, ip + 0.5, jp + 0.5, W, H)
        return np.einsum("ni,nic->nc", bb, Av)

    if derivatives is None:
        pass
    elif derivatives == "analytic":
        _, bx, by = bary_and_derivs_at(clip, faces, t, i + 0.5, j + 0.5, W, H)
        ddx[rr, cc] = np.einsum("ni,nic->nc", bx, Av)
        ddy[rr, cc] = np.einsum("ni,nic->nc", by, Av)
    elif derivatives == "fine":
        ddx[rr, cc] = f(ie + 1, j) - f(ie, j)
        ddy[rr, cc] = f(i, je + 1) - f(i, je)
    elif derivatives == "coarse":
        base = f(ie, je)
        ddx[rr, cc] = f(ie + 1, je) - base
        ddy[rr, cc] = f(ie, je + 1) - base
    else:
        raise ValueError(f"unknown derivatives mode {derivatives!r}")
    return value, ddx, ddy
