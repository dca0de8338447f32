"""jaxnm: a differentiable software rasterizer in JAX for normal-mapping research.

The pipeline, one verb per stage::

    clip  = jaxnm.to_clip(mesh.positions, camera)                 # camera
    frags = jaxnm.rasterize(clip, mesh.faces, width=W, height=H)  # raster
    attrs = jaxnm.interpolate({"p": ..., "uv": ...}, frags, derivatives="fine")
    frame = jaxnm.compute_frame("cotangent", n, inputs=jaxnm.frames.FrameInputs(
        p_attr=attrs["p"], uv_attr=attrs["uv"]))
    m     = jaxnm.decode_normal_map(jaxnm.sample(mips, attrs["uv"], filter="trilinear"))
    n2    = jaxnm.perturb_normal(frame, m)
    rgb   = jaxnm.shade("blinn_phong", n2, p, camera.eye, lights, material)

or, for a whole scene, `jaxnm.render(scene, outputs=(...))` (differentiable in the
scene's arrays) and `jaxnm.fit_normal_map(problem)`. Scene and fit files are read
by `jaxnm.config`; meshes, images and a fit's outputs by `jaxnm.io`.
"""

from .bake import bake_normal_map as bake_normal_map
from .blend import blend_normal_maps as blend_normal_maps
from .camera import Camera as Camera
from .camera import look_at as look_at
from .camera import orthographic as orthographic
from .camera import perspective as perspective
from .camera import to_clip as to_clip
from .config import load_fit as load_fit
from .config import load_scene as load_scene
from .fit import FitJob as FitJob
from .fit import FitOptions as FitOptions
from .fit import FitProblem as FitProblem
from .fit import FitTarget as FitTarget
from .fit import fit_normal_map as fit_normal_map
from .frames import Frame as Frame
from .frames import compute_frame as compute_frame
from .frames import cotangent_frame as cotangent_frame
from .frames import perturb_normal as perturb_normal
from .geometry import Mesh as Mesh
from .interpolate import Attribute as Attribute
from .interpolate import Barycentrics as Barycentrics
from .interpolate import barycentrics as barycentrics
from .interpolate import interpolate as interpolate
from .procedural import default_problem as default_problem
from .procedural import default_scene as default_scene
from .raster import Fragments as Fragments
from .raster import rasterize as rasterize
from .render import render as render
from .scene import Scene as Scene
from .shading import DirectionalLight as DirectionalLight
from .shading import Lights as Lights
from .shading import Material as Material
from .shading import PointLight as PointLight
from .shading import directional_light as directional_light
from .shading import shade as shade
from .textures import NormalMapOptions as NormalMapOptions
from .textures import build_mipmaps as build_mipmaps
from .textures import decode_normal_map as decode_normal_map
from .textures import encode_normal_map as encode_normal_map
from .textures import sample as sample

#: The package version (the one place it is written; pyproject.toml reads it from here).
__version__ = "0.2.0"

__all__ = [
    "Attribute", "Barycentrics", "Camera", "DirectionalLight", "FitJob", "FitOptions",
    "FitProblem", "FitTarget", "Fragments", "Frame", "Lights", "Material", "Mesh",
    "NormalMapOptions", "PointLight", "Scene", "bake_normal_map", "barycentrics",
    "blend_normal_maps", "build_mipmaps", "compute_frame",
    "cotangent_frame", "decode_normal_map", "default_problem", "default_scene",
    "directional_light", "encode_normal_map", "fit_normal_map", "interpolate", "load_fit",
    "load_scene", "look_at", "orthographic", "perspective", "perturb_normal", "rasterize",
    "render", "sample", "shade", "to_clip",
]
