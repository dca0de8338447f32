"""Triangle meshes: the `Mesh` pytree, validation, and vertex normals.

A mesh is a set of arrays: ``positions`` (V, 3), ``faces`` (F, 3) int32 with
counter-clockwise front faces, and optional per-vertex ``uv`` (V, 2) (origin
at the **bottom-left** of the texture image, OpenGL/OBJ convention) and
``normals`` (V, 3). Vertices that differ in any attribute (e.g. at a uv seam)
are separate vertices that share a position.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float, Integer

from .numerics import angle_between, safe_normalize
from .numerics import cross as _cross

__all__ = ["Mesh", "face_normals", "vertex_normals", "check_mesh_arrays", "bounding_sphere"]

_HIGHEST = jax.lax.Precision.HIGHEST


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Mesh:
    """A triangle mesh (see the module docstring for conventions).

    **Fields:**
    - `positions`: (V, 3) float32 world-space positions.
    - `faces`: (F, 3) int32 vertex indices, counter-clockwise = front.
    - `uv`: (V, 2) float32 texture coordinates, origin bottom-left, or None.
    - `normals`: (V, 3) float32 unit vertex normals, or None.
    - `tangents`: (F, 3, 4) float32 per face corner: the tangent ``xyz`` and its
      sign ``w`` (the bitangent is ``w * cross(N, T)``), or None. Per corner
      because MikkTSpace gives a vertex on a mirror seam one tangent per side.
    - `tangent_source` (static): where `tangents` came from: ``"mikktspace"``
      (`with_tangents`), ``"file"`` (a glTF ``TANGENT`` attribute), or None.
    """

    positions: Array
    faces: Array
    uv: Array | None = None
    normals: Array | None = None
    tangents: Array | None = None
    tangent_source: str | None = dataclasses.field(default=None, metadata=dict(static=True))

    def with_tangents(self) -> Mesh:
        """This mesh with MikkTSpace ``tangents`` (`jaxnm.tangents.mikktspace_tangents`),
        replacing any it had; needs concrete (not traced) positions, normals and uvs."""
        from .tangents import mikktspace_tangents

        if self.uv is None or self.normals is None:
            raise ValueError("MikkTSpace tangents need uvs and vertex normals")
        t = mikktspace_tangents(np.asarray(self.positions), np.asarray(self.normals),
                                np.asarray(self.uv), np.asarray(self.faces))
        return dataclasses.replace(self, tangents=jnp.asarray(t), tangent_source="mikktspace")

    @property
    def num_vertices(self) -> int:
        return self.positions.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]

    def with_normals(self, weighting: str = "angle") -> Mesh:
        """This mesh with ``normals`` computed by `vertex_normals` (replacing any it had)."""
        return dataclasses.replace(
            self, normals=vertex_normals(self.positions, self.faces, weighting=weighting))

    def transformed(self, model) -> Mesh:
        """This mesh with positions and normals transformed by a 4x4 affine ``model`` matrix.

        Normals use the inverse transpose (they are covectors), renormalised.
        """
        m = np.asarray(model, np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"model matrix must be a finite 4x4 matrix, got shape {m.shape}")
        if not np.allclose(m[3], [0, 0, 0, 1]):
            raise ValueError("model matrix must be affine (last row 0, 0, 0, 1)")
        lin = m[:3, :3]
        if abs(np.linalg.det(lin)) < 1e-12:
            raise ValueError("model matrix is singular")
        pos = jnp.matmul(jnp.asarray(self.positions), jnp.asarray(lin.T, jnp.float32),
                         precision=_HIGHEST) + jnp.asarray(m[None, :3, 3], jnp.float32)
        normals = self.normals
        faces = self.faces
        if normals is not None:
            nmat = np.linalg.inv(lin).T
            normals = safe_normalize(jnp.matmul(jnp.asarray(normals),
                                                jnp.asarray(nmat.T, jnp.float32),
                                                precision=_HIGHEST))
        tangents = self.tangents
        if tangents is not None:  # directions: the linear part; the sign is re-derived below
            t = jnp.asarray(tangents)
            xyz = safe_normalize(jnp.matmul(t[..., :3], jnp.asarray(lin.T, jnp.float32),
                                            precision=_HIGHEST))
            tangents = jnp.concatenate([xyz, t[..., 3:]], -1)
        if np.linalg.det(lin) < 0:  # a mirror flips the winding; keep CCW = front
            faces = jnp.asarray(faces)[:, ::-1]
            if tangents is not None:  # per corner like the faces; cross(N, T) flips too
                tangents = tangents[:, ::-1] * jnp.asarray([1.0, 1.0, 1.0, -1.0])
        return dataclasses.replace(self, positions=pos, normals=normals, faces=faces,
                                   tangents=tangents)


def face_normals(positions: Float[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"], *,
                 normalize: bool = True) -> Float[Array, "F 3"]:
    """(F, 3) face normals ``(p1 - p0) x (p2 - p0)``; unit length (zero for degenerate faces)
    if ``normalize``, else with length twice the face area."""
    p = jnp.asarray(positions)[jnp.asarray(faces)]
    n = _cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return safe_normalize(n) if normalize else n


def vertex_normals(positions: Float[ArrayLike, "V 3"], faces: Integer[ArrayLike, "F 3"], *,
                   weighting: str = "angle") -> Float[Array, "V 3"]:
    """(V, 3) unit vertex normals from the faces around each vertex.

    ``weighting="angle"`` weights each face normal by the corner angle at the
    vertex (robust to uneven tessellation); ``"area"`` by the face area.
    Degenerate faces contribute nothing; a vertex with no (non-degenerate)
    face gets the zero vector.
    """
    positions = jnp.asarray(positions)
    faces = jnp.asarray(faces, jnp.int32)
    p = positions[faces]  # (F, 3, 3)
    cross = _cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    if weighting == "area":
        w = jnp.broadcast_to(cross[:, None, :], p.shape)  # |cross| = 2 area
    elif weighting == "angle":
        unit = safe_normalize(cross)
        e_next = jnp.roll(p, -1, axis=1) - p  # corner i: edges to i+1 and i-1
        e_prev = jnp.roll(p, 1, axis=1) - p
        angle = angle_between(e_next, e_prev)  # (F, 3)
        w = unit[:, None, :] * angle[..., None]
    else:
        raise ValueError(f"vertex_normals: unknown weighting {weighting!r}; use 'angle' or 'area'")
    acc = jnp.zeros_like(positions).at[faces.reshape(-1)].add(w.reshape(-1, 3))
    return safe_normalize(acc)


def bounding_sphere(*meshes: Mesh) -> tuple[np.ndarray, float]:
    """The centre of the meshes' joint bounding box (float64, on the host) and the radius
    about it that holds every vertex (at least 1e-12)."""
    points = [np.asarray(m.positions, np.float64) for m in meshes]
    centre = (np.min([p.min(0) for p in points], 0) + np.max([p.max(0) for p in points], 0)) / 2
    radius = max(float(np.sqrt(((p - centre) ** 2).sum(1).max())) for p in points)
    return centre, max(radius, 1e-12)


def check_mesh_arrays(positions, faces, uv=None, normals=None, *, source: str = "mesh",
                      values: bool = True) -> None:
    """Raise ``ValueError`` naming ``source`` if the mesh arrays are unusable (a
    ``TypeError`` for what is not an array: a list, say).

    Checks shapes and dtypes (always), and, with ``values``, for concrete (not traced)
    arrays, finite values and face indices in range (a pass over the arrays on the host,
    which copies device arrays there first). Degenerate (zero-area) triangles are allowed:
    they cover no pixel.
    """
    for name, arr, dtype in (("positions", positions, "float32"), ("faces", faces, "int32"),
                             ("uv", uv, "float32"), ("normals", normals, "float32")):
        if arr is not None and not (hasattr(arr, "shape") and hasattr(arr, "dtype")):
            raise TypeError(f"{source}: {name} must be an array (np.asarray({name}, "
                            f"np.{dtype}), say), got a {type(arr).__name__}")
    shape = jnp.shape(positions)
    fshape = jnp.shape(faces)
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"{source}: positions must have shape (V, 3), got {shape}")
    if shape[0] == 0:
        raise ValueError(f"{source}: the mesh has no vertices")
    if len(fshape) != 2 or fshape[1] != 3:
        raise ValueError(f"{source}: faces must be triangles with shape (F, 3), got {fshape}")
    if fshape[0] == 0:
        raise ValueError(f"{source}: the mesh has no faces")
    fdtype = jnp.result_type(faces)
    if not jnp.issubdtype(fdtype, jnp.integer):
        raise ValueError(f"{source}: faces must be integer indices, got dtype {fdtype}")
    for name, arr, c in (("uv", uv, 2), ("normals", normals, 3)):
        if arr is not None and jnp.shape(arr) != (shape[0], c):
            raise ValueError(f"{source}: {name} must have shape ({shape[0]}, {c}), "
                             f"got {jnp.shape(arr)}")
    if values:
        _check_values(positions, faces, uv, normals, shape[0], source)


def _check_values(positions, faces, uv, normals, num_vertices: int, source: str) -> None:
    """The value checks of `check_mesh_arrays`, on whichever arrays are concrete."""
    for one, many, arr in (("vertex position", "vertex positions", positions),
                           ("vertex uv", "vertex uvs", uv),
                           ("vertex normal", "vertex normals", normals)):
        if arr is None or not _is_concrete(arr):
            continue
        bad = ~np.all(np.isfinite(np.asarray(arr)), axis=1)
        if bad.any():
            n = int(bad.sum())
            what = f"1 {one} is" if n == 1 else f"{n} {many} are"
            raise ValueError(f"{source}: {what} NaN or infinite (the first: vertex "
                             f"{int(np.argmax(bad))}, counting from 0)")
    if _is_concrete(faces):
        faces = np.asarray(faces)
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= num_vertices:
            raise ValueError(f"{source}: face indices must be in [0, {num_vertices - 1}], "
                             f"found {lo if lo < 0 else hi}")


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


