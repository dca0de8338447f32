"""``jaxnm render``: a scene file, a mesh file or the built-in scene to a PNG, its AOVs, and
with ``--light`` one image per light beside a fit file that names them."""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
import warnings
from pathlib import Path

from ._flags import output_path
from ._interrupt import CtrlC

__all__ = ["add_parser", "run", "frame_name", "TARGETS_SUFFIX", "SCENE_SUFFIX", "MESH_VIEW",
           "MESH_UP"]

#: With ``--light``, the fit file written beside the images: ``OUT_STEM`` + this.
TARGETS_SUFFIX = "_targets.json"
#: With ``--light`` and a mesh file or the built-in scene (or a scene file with ``--frame``,
#: ``--derivatives`` or ``--precision``), the scene file the fit file names: ``OUT_STEM`` +
#: this.
SCENE_SUFFIX = "_scene.json"
#: Where ``jaxnm render MESH`` looks from: the front (+z, with y up, as in glTF and most OBJ
#: exporters), a little from the right and from above.
MESH_VIEW = (0.4, 0.3, 1.0)
#: ``--up``'s axes: a y-up direction (as `MESH_VIEW`) in a mesh whose up axis is this one.
#: With z up (Blender, most STL and CAD files) the front is -y, as Blender's front view.
MESH_UP = {"y": lambda x, y, z: (x, y, z), "z": lambda x, y, z: (x, -z, y)}
# world units per unit of a --height-map image, without --height-scale
_HEIGHT_SCALE = 0.02


def frame_name(text: str) -> str:
    """``--frame``'s value: a frame of `jaxnm.frames.FRAMES` or one of its aliases
    (``mikktspace``, ``schuler``)."""
    from ..frames import canonical_frame

    try:
        return canonical_frame(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _direction(text: str) -> tuple[float, float, float]:
    """``--light X,Y,Z``: a non-zero direction towards the light."""
    try:
        d = tuple(float(x) for x in text.split(","))
    except ValueError:
        d = ()
    if len(d) != 3 or not all(abs(x) < float("inf") for x in d) or not any(d):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z, three finite numbers not all zero "
                                         f"(the direction towards the light), got {text!r}")
    return d


def add_parser(sub) -> None:
    """Add ``jaxnm render`` and its options to the subcommands ``sub``."""
    from ..frames import FRAME_ALIASES, FRAMES
    from ..interpolate import DERIVATIVE_MODES, PRECISIONS
    from ..render import OUTPUTS

    p = sub.add_parser("render", help="render a scene to a PNG (and optional AOVs)",
                       description="Render SCENE.json, a mesh file seen whole from the front, "
                       "or the built-in default scene to a PNG.")
    p.add_argument("scene", nargs="?", help="scene JSON file, or a mesh file (OBJ, PLY, glTF, "
                   "STL, OFF) seen whole from the front, a glTF file with its own normal map "
                   "(default: the built-in scene)")
    p.add_argument("-o", "--output", default="render.png", help="output PNG (default: %(default)s)")
    p.add_argument("--aovs", metavar="OUT.npz",
                   help="also write per-pixel arrays to an .npz: " + ", ".join(OUTPUTS)
                   + " (linear); see --aov-list")
    p.add_argument("--aov-list", metavar="NAMES",
                   help="comma-separated names of the arrays --aovs writes (default: all)")
    p.add_argument("--derivatives", choices=DERIVATIVE_MODES, help="screen-space derivative mode")
    p.add_argument("--frame", type=frame_name, metavar="FRAME",
                   help="tangent frame: " + ", ".join(FRAMES) + " (also "
                   + ", ".join(a for a in FRAME_ALIASES if a.isascii()) + ")")
    p.add_argument("--precision", choices=PRECISIONS,
                   help="shader arithmetic of the frame and perturbation (float16: mediump)")
    p.add_argument("--light", type=_direction, action="append", metavar="X,Y,Z",
                   help="render under a white directional light from this world direction "
                   "instead of the scene's lights; repeat it for one image per light "
                   f"(OUT_00.png, ...), with a fit file naming them (OUT{TARGETS_SUFFIX})")
    maps = p.add_mutually_exclusive_group()
    maps.add_argument("--normal-map", metavar="PATH",
                      help="use this tangent-space normal map (an 8/16-bit PNG, or a BC5 or "
                      "DXT5nm DDS; unsigned, green up; the scene's uv origin, wrap, filter and "
                      "strength)")
    maps.add_argument("--height-map", metavar="PATH", dest="height_map",
                      help="bump the surface with this height map instead (grayscale image)")
    p.add_argument("--height-scale", type=float, dest="height_scale",
                   help=f"world units per unit of the height map (default: {_HEIGHT_SCALE})")
    p.add_argument("--width", type=int,
                   help="image width in pixels (default: the scene's; the built-in scene's "
                   "is 512); the camera keeps its vertical field of view")
    p.add_argument("--height", type=int, help="image height in pixels (as --width)")
    p.add_argument("--up", choices=tuple(MESH_UP),
                   help="a mesh file's up axis (default: y; z for Blender's, most STL and CAD "
                   "files): the mesh is seen from its front, upright")
    p.add_argument("--exposure", type=float, default=1.0, help="linear scale before sRGB")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bit depth")


