"""Files in and out: meshes, textures, images, AOVs, JSON, and the outputs of a fit.

Every file jaxnm reads or writes goes through this module but two kinds: the DDS files
of `jaxnm.storage` and the checkpoints of `jaxnm.fit.checkpoint`, which write through
`atomic_write` as well. It is the only module that imports trimesh or imageio; the
stages of the pipeline see plain arrays. Errors about bad files are raised where the file
is read or written, because there the file name is at hand: every message starts with
the path.

Conventions:

- **Images** are float32 arrays ``(H, W, C)`` in IMAGE layout: row 0 is the top
  row of the file as displayed, column 0 its left column. Values are in
  ``[0, 1]`` for integer files. No colour transform is applied on load or save
  (sRGB encoding and decoding is the caller's job).
- **uv** origin is the BOTTOM-left of the texture image as displayed
  (OpenGL/OBJ convention), whatever the file format; glTF's top-left uvs are
  flipped (``v -> 1 - v``) on load.
- **Meshes** come back as `jaxnm.geometry.Mesh` with float32 positions (V, 3),
  int32 faces (F, 3), float32 uv (V, 2) or None, and float32 unit normals (V, 3).
"""

from __future__ import annotations

import base64
import contextlib
import copy
import io
import itertools
import json
import os
import re
import struct
import tempfile
import urllib.parse
import warnings
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import png

from .geometry import Mesh, check_mesh_arrays, vertex_normals
from .textures import NormalMapOptions, encode_normal_map, quantize

if TYPE_CHECKING:  # trimesh (with scipy, ~45 MB) is imported when a mesh file is read
    import trimesh

__all__ = [
    "JaxnmWarning", "load_mesh", "load_texture", "load_image_float", "save_png", "save_aovs",
    "load_aovs", "load_json", "save_json", "save_loss_plot", "write_fit_outputs",
    "write_fit_renders", "atomic_write", "writable", "unfinished_writes", "PathLike",
    "MESH_EXTENSIONS", "TEXTURE_EXTENSIONS", "IMAGE_EXTENSIONS", "save_obj", "save_normal_map_npz",
    "save_figure_grid", "check_tangent_normal_map", "INWARD_Z", "INWARD_SHARE",
    "load_gltf_normal_map", "save_glb",
]

PathLike = str | os.PathLike

MESH_EXTENSIONS = (".obj", ".ply", ".gltf", ".glb", ".stl", ".off")
TEXTURE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".npy", ".npz")
IMAGE_EXTENSIONS = TEXTURE_EXTENSIONS + (".exr",)

_CHANNEL_NAMES = {1: "grayscale", 2: "grayscale+alpha", 3: "RGB", 4: "RGBA"}


_vertex_normals_jit = jax.jit(vertex_normals, static_argnames="weighting")


class JaxnmWarning(UserWarning):
    """Something in an input file was repaired or guessed (e.g. normals computed)."""


_TEMPORARY = itertools.count()