def _rescaled_camera(scene, width: int, height: int):
    """The scene's camera with the projection's aspect ratio adapted to a new image size."""
    import numpy as np

    from ..camera import Camera

    proj = np.array(scene.camera.projection, np.float64)
    proj[0, :] *= (scene.width / scene.height) / (width / height)  # x scale ~ 1 / aspect
    return Camera.from_matrices(np.asarray(scene.camera.view, np.float64), proj)


def _aov_names(args) -> tuple[str, ...]:
    """The arrays ``--aovs`` writes, checked before anything is loaded."""
    from ..render import OUTPUTS

    if not args.aovs:
        if args.aov_list is not None:
            raise ValueError("--aov-list names the arrays that --aovs writes: give --aovs "
                             "OUT.npz too")
        return ()
    if Path(args.aovs).suffix.lower() != ".npz":
        raise ValueError(f"--aovs {args.aovs}: the arrays are written as NumPy .npz; the name "
                         "must end in .npz")
    if args.aov_list is None:
        return tuple(OUTPUTS)
    asked = tuple(dict.fromkeys(n.strip() for n in args.aov_list.split(",") if n.strip()))
    bad = [n for n in asked if n not in OUTPUTS]
    if not asked:
        raise ValueError(f"--aov-list names no array; name at least one of {', '.join(OUTPUTS)}")
    if bad:
        raise ValueError(f"--aov-list: unknown AOV names {bad}; known: {', '.join(OUTPUTS)}")
    return asked


def _check_map_options(args) -> None:
    """The map files exist and ``--height-scale`` comes with a height map, checked before
    anything is loaded."""
    if args.height_scale is not None:
        if not args.height_map:
            raise ValueError("--height-scale scales the map --height-map reads: give "
                             "--height-map PATH too")
        if not abs(args.height_scale) < float("inf"):
            raise ValueError(f"--height-scale must be finite, got {args.height_scale}")
    for flag, path in (("--normal-map", args.normal_map), ("--height-map", args.height_map)):
        if path and not Path(path).exists():
            raise FileNotFoundError(f"{flag}: {path}: no such file")
        if path and not Path(path).is_file():
            raise ValueError(f"{flag}: {path}: not a regular file")


def _scene(args):
    """The scene of ``args``: the file's or the built-in one, with the options applied."""
    from .. import io
    from ..config import OBJECT_SPACE_HINT, load_height_map, load_scene
    from ..procedural import default_scene

    if args.scene and Path(args.scene).suffix.lower() in io.MESH_EXTENSIONS:
        scene = _mesh_scene(args.scene, args.width or 512, args.height or 512, args.up or "y",
                            own_map=not (args.normal_map or args.height_map))
    elif args.up:
        raise ValueError("--up is a mesh file's up axis; a scene file has its camera, and the "
                         "built-in scene its own")
    elif args.scene:
        scene = load_scene(args.scene)
    else:
        scene = default_scene(width=args.width or 512, height=args.height or 512)
    changes = {}
    if args.width or args.height:
        w, h = args.width or scene.width, args.height or scene.height
        if (w, h) != (scene.width, scene.height):
            changes.update(width=w, height=h, camera=_rescaled_camera(scene, w, h))
    if args.normal_map and Path(args.normal_map).suffix.lower() == ".dds":
        from ..storage import load_dds_normal_map

        m = load_dds_normal_map(args.normal_map)  # BC5 or DXT5nm: two channels, z rebuilt
        changes.update(normal_map=m.texels, normal_map_options=dataclasses.replace(
            m.options(scene.normal_map_options), green="up"))
    elif args.normal_map:
        raw, bits = io.load_texture(args.normal_map, channels=3)
        io.check_tangent_normal_map(raw, source=args.normal_map, hint=OBJECT_SPACE_HINT)
        changes.update(normal_map=raw, normal_map_options=dataclasses.replace(
            scene.normal_map_options, encoding="unsigned", channels=3, green="up",
            space="tangent", bits=bits if bits in (8, 16) else 8))
    if args.height_map:
        scale = _HEIGHT_SCALE if args.height_scale is None else args.height_scale
        d, opts = load_height_map({"path": args.height_map, "scale": scale})
        changes.update(normal_map=d, normal_map_options=opts)
    if changes:
        scene = scene.replace(**changes)
    frame = args.frame or scene.frame
    if frame == "vertex" and scene.mesh.tangents is None and scene.mesh.uv is not None:
        scene = scene.replace(mesh=scene.mesh.with_tangents())  # MikkTSpace
    return scene, frame