@contextlib.contextmanager
def atomic_write(path: PathLike):
    """Write ``path`` atomically: yields a binary file open on a temporary name in the same
    folder (``.NAME.PID-N.tmp``), which replaces ``path`` (`os.replace`) once the block has
    finished; if it raises (a ``KeyboardInterrupt`` included), the temporary file is
    removed and ``path`` is left as it was. Readers never see a part of a file, whenever
    the writer is stopped. Parent directories are created. A ``path`` that is a folder, or
    whose parent is a file, is refused before anything is written (`writable`)."""
    p = writable(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}-{next(_TEMPORARY)}.tmp")
    try:
        with open(tmp, "xb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())  # the data is on disk before the name points to it
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def writable(path: PathLike, *, folder: bool = False) -> Path:
    """``path`` as a `Path`, or an `OSError` naming it where nothing could be written there:
    a file's name that is a folder (``IsADirectoryError``), a folder's name (``folder``)
    that is a file, or a parent that is a file (``NotADirectoryError``), or a folder that
    takes no new file (read-only, no permission: tried with a nameless temporary file).
    Missing parents are fine (the writers make them). What a command checks before its
    work, so that a wrong output name is not found after it."""
    p = Path(os.fspath(path))
    if folder and p.exists() and not p.is_dir():
        raise NotADirectoryError(f"{p}: is a file, not a folder")
    if not folder and p.is_dir():
        raise IsADirectoryError(f"{p}: is a folder; name the file to write")
    nearest = next(q for q in ((p, *p.parents) if folder else p.parents) if q.exists())
    if not nearest.is_dir():
        raise NotADirectoryError(f"{p}: {nearest} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=nearest):
            pass
    except OSError as e:
        raise type(e)(f"{p}: cannot write in {nearest}: {e.strerror or e}") from None
    return p


def unfinished_writes(folder: PathLike) -> list[Path]:
    """The temporary files of this process's `atomic_write` blocks in ``folder`` that have
    not finished: what a process that ends at once (``os._exit``) removes first."""
    return sorted(Path(os.fspath(folder)).glob(f".*.{os.getpid()}-*.tmp"))


# ----------------------------------------------------------------------------- common


def _existing_file(path: PathLike) -> Path:
    """``path`` as a `Path`, or FileNotFoundError / ValueError naming it."""
    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    if not p.is_file():
        raise ValueError(f"{p}: not a regular file")
    return p


def _output_file(path: PathLike, suffix: str, writer: str, kind: str) -> Path:
    """``path`` as a `Path`, or a ValueError naming it where its name does not end in
    ``suffix``: what each ``save_*`` writes is read back by its extension."""
    p = Path(os.fspath(path))
    if p.suffix.lower() != suffix:
        raise ValueError(f"{p}: {writer} writes {kind} files; the name must end in {suffix}")
    return p


def _check_extension(p: Path, allowed: tuple[str, ...], what: str) -> str:
    ext = p.suffix.lower()
    if ext not in allowed:
        raise ValueError(f"{p}: unsupported {what} format {ext or '(no extension)'!r}; "
                         f"supported: {', '.join(allowed)}")
    return ext


def _parse_json_text(text: str | bytes, source: str) -> Any:
    """``json.loads`` with errors naming ``source`` and the line and column."""
    try:
        if isinstance(text, bytes):
            text = text.decode("utf-8-sig")
        return json.loads(text)
    except UnicodeDecodeError as e:
        raise ValueError(f"{source}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{source}: invalid JSON at line {e.lineno}, column {e.colno}: "
                         f"{e.msg}") from None


def load_json(path: PathLike) -> dict:
    """The JSON object in ``path`` (a dict); errors name the file, and the line and
    column of a syntax error."""
    p = _existing_file(path)
    data = _parse_json_text(p.read_bytes(), str(p))
    if not isinstance(data, dict):
        raise ValueError(f"{p}: expected a JSON object {{...}} at the top level, got "
                         f"{type(data).__name__}")
    return data


# ----------------------------------------------------------------------------- meshes


def load_mesh(path: PathLike, *, require_uv: bool = False,
              normals: str = "file_or_angle") -> Mesh:
    """Load a triangle mesh (OBJ, PLY, glTF/GLB, STL, OFF) as a `Mesh`.

    Vertices are not merged: a vertex at a uv seam stays two vertices. PLY, OFF,
    STL and glTF keep the file's vertex order (an STL triangle has its own three
    vertices). OBJ indexes positions, uvs and normals separately, so each distinct
    ``v/vt/vn`` corner becomes a vertex, sorted by its ``v`` index (vertices no
    face uses are dropped). A scene with several meshes (glTF nodes, OBJ
    ``usemtl`` groups) is concatenated in trimesh's scene-graph order, which is not
    always the file's, with the node transforms applied (normals by the inverse
    transpose; a mirroring transform reverses the winding so that counter-clockwise
    stays front). Polygons are triangulated; degenerate triangles are kept.

    **uv orientation.** uvs are returned with the origin at the bottom-left of
    the image for every format. OBJ and PLY already use that convention. glTF
    puts the origin at the top-left; trimesh (5.x, ``exchange/gltf``) flips it
    on load with ``uv[:, 1] = 1 - uv[:, 1]``, but only for primitives that have a
    material; for a primitive without one it silently drops ``TEXCOORD_0``. This
    function gives every primitive a bare material before trimesh parses the
    file, so glTF uvs are always loaded and always flipped (tested on a
    hand-written glTF).

    **Arguments:**
    - `path`: the mesh file. Extensions: .obj .ply .gltf .glb .stl .off.
    - `require_uv`: raise if the mesh has no texture coordinates.
    - `normals`: ``"file_or_angle"`` uses the file's vertex normals
      (renormalised; zero-length or non-finite ones are replaced by computed
      ones with a `JaxnmWarning`) and computes angle-weighted normals with a
      `JaxnmWarning` where the file has none. ``"angle"`` or ``"area"`` always
      recompute them with `jaxnm.geometry.vertex_normals`. Computed normals are those
      of the surface with the vertices at one position joined, so that an STL's
      separate triangles or an OBJ's uv seams are shaded smoothly, not creased.

    **Tangents.** A glTF primitive's ``TANGENT`` attribute (``xyz`` and the sign
    ``w``, the bitangent being ``w * cross(N, T)``, pointing to the top of the
    image) becomes the mesh's per-corner ``tangents`` (``tangent_source="file"``),
    which the ``"vertex"`` frame uses as glTF prescribes; without it, the frame
    computes MikkTSpace tangents. The sign needs no change for the flipped uvs:
    glTF defines it against the image's "up", which is jaxnm's +v.

    **Materials** are not read; `load_gltf_normal_map` reads a glTF file's normal map.

    **Returns:** a `Mesh` of jax arrays; ``uv`` is None if the file has none.

    **Raises:** `FileNotFoundError` for a missing file; `ValueError` (message
    starting with the path) for an unsupported extension, an unparsable file,
    no faces, NaN/inf positions or uvs, out-of-range face indices, or missing
    uvs when ``require_uv``.
    """
    if normals not in ("file_or_angle", "angle", "area"):
        raise ValueError(f"load_mesh: unknown normals={normals!r}; use 'file_or_angle', "
                         f"'angle' or 'area'")
    p = _existing_file(path)
    ext = _check_extension(p, MESH_EXTENSIONS, "mesh")
    src = str(p)
    scene = _load_scene(p, ext)
    pos, faces, uv, file_n, has_n, tangents = _concatenate_scene(scene, src)

    pos = pos.astype(np.float32)
    check_mesh_arrays(pos, faces, source=src)  # before any normal is computed from them
    faces = faces.astype(np.int32)
    if uv is not None:
        uv = uv.astype(np.float32)
        check_mesh_arrays(pos, faces, uv, source=src)
    elif require_uv:
        hint = (" STL and OFF files cannot store uv; use OBJ, PLY or glTF."
                if ext in (".stl", ".off") else
                " Unwrap it and export it with uvs (OBJ 'vt', PLY s/t, glTF TEXCOORD_0).")
        raise ValueError(f"{src}: the mesh has no texture coordinates (uv); normal mapping "
                         f"needs them.{hint}")

    n = _resolve_normals(pos, faces, file_n, has_n, normals, src,
                         partial=scene.metadata.get("jaxnm_partial", {}).get("normals"))
    check_mesh_arrays(pos, faces, uv, n, source=src)
    if tangents is not None:
        tangents = _file_tangents(tangents, src)
    return Mesh(positions=jnp.asarray(pos), faces=jnp.asarray(faces),
                uv=None if uv is None else jnp.asarray(uv), normals=jnp.asarray(n),
                tangents=tangents, tangent_source=None if tangents is None else "file")


def _file_tangents(tangents: np.ndarray, src: str) -> jax.Array:
    """A file's per-corner tangents (..., 4) as unit xyz and a sign w of +-1, float32."""
    if not np.all(np.isfinite(tangents)):
        raise ValueError(f"{src}: TANGENT contains NaN or infinite values")
    xyz = tangents[..., :3]
    xyz = xyz / np.maximum(np.linalg.norm(xyz, axis=-1, keepdims=True), 1e-30)
    w = np.where(tangents[..., 3:] < 0, -1.0, 1.0)
    return jnp.asarray(np.concatenate([xyz, w], -1), jnp.float32)


def save_obj(path: PathLike, mesh: Mesh) -> None:
    """Write ``mesh`` as a Wavefront OBJ, atomically (`atomic_write`): ``v``, and ``vt`` and
    ``vn`` where it has uvs and normals (origin of the uvs at the bottom left, as OBJ's),
    one ``f v/vt/vn`` corner per vertex index, counter-clockwise as ``mesh.faces``. Read
    back by `load_mesh` (which orders vertices by position index: the same vertices)."""
    p = _output_file(path, ".obj", "save_obj", "OBJ")
    pos = np.asarray(mesh.positions, np.float64)
    faces = np.asarray(mesh.faces, np.int64) + 1
    parts = ["# jaxnm\n", "".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in pos)]
    corner = "{0}"
    if mesh.uv is not None:
        parts.append("".join(f"vt {u:.9g} {v:.9g}\n" for u, v in np.asarray(mesh.uv, np.float64)))
        corner += "/{0}"
    if mesh.normals is not None:
        parts.append("".join(f"vn {x:.9g} {y:.9g} {z:.9g}\n"
                             for x, y, z in np.asarray(mesh.normals, np.float64)))
        corner += "/{0}" if mesh.uv is not None else "//{0}"
    parts.append("".join("f " + " ".join(corner.format(int(i)) for i in f) + "\n"
                         for f in faces))
    with atomic_write(p) as fh:
        fh.write("".join(parts).encode())


def save_glb(path: PathLike, mesh: Mesh, normal_map=None) -> None:
    """Write ``mesh`` as a binary glTF (GLB), atomically (`atomic_write`), by trimesh's
    exporter: positions, vertex normals, uvs (turned to glTF's origin at the image's top
    left) and, with ``normal_map``, that map as the material's normal texture (an 8-bit PNG,
    unsigned, +green up). glTF viewers decode it in MikkTSpace over these normals and uvs,
    so ``normal_map`` is a map for the ``"vertex"`` frame with computed MikkTSpace tangents:
    unit tangent-space normals ``(H, W, 3)``, row 0 at the top. Read back by `load_mesh`
    and `load_gltf_normal_map`."""
    import trimesh
    from PIL import Image
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    p = _output_file(path, ".glb", "save_glb", "GLB")
    tm = trimesh.Trimesh(np.asarray(mesh.positions, np.float64), np.asarray(mesh.faces),
                         vertex_normals=None if mesh.normals is None
                         else np.asarray(mesh.normals, np.float64), process=False)
    if normal_map is not None and mesh.uv is None:
        raise ValueError(f"{p}: save_glb: a normal map needs the mesh's uvs; this mesh has none")
    if mesh.uv is not None:
        texture = None
        if normal_map is not None:
            codes = quantize(encode_normal_map(np.asarray(normal_map, np.float32),
                                               encoding="unsigned", green="up", bits=8), 8)
            texture = Image.fromarray(np.round(np.asarray(codes) * 255).astype(np.uint8))
        tm.visual = TextureVisuals(uv=np.asarray(mesh.uv, np.float64),
                                   material=PBRMaterial(normalTexture=texture))
    data = tm.export(file_type="glb")
    with atomic_write(p) as fh:
        fh.write(data)


def _load_scene(p: Path, ext: str) -> trimesh.Scene:
    """Parse ``p`` with trimesh into a Scene, with errors naming the file."""
    import trimesh

    data = p.read_bytes()
    kwargs: dict[str, Any] = {"process": False}
    partial = {}
    if ext == ".obj":
        data, partial = _clean_obj(data, str(p))
        # materials are not used; skipping them avoids decoding texture images and
        # keeps the uvs (trimesh keeps them on a material-less OBJ mesh)
        kwargs["skip_materials"] = True
        # NOT maintain_order=True: for OBJ it keeps one uv per position (the median
        # of the vt's used with it) and so merges the vertices of uv seams
    elif ext == ".gltf":
        data = _gltf_for_geometry(data, str(p))
    elif ext == ".glb":
        data = _glb_for_geometry(data, str(p))
    try:
        scene = trimesh.load_scene(io.BytesIO(data), file_type=ext[1:],
                                   resolver=trimesh.resolvers.FilePathResolver(str(p)),
                                   **kwargs)
    except Exception as e:  # trimesh raises anything from IndexError to KeyError
        bad = _obj_malformed_line(data, p) if ext == ".obj" else None
        raise ValueError(bad or f"{p}: trimesh cannot parse this {ext[1:].upper()} file "
                                f"({type(e).__name__}: {e})") from None
    if ext == ".obj" and any(np.shape(getattr(g, "vertices", np.zeros((0, 3))))[-1:] != (3,)
                             for g in scene.geometry.values()):
        # (trimesh reads 'v' lines of two numbers as 2-D positions)
        raise ValueError(_obj_malformed_line(data, p)
                         or f"{p}: trimesh read positions that are not 3-D")
    scene.metadata["jaxnm_partial"] = partial  # (said where none is left)
    return scene


def _concatenate_scene(scene: trimesh.Scene, src: str):
    """(positions f64, faces i64, uv f64 | None, file normals f64, bool mask of the
    vertices that have file normals) of all triangle meshes in ``scene``, in world
    space."""
    import trimesh

    parts, skipped = [], 0
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        geom = scene.geometry[name]
        if isinstance(geom, trimesh.Trimesh) and len(geom.faces) > 0:
            parts.append((geom, np.asarray(transform, np.float64)))
        else:
            skipped += 1
    if not parts:
        found = " (it holds only points or lines)" if skipped else ""
        raise ValueError(f"{src}: the mesh has no faces{found}")
    if skipped:
        warnings.warn(f"{src}: ignored {skipped} geometries without triangles (points or "
                      f"lines)", JaxnmWarning, stacklevel=3)

    pos, faces, uvs, nrm, has_n, tans, offset = [], [], [], [], [], [], 0
    for geom, t in parts:
        # trimesh computes vertex normals lazily and caches them under the same key
        # as the normals it was given by the loader, so the file had normals iff the
        # key is in the cache before anything reads `vertex_normals` (trimesh's own
        # OBJ exporter uses the same test)
        had_normals = "vertex_normals" in geom._cache
        v = np.array(geom.vertices, np.float64)
        f = np.array(geom.faces, np.int64)
        n = (np.array(geom._cache["vertex_normals"], np.float64) if had_normals
             else np.zeros_like(v))
        uv = getattr(geom.visual, "uv", None)
        if uv is not None:
            uv = np.array(uv, np.float64)
            if uv.ndim != 2 or uv.shape[0] != len(v) or uv.shape[1] < 2:
                raise ValueError(f"{src}: {uv.shape[0]} texture coordinates for {len(v)} "
                                 f"vertices")
            uv = uv[:, :2]
        tan = getattr(geom, "vertex_attributes", {}).get("_TANGENT")
        if tan is not None:
            tan = np.array(tan, np.float64)
            if tan.shape != (len(v), 4):
                raise ValueError(f"{src}: TANGENT must be one VEC4 per vertex, got shape "
                                 f"{tan.shape}")
        if not np.allclose(t, np.eye(4)):
            lin = t[:3, :3]
            det = np.linalg.det(lin)
            if not np.isfinite(det) or abs(det) < 1e-12:
                raise ValueError(f"{src}: a scene node has a singular transform")
            v = v @ lin.T + t[:3, 3]
            n = n @ np.linalg.inv(lin)  # inverse transpose, as row vectors
            if tan is not None:  # a direction; a mirror flips cross(N, T), hence the sign
                tan = np.concatenate([tan[:, :3] @ lin.T, tan[:, 3:] * np.sign(det)], 1)
            if det < 0:
                f = f[:, ::-1]
        tans.append(None if tan is None else tan[f])  # per face corner
        pos.append(v)
        faces.append(f + offset)
        uvs.append(uv)
        nrm.append(n)
        has_n.append(np.full(len(v), had_normals))
        offset += len(v)

    with_t = sum(x is not None for x in tans)
    tangents = np.concatenate(tans) if with_t == len(tans) else None
    if 0 < with_t < len(tans):
        warnings.warn(f"{src}: only {with_t} of {len(tans)} meshes have TANGENT; ignoring "
                      f"them all (MikkTSpace tangents are computed instead)", JaxnmWarning,
                      stacklevel=3)
    uv_all = _joined_uvs(uvs, scene.metadata.get("jaxnm_partial", {}).get("uv"), src)
    return (np.concatenate(pos), np.concatenate(faces), uv_all, np.concatenate(nrm),
            np.concatenate(has_n), tangents)


def _joined_uvs(uvs: list, partial: str | None, src: str) -> np.ndarray | None:
    """The meshes' uvs (each (V_i, 2) or None) joined; None, with a warning, where some
    meshes have none, or where an OBJ's faces had them in part (``partial``, `_clean_obj`'s
    words) and trimesh dropped them."""
    with_uv = sum(u is not None for u in uvs)
    if with_uv == len(uvs):
        return np.concatenate(uvs)
    if with_uv:
        warnings.warn(f"{src}: only {with_uv} of {len(uvs)} meshes have texture coordinates; "
                      f"ignoring them all", JaxnmWarning, stacklevel=4)
    elif partial:
        warnings.warn(f"{src}: {partial}; ignoring them all", JaxnmWarning, stacklevel=4)
    return None


def _resolve_normals(pos: np.ndarray, faces: np.ndarray, file_n: np.ndarray,
                     has_n: np.ndarray, mode: str, src: str,
                     partial: str | None = None) -> np.ndarray:
    """Final (V, 3) float32 unit normals: the file's where ``has_n`` (and usable).
    ``partial``: `_clean_obj`'s words for an OBJ whose faces had normals in part only."""
    if mode != "file_or_angle":
        return _welded_normals(pos, faces, mode).astype(np.float32)
    absent = ~has_n
    length = np.linalg.norm(file_n, axis=1)
    bad = ~absent & ~(np.isfinite(length) & (length > 1e-12))
    out = file_n / np.where(absent | bad, 1.0, length)[:, None]
    fill = absent | bad
    if fill.any():
        computed = _welded_normals(pos, faces, "angle").astype(np.float64)
        out[fill] = computed[fill]
    if absent.all():
        why = f"{partial}, which were dropped" if partial else "no vertex normals in the file"
        warnings.warn(f"{src}: {why}; computed angle-weighted normals", JaxnmWarning,
                      stacklevel=3)
    elif absent.any():
        warnings.warn(f"{src}: no vertex normals in the file for {int(absent.sum())} of "
                      f"{len(absent)} vertices; computed angle-weighted normals for them",
                      JaxnmWarning, stacklevel=3)
    if bad.any():
        warnings.warn(f"{src}: {int(bad.sum())} vertex normals in the file are zero-length or "
                      f"not finite (first: vertex {int(np.argmax(bad))}); replaced them by "
                      f"computed angle-weighted normals", JaxnmWarning, stacklevel=3)
    return out.astype(np.float32)


def _welded_normals(pos: np.ndarray, faces: np.ndarray, weighting: str) -> np.ndarray:
    """`vertex_normals` of the surface with the vertices at one position joined, given to
    each of them: a mesh split at uv seams (OBJ corners) or into separate triangles (an STL
    file) is shaded as the one surface it is, not creased along its splits. Positions are
    joined where their float32 bits agree (-0 as +0), found by a sort on two integer keys
    (several times faster than ``np.unique(axis=0)`` on a large STL)."""
    key = np.ascontiguousarray(np.asarray(pos, np.float32) + np.float32(0)).view(np.uint32)
    xy = (key[:, 0].astype(np.uint64) << np.uint64(32)) | key[:, 1]
    order = np.lexsort((key[:, 2], xy))
    ordered = key[order]
    first = np.ones(len(order), bool)  # the first vertex of each position, in sorted order
    first[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    inverse = np.empty(len(order), np.int64)
    inverse[order] = np.cumsum(first) - 1
    return _vertex_normals(pos[order[first]], inverse[faces], weighting)[inverse]


def _vertex_normals(pos: np.ndarray, faces: np.ndarray, weighting: str) -> np.ndarray:
    """`vertex_normals`, jitted on arrays padded to power-of-two sizes so that meshes of
    similar size share one XLA compilation. Padding: vertices at the origin used only
    by padding faces ``(V, V, V)``, which are degenerate and touch no real vertex."""
    v, f = len(pos), len(faces)
    vb, fb = max(64, 1 << v.bit_length()), max(64, 1 << (f - 1).bit_length())  # vb > v
    pos_p = np.zeros((vb, 3), np.float32)
    pos_p[:v] = pos
    faces_p = np.full((fb, 3), v, np.int32)
    faces_p[:f] = faces
    return np.asarray(_vertex_normals_jit(pos_p, faces_p, weighting=weighting))[:v]


_OBJ_COMMENT = re.compile(rb"#[^\n]*")
_OBJ_FACE_LINE = re.compile(rb"\nf[ \t]([^\n]*)")
_OBJ_KINDS = (("v", "vertex"), ("vt", "texture coordinate"), ("vn", "normal"))


def _clean_obj(data: bytes, src: str) -> tuple[bytes, dict[str, str]]:
    """OBJ text without comments, after checking that every face index exists, and, for
    ``"uv"`` (``"normals"``) where the face corners have ``vt`` (``vn``) indices in part only
    (trimesh then drops those of every mesh that mixes them), ``"only K of N face corners
    have texture coordinates (normals) (the first without: line L)"``.

    trimesh crashes with an IndexError on a bad ``v`` index, silently drops all
    uvs (normals) on a bad ``vt`` (``vn``) index and reads index 0 as 1, so check
    them first; and it cannot parse a comment after a face (``f 1 2 3 # ...``).
    """
    data = _OBJ_COMMENT.sub(b"", data)
    text = b"\n" + data.replace(b"\r", b"")
    indices = _obj_corner_indices(b" ".join(_OBJ_FACE_LINE.findall(text)))
    for (kind, name), idx in zip(_OBJ_KINDS, indices):
        n = text.count(b"\n" + kind.encode() + b" ")  # the lines that trimesh reads
        bad = (idx == 0) | (idx > n) | (idx < -n)
        if bad.any():
            i = int(idx[np.argmax(bad)])
            raise ValueError(f"{src}: line {_obj_face_line_with(text, kind, i)}: a face refers to "
                             f"{name} {i}, but the file has {n} ('{kind}' lines; indices are "
                             f"1..{n} or -{n}..-1)")
    partial = {}
    for k, key, what in ((1, "uv", "texture coordinates"), (2, "normals", "normals")):
        if 0 < len(indices[k]) < len(indices[0]):
            partial[key] = (f"only {len(indices[k])} of {len(indices[0])} face corners have "
                            f"{what} (the first without: line "
                            f"{_obj_face_line_without(text, k)})")
    return data, partial


def _obj_face_line_without(text: bytes, k: int) -> int | str:
    """Line number of the first face with a corner that has no ``vt`` (``k`` = 1) or ``vn``
    (``k`` = 2) index."""
    return _obj_first_face_line(text, k, lambda x: not x)


_OBJ_COUNTS = {b"v": (3, 7, "x y z"), b"vt": (1, 3, "u [v [w]]"), b"vn": (3, 3, "x y z")}


def _obj_malformed_line(data: bytes, src) -> str | None:
    """For an OBJ file trimesh could not read: ``"src: line N: ..."`` naming the first ``v``,
    ``vt`` or ``vn`` line that is not made of the numbers it needs, or None if every such
    line is fine. A loop over the lines, run only when reading has failed."""
    for lineno, line in enumerate(data.replace(b"\r", b"").split(b"\n"), 1):
        words = line.split()
        if not words or words[0] not in _OBJ_COUNTS:
            continue
        lo, hi, form = _OBJ_COUNTS[words[0]]
        try:
            numbers = [float(w) for w in words[1:]]
        except ValueError:
            numbers = None
        if numbers is None or not lo <= len(numbers) <= hi:
            shown = line.decode(errors="replace").strip()
            return (f"{src}: line {lineno}: {shown!r}: a '{words[0].decode()}' line holds "
                    f"{form} (numbers)")
    return None


def _obj_corner_indices(corners: bytes) -> list[np.ndarray]:
    """The v, vt and vn indices in whitespace-separated ``v[/[vt][/vn]]`` face corners,
    parsed with array operations (a Python loop takes seconds on large files)."""
    b = np.frombuffer(corners, np.uint8)
    digit = (b >= ord("0")) & (b <= ord("9"))
    num = digit | (b == ord("-"))
    first = np.flatnonzero(num & ~np.r_[False, num[:-1]])
    last = np.flatnonzero(num & ~np.r_[num[1:], False])
    run = np.cumsum(num & ~np.r_[False, num[:-1]]) - 1  # number id of each character
    pos = np.flatnonzero(digit)
    weights = (b[pos] - ord("0")) * 10.0 ** (last[run[pos]] - pos)
    value = np.bincount(run[pos], weights, minlength=len(first))
    value = np.where(b[first] == ord("-"), -value, value)
    slash = np.cumsum(b == ord("/"))
    blank = np.maximum.accumulate(np.where(np.isin(b, list(b" \t\n")), np.arange(len(b)), -1))
    slot = slash[first] - np.where(blank[first] >= 0, slash[np.maximum(blank[first], 0)], 0)
    return [value[slot == k] for k in range(3)]


def _obj_face_line_with(text: bytes, kind: str, index: int) -> int | str:
    """Line number of the first face using ``index`` for ``kind`` (for error messages)."""
    k = [name for name, _ in _OBJ_KINDS].index(kind)
    return _obj_first_face_line(
        text, k, lambda x: x.lstrip(b"-").isdigit() and int(x) == index)


def _obj_first_face_line(text: bytes, k: int, test) -> int | str:
    """Line number of the first face with a corner whose index ``k`` (0: ``v``, 1: ``vt``,
    2: ``vn``; b"" where the corner has none) passes ``test``, or "?" (a loop over the
    lines, for error messages only)."""
    for lineno, line in enumerate(text[1:].split(b"\n"), 1):
        if line.startswith((b"f ", b"f\t")):
            for corner in line.split()[1:]:
                parts = corner.split(b"/")
                if test(parts[k] if len(parts) > k else b""):
                    return lineno
    return "?"


# glTF: trimesh reads TEXCOORD_0 only for primitives with a material (and then
# flips v), and decodes every texture image of the file. jaxnm needs the geometry
# alone, so it hands trimesh a copy of the JSON in which every material is bare,
# every primitive has one, and there are no images.

_GLTF_FLOAT = 5126
_GLTF_UNSUPPORTED_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression",
                                "KHR_mesh_quantization")


def _gltf_tree_for_geometry(tree: Any, src: str) -> dict:
    if not isinstance(tree, dict):
        raise ValueError(f"{src}: not a glTF file (the JSON is not an object)")
    used = set(tree.get("extensionsUsed", [])) | set(tree.get("extensionsRequired", []))
    for ext in _GLTF_UNSUPPORTED_EXTENSIONS:
        if ext in used:
            raise ValueError(f"{src}: uses the glTF extension {ext}, which jaxnm cannot read; "
                             f"re-export without compression or quantisation")
    tree = copy.deepcopy(tree)
    accessors = tree.get("accessors", [])
    bare = len(tree.get("materials", []))
    tree["materials"] = [{} for _ in range(bare + 1)]
    for key in ("textures", "images", "samplers"):
        tree.pop(key, None)
    try:
        for mesh in tree.get("meshes", []):
            for prim in mesh.get("primitives", []):
                prim.setdefault("material", bare)
                attrs = prim.get("attributes", {})
                if "TANGENT" in attrs:  # trimesh keeps only custom ("_") attributes
                    attrs["_TANGENT"] = attrs.pop("TANGENT")
                for attr in ("POSITION", "NORMAL", "TEXCOORD_0", "_TANGENT"):
                    if attr in prim.get("attributes", {}):
                        ctype = accessors[prim["attributes"][attr]].get("componentType")
                        if ctype != _GLTF_FLOAT:
                            raise ValueError(f"{src}: {attr} is stored as componentType {ctype}; "
                                             f"jaxnm reads float ({_GLTF_FLOAT}) only")
    except (AttributeError, TypeError, IndexError, KeyError) as e:
        raise ValueError(f"{src}: malformed glTF meshes or accessors ({type(e).__name__}: "
                         f"{e})") from None
    return tree


def _gltf_for_geometry(data: bytes, src: str) -> bytes:
    tree = _gltf_tree_for_geometry(_parse_json_text(data, src), src)
    return json.dumps(tree).encode()


def _glb_chunks(data: bytes, src: str) -> tuple[bytes, bytes]:
    """A GLB file's JSON chunk and the bytes after it (the binary chunk, if any, with its
    header)."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError(f"{src}: not a GLB file (it does not start with 'glTF')")
    version, _ = struct.unpack_from("<II", data, 4)
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    if version != 2 or json_type != b"JSON" or 20 + json_len > len(data):
        raise ValueError(f"{src}: not a valid glTF 2.0 binary (version {version}, first chunk "
                         f"{json_type!r} of {json_len} bytes)")
    return data[20:20 + json_len], data[20 + json_len:]


def _glb_for_geometry(data: bytes, src: str) -> bytes:
    text, rest = _glb_chunks(data, src)
    tree = _gltf_tree_for_geometry(_parse_json_text(text, src), src)
    chunk = json.dumps(tree).encode()
    chunk += b" " * (-len(chunk) % 4)  # chunks are 4-byte aligned, JSON padded with spaces
    body = struct.pack("<I4s", len(chunk), b"JSON") + chunk + rest
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def load_gltf_normal_map(path: PathLike) -> tuple[np.ndarray, NormalMapOptions] | None:
    """The tangent-space normal map of a glTF or GLB file's materials and how glTF says to
    read it, or None if no primitive's material has one.

    glTF stores it unsigned, +green towards the image's top, in the MikkTSpace frame of the
    vertex normals and uvs (or of the file's ``TANGENT`` attribute): read it with
    `load_mesh`'s uvs (origin at the bottom left) and ``frame="vertex"``. The options carry
    ``normalTexture.scale`` as the strength, the sampler's wrap (``wrapS``) and its filter:
    ``"nearest"`` or ``"bilinear"`` for a NEAREST or LINEAR ``minFilter``, else (mipmaps, or
    none named) ``"trilinear"``. jaxnm renders a scene with one map and one wrap: a file
    whose primitives name different normal textures, or leave some without one, gives None
    with a `JaxnmWarning`, as does a map read through a ``texCoord`` other than 0 or moved
    by ``KHR_texture_transform``; a sampler that wraps its axes differently warns and uses
    ``wrapS``.

    **Returns:** ``(image, options)``: the texture as `load_texture` gives it (float32
    ``(H, W, 3)`` in [0, 1], row 0 at the top) and its `NormalMapOptions`.

    **Raises:** `ValueError` naming the file for a texture that cannot be found or read
    (PNG and JPEG images are read; KTX2 and WebP, through their extensions, are not).
    """
    p = _existing_file(path)
    ext = _check_extension(p, (".gltf", ".glb"), "glTF")
    src = str(p)
    tree, binary = _gltf_parts(p.read_bytes(), ext, src)
    used = _gltf_normal_textures(tree, src)
    if not used:
        return None
    ref = used[0]
    unused = _gltf_map_unused(used)
    if unused:
        warnings.warn(f"{src}: {unused}, so it is not used", JaxnmWarning, stacklevel=2)
        return None
    try:
        texture = tree["textures"][ref["index"]]
        if "source" not in texture:
            raise ValueError(f"{src}: the normal texture is stored only through the extensions "
                             f"{sorted(texture.get('extensions', {}))}; jaxnm reads PNG and "
                             "JPEG images")
        image = tree["images"][texture["source"]]
        data, kind = _gltf_image_bytes(tree, image, binary, p)
        sampler = tree["samplers"][texture["sampler"]] if "sampler" in texture else {}
    except (KeyError, IndexError, TypeError) as e:
        raise ValueError(f"{src}: malformed glTF normal texture ({type(e).__name__}: "
                         f"{e})") from None
    where = f"{src}: normal texture {image.get('uri') or image.get('name') or ''}".rstrip()
    texels, bits = _decode_image(data, kind, where)
    scale = ref.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not abs(scale) < np.inf:
        raise ValueError(f"{src}: normalTexture.scale must be a finite number, got {scale!r}")
    return _select_channels(texels, 3, where), NormalMapOptions(
        encoding="unsigned", channels=3, green="up", strength=float(scale), space="tangent",
        bits=bits if bits in (8, 16) else 8, **_gltf_sampling(sampler, src))


def _gltf_map_unused(used: list[dict]) -> str | None:
    """Why the normal textures ``used`` (`_gltf_normal_textures`) give jaxnm no map, or None."""
    ref = used[0]
    if len(used) > 1:
        return (f"its primitives use {len(used)} normal textures (or some none); jaxnm renders "
                "a scene with one map")
    if ref.get("texCoord", 0) != 0:
        return (f"the normal texture is read through TEXCOORD_{ref['texCoord']}; jaxnm reads "
                "TEXCOORD_0 only")
    if "KHR_texture_transform" in ref.get("extensions", {}):
        return "the normal texture is moved by KHR_texture_transform, which jaxnm does not apply"
    return None


#: glTF sampler codes: wrap modes, and the minifying filters without mipmaps.
_GLTF_WRAPS = {10497: "repeat", 33071: "clamp", 33648: "mirror"}
_GLTF_FILTERS = {9728: "nearest", 9729: "bilinear"}


def _gltf_sampling(sampler: dict, src: str) -> dict:
    """`NormalMapOptions`' ``wrap`` and ``filter`` for a glTF sampler."""
    wrap_s, wrap_t = sampler.get("wrapS", 10497), sampler.get("wrapT", 10497)
    if wrap_s not in _GLTF_WRAPS or wrap_t not in _GLTF_WRAPS:
        raise ValueError(f"{src}: the normal texture's sampler has an unknown wrap "
                         f"({wrap_s}, {wrap_t}); glTF's are {sorted(_GLTF_WRAPS)}")
    if wrap_t != wrap_s:
        warnings.warn(f"{src}: the normal texture wraps u {_GLTF_WRAPS[wrap_s]} and v "
                      f"{_GLTF_WRAPS[wrap_t]}; jaxnm wraps both as u does", JaxnmWarning,
                      stacklevel=3)
    return {"wrap": _GLTF_WRAPS[wrap_s],
            "filter": _GLTF_FILTERS.get(sampler.get("minFilter"), "trilinear")}


def _gltf_parts(data: bytes, ext: str, src: str) -> tuple[dict, bytes | None]:
    """A glTF file's JSON tree and, for a GLB, its binary chunk (None if it has none)."""
    binary = None
    if ext == ".gltf":
        tree = _parse_json_text(data, src)
    else:
        text, rest = _glb_chunks(data, src)
        tree = _parse_json_text(text, src)
        if len(rest) >= 8 and rest[4:8] == b"BIN\0":
            binary = rest[8:8 + struct.unpack_from("<I", rest)[0]]
    if not isinstance(tree, dict):
        raise ValueError(f"{src}: not a glTF file (the JSON is not an object)")
    return tree, binary


def _gltf_normal_textures(tree: dict, src: str) -> list[dict]:
    """The distinct ``normalTexture`` references of the materials the primitives use, with
    an empty one for a primitive without (so that a partly mapped mesh counts as two)."""
    refs = []
    materials = tree.get("materials", [])
    try:
        for mesh in tree.get("meshes", []):
            for prim in mesh.get("primitives", []):
                m = prim.get("material")
                ref = materials[m].get("normalTexture", {}) if m is not None else {}
                if not isinstance(ref, dict):
                    raise TypeError(f"normalTexture is {ref!r}, not an object")
                if ref not in refs:
                    refs.append(ref)
    except (AttributeError, TypeError, IndexError) as e:
        raise ValueError(f"{src}: malformed glTF materials ({type(e).__name__}: {e})") from None
    return [] if refs in ([], [{}]) else refs


def _gltf_image_bytes(tree: dict, image: dict, binary: bytes | None,
                      p: Path) -> tuple[bytes, str]:
    """An image's encoded bytes (from a data URI, a file beside ``p`` or a buffer view)
    and its extension."""
    kinds = {"image/png": ".png", "image/jpeg": ".jpg"}
    uri = image.get("uri")
    if uri is not None:
        if uri.startswith("data:"):
            head, _, body = uri.partition(",")
            return base64.b64decode(body), kinds.get(head[5:].split(";")[0], ".png")
        file = p.parent / urllib.parse.unquote(uri)
        if not file.is_file():
            raise ValueError(f"{p}: the normal texture {uri!r} is not beside it ({file})")
        return file.read_bytes(), file.suffix.lower()
    view = tree["bufferViews"][image["bufferView"]]
    buffer = tree["buffers"][view["buffer"]]
    if "uri" in buffer:
        blob, _ = _gltf_image_bytes(tree, {"uri": buffer["uri"]}, binary, p)
    elif binary is not None:
        blob = binary
    else:
        raise ValueError(f"{p}: the normal texture's buffer has no data")
    start = view.get("byteOffset", 0)
    return blob[start:start + view["byteLength"]], kinds.get(image.get("mimeType"), ".png")


# ----------------------------------------------------------------------------- images


def load_texture(path: PathLike, *, channels: int | None = None) -> tuple[np.ndarray, int]:
    """Load a texture as float32 ``(H, W, C)`` in ``[0, 1]``, IMAGE layout (row 0 = top).

    **Arguments:**
    - `path`: .png (8 or 16 bit, grayscale/RGB/RGBA, palette), .jpg/.jpeg, .npy or
      .npz (one array, or one named ``image``; float arrays are taken as they are,
      uint8/uint16 arrays scaled to [0, 1]; shape (H, W) or (H, W, C)).
    - `channels`: None keeps the file's channels. 3 accepts RGB and RGBA (alpha
      dropped) and refuses grayscale; 2 takes the first two of 2+ channels; 1
      accepts grayscale (+alpha, dropped) and takes the red channel of a colour
      image with a `JaxnmWarning`.

    **Returns:** ``(image, bits)``: ``bits`` is the sample depth of the file: 8, 16,
    or 32 for float arrays. 16-bit PNGs are decoded by jaxnm itself because
    imageio's Pillow plugin reduces 16-bit colour PNGs to 8 bits.
    """
    p = _existing_file(path)
    ext = _check_extension(p, TEXTURE_EXTENSIONS, "texture")
    image, bits = _read_image(p, ext)
    return _select_channels(image, channels, str(p)), bits


#: Decoded z below which a texel of a tangent-space map points into the surface.
INWARD_Z = -0.05
#: The share of a tangent-space map's texels (black ones left out) that may point into the
#: surface before `check_tangent_normal_map` warns.
INWARD_SHARE = 0.05


def check_tangent_normal_map(raw, *, encoding: str = "unsigned", channels: int = 3,
                             source: str = "normal map", hint: str = "") -> None:
    """Warn (`JaxnmWarning`) when ``raw``, a 3-channel tangent-space normal map as stored
    (float ``(H, W, 3)``, ``encoding`` as `jaxnm.textures.NormalMapOptions`), looks like
    another kind of map: every texel black, or more than `INWARD_SHARE` of the others
    pointing into the surface (decoded z below `INWARD_Z`). A tangent-space map's normals
    point out of the surface (z > 0); an object-space map's point every way, so about half
    of them have z < 0. Black texels (0 in every channel) are a baker's background and are
    not counted. Two-channel maps rebuild z >= 0 and are not checked. ``hint``, if given,
    ends the object-space warning: how the caller's input names an object-space map."""
    if channels != 3:
        return
    raw = np.asarray(raw, np.float32)
    black = np.all(raw == 0, axis=-1)
    if black.all():
        warnings.warn(f"{source}: every texel is black (0, 0, 0), which is no normal",
                      JaxnmWarning, stacklevel=2)
        return
    z = raw[..., 2] if encoding == "signed" else 2 * raw[..., 2] - 1
    share = float(np.count_nonzero((z < INWARD_Z) & ~black) / np.count_nonzero(~black))
    if share > INWARD_SHARE:
        warnings.warn(f"{source}: {share:.0%} of its texels point into the surface (z < 0 "
                      "once decoded), where a tangent-space map's point out of it; is it an "
                      f"object-space map?{f' ({hint})' if hint else ''}", JaxnmWarning,
                      stacklevel=2)


def load_image_float(path: PathLike) -> tuple[np.ndarray, int]:
    """Like `load_texture` (all channels) but also reads OpenEXR (.exr), e.g. target images.

    EXR is read through the OpenEXR bindings (the ``exr`` extra:
    ``pip install -e ".[exr]"``); without them an `ImportError` says so.
    """
    p = _existing_file(path)
    ext = _check_extension(p, IMAGE_EXTENSIONS, "image")
    return _read_image(p, ext)


def _read_image(p: Path, ext: str) -> tuple[np.ndarray, int]:
    """(float32 (H, W, C), bits) of any supported image file."""
    src = str(p)
    if ext in (".npy", ".npz"):
        raw = _read_array_file(p, ext)
    elif ext == ".exr":
        raw = _read_exr(p)
    else:
        return _decode_image(p.read_bytes(), ext, src)
    return _image_to_float(raw, src)


def _decode_image(data: bytes, ext: str, src: str) -> tuple[np.ndarray, int]:
    """(float32 (H, W, C), bits) of a PNG or JPEG file's bytes."""
    if not data:
        raise ValueError(f"{src}: empty file")
    if data[:8] == _PNG_SIGNATURE and len(data) > 24 and data[24] == 16:
        raw = _decode_png16(data, src)  # IHDR bit depth is byte 24
    else:
        raw = _read_pillow(data, ext, src)
    return _image_to_float(raw, src)


def _read_pillow(data: bytes, ext: str, src: str) -> np.ndarray:
    try:
        with iio.imopen(data, "r", plugin="pillow", extension=ext) as f:
            mode = f.metadata(index=0).get("mode")
            if mode not in ("1", "L", "LA", "P", "PA", "RGB", "RGBA", "CMYK", "I;16"):
                raise ValueError(f"{src}: unsupported image mode {mode!r}")
            return f.read(index=0, mode="RGB" if mode == "CMYK" else None)
    except ValueError as e:
        if str(e).startswith(src):
            raise
        raise ValueError(f"{src}: cannot read the image ({e})") from None
    except Exception as e:  # Pillow raises OSError, SyntaxError, ...
        raise ValueError(f"{src}: not an image or unreadable ({type(e).__name__}: {e})") from None


def _read_array_file(p: Path, ext: str) -> np.ndarray:
    src = str(p)
    try:
        if ext == ".npy":
            return np.load(p, allow_pickle=False)
        with np.load(p, allow_pickle=False) as z:
            names = list(z.files)
            if len(names) != 1 and "image" not in names:
                raise ValueError(f"{src}: an .npz image must hold one array or one named "
                                 f"'image'; found {names}")
            return z[names[0] if len(names) == 1 else "image"]
    except ValueError as e:
        if str(e).startswith(src):
            raise
        raise ValueError(f"{src}: cannot read the array file ({e})") from None
    except (OSError, EOFError) as e:
        raise ValueError(f"{src}: cannot read the array file ({type(e).__name__}: {e})") from None


def _read_exr(p: Path) -> np.ndarray:
    """An OpenEXR image as float32 (H, W, C), via the OpenEXR bindings (RGBA, RGB or Y)."""
    try:
        import OpenEXR
    except ImportError:
        raise ImportError(f"{p}: reading EXR images needs the OpenEXR bindings: "
                          'pip install -e ".[exr]"') from None

    src = str(p)
    try:
        with OpenEXR.File(src) as f:
            channels = f.channels()
            for name in ("RGBA", "RGB", "Y"):
                if name in channels:
                    arr = np.asarray(channels[name].pixels)
                    break
            else:
                names = sorted(channels)
                if len(names) != 1:
                    raise ValueError(f"{src}: expected RGB(A) or Y channels, found {names}")
                arr = np.asarray(channels[names[0]].pixels)
    except ValueError:
        raise
    except Exception as e:  # OpenEXR raises RuntimeError/OSError on bad files
        raise ValueError(f"{src}: not a readable OpenEXR file ({type(e).__name__}: {e})") from None
    arr = arr.astype(np.float32)
    return arr[..., None] if arr.ndim == 2 else arr


def _image_to_float(raw: np.ndarray, src: str) -> tuple[np.ndarray, int]:
    raw = np.asarray(raw)
    if raw.ndim == 2:
        raw = raw[:, :, None]
    if raw.ndim != 3 or not 1 <= raw.shape[2] <= 4:
        raise ValueError(f"{src}: expected an image of shape (H, W) or (H, W, C) with C in "
                         f"1..4, got {raw.shape}")
    if raw.shape[0] == 0 or raw.shape[1] == 0:
        raise ValueError(f"{src}: the image is empty (shape {raw.shape})")
    if raw.dtype == np.uint8 or raw.dtype == np.bool_:
        return raw.astype(np.float32) / (1.0 if raw.dtype == np.bool_ else 255.0), 8
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) / 65535.0, 16
    if np.issubdtype(raw.dtype, np.floating):
        image = raw.astype(np.float32)
        if not np.all(np.isfinite(image)):
            raise ValueError(f"{src}: the image contains NaN or infinite values")
        return image, 32
    raise ValueError(f"{src}: unsupported sample type {raw.dtype}; expected uint8, uint16 or "
                     f"float")


def _select_channels(image: np.ndarray, channels: int | None, src: str) -> np.ndarray:
    if channels is None:
        return image
    c = image.shape[2]
    if channels == 3:
        if c < 3:
            raise ValueError(f"{src}: a normal map needs 3 channels (RGB), got {c} "
                             f"({_CHANNEL_NAMES[c]})")
        return image[:, :, :3]
    if channels == 2:
        if c < 2:
            raise ValueError(f"{src}: need 2 channels, got 1 (grayscale)")
        return image[:, :, :2]
    if channels == 1:
        if c >= 3:
            warnings.warn(f"{src}: expected a grayscale image, got {c} channels "
                          f"({_CHANNEL_NAMES[c]}); using the first (red) channel",
                          JaxnmWarning, stacklevel=3)
        return image[:, :, :1]
    raise ValueError(f"load_texture: channels must be None, 1, 2 or 3, got {channels!r}")


def save_png(path: PathLike, image, *, bits: int = 8) -> None:
    """Write a float image in IMAGE layout (row 0 = top) as an 8- or 16-bit PNG.

    ``image`` is (H, W), (H, W, 1), (H, W, 2), (H, W, 3) or (H, W, 4). Values are
    clipped to [0, 1] and quantised to ``round(x * (2**bits - 1))`` (halves round
    up). No colour transform is applied: encode sRGB first if you want it.
    Parent directories are created.
    """
    p = _output_file(path, ".png", "save_png", "PNG")
    if bits not in (8, 16):
        raise ValueError(f"{p}: bits must be 8 or 16, got {bits!r}")
    img = np.asarray(image)
    if not np.issubdtype(img.dtype, np.floating):
        raise ValueError(f"{p}: save_png takes a float image in [0, 1], got dtype {img.dtype}")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or not 1 <= img.shape[2] <= 4 or img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"{p}: image must have shape (H, W) or (H, W, C) with C in 1..4 and "
                         f"H, W > 0, got {np.shape(image)}")
    if np.isnan(img).any():
        raise ValueError(f"{p}: the image to save contains NaN values")
    maxv = 2**bits - 1
    q = np.floor(np.clip(img.astype(np.float64), 0.0, 1.0) * maxv + 0.5)
    q = q.astype(np.uint8 if bits == 8 else np.uint16)
    data = _encode_png(q)  # not imageio: Pillow cannot write 16-bit colour PNGs
    with atomic_write(p) as f:
        f.write(data)


def save_aovs(path: PathLike, aovs: dict[str, Any]) -> None:
    """Write named image buffers (AOVs) to an .npz file as float32 ``(H, W, C)`` arrays.

    2-D arrays get a trailing channel axis; bool and integer arrays become float32.
    Parent directories are created; the file is written atomically (`atomic_write`).
    """
    p = _output_file(path, ".npz", "save_aovs", ".npz")
    out = {}
    for name, value in aovs.items():
        if not isinstance(name, str) or not name or "/" in name:
            raise ValueError(f"{p}: AOV names must be non-empty strings without '/', got "
                             f"{name!r}")
        a = np.asarray(value)
        if not (a.dtype == np.bool_ or np.issubdtype(a.dtype, np.integer)
                or np.issubdtype(a.dtype, np.floating)):
            raise ValueError(f"{p}: AOV {name!r} has unsupported dtype {a.dtype}")
        if a.ndim == 2:
            a = a[:, :, None]
        if a.ndim != 3:
            raise ValueError(f"{p}: AOV {name!r} must have shape (H, W) or (H, W, C), got "
                             f"{a.shape}")
        out[name] = a.astype(np.float32)
    with atomic_write(p) as f:  # a file object: np.savez would append .npz to other names
        np.savez(f, **out)


def load_aovs(path: PathLike) -> dict[str, np.ndarray]:
    """The float32 arrays written by `save_aovs`, by name."""
    p = _existing_file(path)
    try:
        z = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{p}: cannot read AOVs ({type(e).__name__}: {e})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{p}: not an .npz archive of AOVs")
    with z:
        return {k: np.asarray(z[k], np.float32) for k in z.files}