def _mesh_scene(path: str, width: int, height: int, up: str = "y", *, own_map: bool = True):
    """The scene of a mesh file alone: the whole mesh seen from `MESH_VIEW`, turned for the
    mesh's ``up`` axis (`MESH_UP`), through a 40-degree view; grey Blinn-Phong lit from the
    camera's upper left, as a scene file that names only the mesh and a camera. With
    ``own_map``, a glTF file's own normal map (`jaxnm.io.load_gltf_normal_map`), decoded as
    glTF prescribes: the "vertex" frame (MikkTSpace, or the file's tangents)."""
    from .. import io
    from ..camera import Camera
    from ..geometry import bounding_sphere
    from ..scene import Scene, back_faces_hidden, check_scene_options, validate_scene

    check_scene_options(width=width, height=height, source=path)
    mesh = io.load_mesh(path)
    centre, radius = bounding_sphere(mesh)
    turn = MESH_UP[up]
    camera = Camera.framing(centre, radius, turn(*MESH_VIEW), up=turn(0.0, 1.0, 0.0),
                            fov_y_deg=40.0, aspect=width / height, margin=1.05)
    scene = Scene(mesh=mesh, camera=camera, width=width, height=height,
                  cull_back=back_faces_hidden(mesh, camera), source=path)
    found = None
    if own_map and mesh.uv is not None and Path(path).suffix.lower() in (".gltf", ".glb"):
        try:
            found = io.load_gltf_normal_map(path)
        except ValueError as e:  # the mesh still renders: say why it has no map
            warnings.warn(f"{e}; rendered without it (--normal-map gives one)", io.JaxnmWarning,
                          stacklevel=2)
    if found is not None:
        texels, options = found
        scene = scene.replace(normal_map=texels, frame="vertex", normal_map_options=options)
    return validate_scene(scene)


def _numbered(path: str, i: int, count: int) -> Path:
    """``path`` itself for one image, else ``STEM_NN.EXT``."""
    p = Path(path)
    return p if count == 1 else p.with_name(f"{p.stem}_{i:02d}{p.suffix}")


def _targets_scene(args, scene, path: Path) -> Path | None:
    """None where a targets fit file can name the scene file given; else ``path``, a scene
    file written there that describes the scene the images were rendered from (a mesh
    file's or the built-in scene, or the scene file given with the frame, derivatives or
    precision the options changed)."""
    import numpy as np

    from .. import io

    def rel(p) -> str:
        return os.path.relpath(Path(p).resolve(), path.parent.resolve())

    changed = {k: v for k, v in (("frame", args.frame), ("derivatives", args.derivatives),
                                 ("precision", args.precision))
               if v is not None and v != getattr(scene, k)}
    mesh_file = args.scene and Path(args.scene).suffix.lower() in io.MESH_EXTENSIONS
    if args.scene and not mesh_file:
        if not changed:
            return None
        spec = _rebased(io.load_json(args.scene), Path(args.scene).parent, rel)
    else:
        m = scene.material
        spec = {"mesh": rel(args.scene) if mesh_file else "builtin:torus",
                "width": scene.width, "height": scene.height,
                "camera": {k: np.asarray(getattr(scene.camera, k), np.float64).tolist()
                           for k in ("view", "projection")},
                "albedo": _shortest(scene.albedo),
                "material": {"model": scene.shading, "shininess": _shortest(m.shininess)[0],
                             **{k: _shortest(getattr(m, k))
                                for k in ("diffuse", "specular", "ambient")}},
                "frame": scene.frame, "derivatives": scene.derivatives,
                "precision": scene.precision, "double_sided": scene.double_sided}
    io.save_json(path, {**spec, **changed})
    return path


def _shortest(values) -> list[float]:
    """float32 ``values`` as the shortest decimals that read back as them (0.85, not
    0.8500000238418579)."""
    import numpy as np

    return [float(str(v)) for v in np.asarray(values, np.float32).reshape(-1)]