# ----------------------------------------------------------------------------- reports


def _json_default(o):
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def save_json(path: PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON (NumPy scalars and arrays as numbers and lists),
    atomically (`atomic_write`); the name must end in ``.json``."""
    p = _output_file(path, ".json", "save_json", "JSON")
    text = json.dumps(obj, indent=2, default=_json_default) + "\n"
    with atomic_write(p) as f:
        f.write(text.encode())


def save_loss_plot(path: PathLike, history: list[dict]) -> bool:
    """Plot the loss (log scale) and, when recorded, the mean angular error per iteration.

    Needs matplotlib (the ``cli`` extra: ``pip install -e ".[cli]"``); returns False,
    writing nothing, when it is not installed. Written atomically (`atomic_write`), as a PNG
    (the name must end in ``.png``).
    """
    path = _output_file(path, ".png", "save_loss_plot", "PNG")
    try:
        from matplotlib.figure import Figure  # no pyplot: leaves the caller's backend alone
    except ImportError:
        return False
    fig = Figure(figsize=(6, 3.5), dpi=100)
    ax = fig.add_subplot()
    steps = np.arange(len(history))  # iterations, across coarse-to-fine levels
    ax.semilogy(steps, [max(h["loss"], 1e-30) for h in history], label="loss")
    ax.set_xlabel("iteration")
    ax.set_ylabel("0.5 * sum of squared residuals")
    if history and "mean_angular_error_deg" in history[-1]:
        ax2 = ax.twinx()
        ax2.plot(steps, [h.get("mean_angular_error_deg", np.nan) for h in history], "C1",
                 label="mean angular error")
        ax2.set_ylabel("mean angular error (deg)", color="C1")
    ax.set_title("jaxnm fit")
    fig.tight_layout()
    with atomic_write(path) as f:
        fig.savefig(f, format="png")
    return True


def write_fit_outputs(outdir: PathLike, outputs, *, plot: bool = True) -> list[str]:
    """Write a `jaxnm.fit.FitOutputs` into ``outdir``, every file atomically
    (`atomic_write`) and the map first: ``normal_map.npz``, ``normal_map.png``,
    ``loss.json``, ``error_map.png`` (with a ground truth), ``report.json``, then
    ``render_NN.png`` (one per row of `renders`, if any) and ``loss.png`` (with
    ``plot`` and matplotlib). Returns the names written."""
    out = Path(os.fspath(outdir))
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "normal_map.npz") as f:
        np.savez_compressed(f, normals=outputs.normals, slopes=outputs.slopes)
    save_png(out / "normal_map.png", outputs.map_texels, bits=outputs.bits)
    written = ["normal_map.npz", "normal_map.png", "loss.json"]
    with atomic_write(out / "loss.json") as f:
        f.write((json.dumps(outputs.history, indent=1) + "\n").encode())
    if outputs.error_map is not None:
        save_png(out / "error_map.png", outputs.error_map)
        written.append("error_map.png")
    save_json(out / "report.json", outputs.report)
    written += ["report.json"] + write_fit_renders(out, outputs.renders)
    if plot and save_loss_plot(out / "loss.png", outputs.history):
        written.append("loss.png")
    return written


def save_normal_map_npz(path: PathLike, normals, **extra) -> None:
    """Write a tangent-space map as ``jaxnm fit`` writes ``normal_map.npz``, atomically:
    ``normals`` ``(h, w, 3)`` float32 unit vectors, row 0 on top, and any ``extra`` arrays
    (e.g. ``slopes``, masks) under their names. Refused, writing nothing: a name not ending
    in ``.npz``, normals of another shape or with NaN or infinite values (which
    `load_texture` would not read back)."""
    p = _output_file(path, ".npz", "save_normal_map_npz", ".npz")
    arrays = {"normals": np.asarray(normals, np.float32)}
    n = arrays["normals"]
    if n.ndim != 3 or n.shape[-1] != 3 or 0 in n.shape:
        raise ValueError(f"{p}: normals must be (h, w, 3), got {n.shape}")
    if not np.isfinite(n).all():
        raise ValueError(f"{p}: the normals to save contain NaN or infinite values")
    arrays.update({k: np.asarray(v) for k, v in extra.items()})
    with atomic_write(p) as f:
        np.savez_compressed(f, **arrays)


def save_figure_grid(path: PathLike, rows: list[list], *, titles: list[str],
                     row_labels: list[str], note: str = "") -> bool:
    """A grid of images (each ``(H, W)`` grey, with its colour scale, or ``(H, W, 3)`` RGB
    in [0, 1]; None leaves a cell empty) as a PNG with column titles and row labels,
    atomically. A grey cell is given as ``(array, vmax, label)`` and drawn from 0 to
    ``vmax`` with a colour bar. Needs matplotlib (the ``cli`` extra); returns False, writing
    nothing, without it. The name must end in ``.png``."""
    path = _output_file(path, ".png", "save_figure_grid", "PNG")
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return False
    n_rows, n_cols = len(rows), max(len(r) for r in rows)
    fig = Figure(figsize=(3.0 * n_cols, 3.0 * n_rows + 0.4), dpi=100)
    for i, row in enumerate(rows):
        for j, cell in enumerate(row):
            ax = fig.add_subplot(n_rows, n_cols, i * n_cols + j + 1)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(titles[j], fontsize=9)
            if j == 0:
                ax.set_ylabel(row_labels[i], fontsize=9)
            if cell is None:
                ax.set_frame_on(False)
            elif isinstance(cell, tuple):
                img, vmax, label = cell
                im = ax.imshow(np.ma.masked_invalid(img), vmin=0, vmax=vmax, cmap="magma",
                               interpolation="nearest")
                fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02).set_label(label, fontsize=7)
            else:
                ax.imshow(np.clip(cell, 0, 1), interpolation="nearest")
    if note:
        fig.suptitle(note, fontsize=8)
    fig.tight_layout()
    with atomic_write(path) as f:
        fig.savefig(f, format="png")
    return True


def write_fit_renders(outdir: PathLike, renders: list) -> list[str]:
    """Write each row of ``renders`` (`jaxnm.fit.FitOutputs.renders`) to
    ``outdir/render_NN.png``; returns ``["render_*.png"]``, or ``[]`` for no rows."""
    out = Path(os.fspath(outdir))
    for k, row in enumerate(renders):
        save_png(out / f"render_{k:02d}.png", row)
    return ["render_*.png"] if len(renders) else []


# ----------------------------------------------------------------------------- PNG codec
# imageio reads PNGs through Pillow, which turns 16-bit colour PNGs into 8-bit
# images and cannot write them at all; 16-bit PNGs therefore go through pypng.

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _decode_png16(data: bytes, src: str) -> np.ndarray:
    """A 16-bit PNG as uint16 (H, W, C), via pypng (Pillow reduces 16-bit colour to 8 bits)."""
    try:
        width, height, rows, info = png.Reader(bytes=data).asDirect()
        arr = np.vstack([np.asarray(row, np.uint16) for row in rows])
    except (png.Error, ValueError, zlib.error) as e:
        raise ValueError(f"{src}: corrupt or not a valid PNG ({e})") from None
    return arr.reshape(height, width, info["planes"])


def _encode_png(q: np.ndarray) -> bytes:
    """PNG bytes of a uint8/uint16 (H, W, C) array, via pypng (Pillow cannot write 16-bit RGB)."""
    h, w, c = q.shape
    writer = png.Writer(w, h, greyscale=c <= 2, alpha=c in (2, 4), bitdepth=q.itemsize * 8)
    buf = io.BytesIO()
    writer.write(buf, q.reshape(h, w * c))
    return buf.getvalue()