def _rebased(spec: dict, base: Path, rel) -> dict:
    """A scene file's object with the files it names (relative to ``base``) named by
    ``rel``, for a copy of it elsewhere."""
    def moved(ref):
        if isinstance(ref, dict) and isinstance(ref.get("path"), str):
            return {**ref, "path": moved(ref["path"])}
        if isinstance(ref, str) and not ref.startswith("builtin:"):
            return rel(base / ref)
        return ref

    return {k: moved(v) if k in ("mesh", "normal_map", "height_map", "albedo") else v
            for k, v in spec.items()}


def _targets_file(args, scene, images: list[Path]) -> list[Path]:
    """With ``--light``: a fit file naming the scene (`_targets_scene`), its view and each
    image with its light, beside the images (``OUT_STEM`` + `TARGETS_SUFFIX`); paths
    relative to it. Returns the files written: the scene file, if any, and the fit file."""
    import numpy as np

    from .. import io

    out = Path(args.output)
    path = out.with_name(out.stem + TARGETS_SUFFIX)
    folder = path.parent.resolve()
    written = _targets_scene(args, scene, out.with_name(out.stem + SCENE_SUFFIX))
    fit = {"scene": os.path.relpath(Path(written or args.scene).resolve(), folder)}
    fit["views"] = [{"camera": {"view": np.asarray(scene.camera.view, np.float64).tolist(),
                                "projection": np.asarray(scene.camera.projection,
                                                         np.float64).tolist()},
                     "width": scene.width, "height": scene.height}]
    fit["targets"] = [{"image": os.path.relpath(img.resolve(), folder), "view": 0,
                       "lights": [{"type": "directional", "direction": list(d)}]}
                      for img, d in zip(images, args.light, strict=True)]
    io.save_json(path, fit)
    return [p for p in (written, path) if p is not None]


def run(args, ctrl_c: CtrlC) -> int:
    """Render and write the image(s); Ctrl-C stops before anything is written."""
    import numpy as np

    from .. import io
    from ..render import render
    from ..scene import MAX_IMAGE_SIZE
    from ..shading import directional_light, to_display

    t0 = time.perf_counter()
    aovs = _aov_names(args)
    for flag, v in (("--width", args.width), ("--height", args.height)):
        if v is not None and not 0 < v <= MAX_IMAGE_SIZE:
            raise ValueError(f"{flag} must be 1 to {MAX_IMAGE_SIZE} pixels, got {v}")
    if not 0 < args.exposure < float("inf"):
        raise ValueError(f"--exposure must be a positive finite scale, got {args.exposure}")
    if args.light and args.exposure != 1:
        raise ValueError("--exposure scales the images, and the fit file --light writes beside "
                         "them could not say so: leave one of them out")
    if Path(args.output).suffix.lower() != ".png":
        raise ValueError(f"-o {args.output}: jaxnm render writes PNG images; the name must end "
                         "in .png")
    _check_map_options(args)
    if args.scene and Path(args.scene).suffix.lower() in io.IMAGE_EXTENSIONS:
        raise ValueError(f"{args.scene}: an image, not a scene file (JSON) or a mesh file; a "
                         f"map goes to --normal-map or --height-map")
    output_path("-o", args.output)
    if args.aovs is not None:
        output_path("--aovs", args.aovs)
    scene, frame = _scene(args)
    ctrl_c.check()
    lights = ([directional_light(d) for d in args.light] if args.light
              else [scene.lights])
    outputs = tuple(dict.fromkeys(("color", *aovs)))
    results = []
    for lit in lights:
        results.append(render(scene.replace(lights=lit), outputs=outputs,
                              derivatives=args.derivatives, frame=args.frame,
                              precision=args.precision))
        ctrl_c.check()
    written = []
    for i, result in enumerate(results):
        png = _numbered(args.output, i, len(results))
        io.save_png(png, np.asarray(to_display(result["color"], exposure=args.exposure)),
                    bits=args.bits)
        written.append(png)
        if aovs:
            npz = _numbered(args.aovs, i, len(results))
            io.save_aovs(npz, {k: result[k] for k in aovs})
            written.append(npz)
    if args.light:
        written += _targets_file(args, scene, written[::2 if aovs else 1])
    what = f"{scene.width}x{scene.height}, frame {frame}"
    if frame == "vertex":
        what += f", tangents: {scene.mesh.tangent_source}"
    if aovs:
        what += f"; arrays: {', '.join(aovs)}"
    print(f"wrote {', '.join(map(str, written))} ({what}) in {time.perf_counter() - t0:.2f} s")
    return 0
