"""Procedural assets and the built-in scene and problem, generated in code (no downloads).

- `assets`: meshes with uvs and normals (`torus`, `plane`, `uv_sphere`), the
  rivet height field and its normal map.
- `builtin`: `default_scene` (``jaxnm render``) and `default_problem` /
  `default_fit_job` (``jaxnm fit``).
"""

from .assets import BUILTIN_MESHES as BUILTIN_MESHES
from .assets import RIVET_STRENGTH as RIVET_STRENGTH
from .assets import builtin_mesh as builtin_mesh
from .assets import default_normal_map as default_normal_map
from .assets import default_normal_map_texels as default_normal_map_texels
from .assets import default_torus as default_torus
from .assets import plane as plane
from .assets import rivet_height as rivet_height
from .assets import torus as torus
from .assets import uv_sphere as uv_sphere
from .builtin import DEFAULT_FIT_EYES as DEFAULT_FIT_EYES
from .builtin import HELD_OUT_LIGHT as HELD_OUT_LIGHT
from .builtin import default_fit_job as default_fit_job
from .builtin import default_light_directions as default_light_directions
from .builtin import default_problem as default_problem
from .builtin import default_scene as default_scene

__all__ = [
    "BUILTIN_MESHES", "DEFAULT_FIT_EYES", "HELD_OUT_LIGHT", "RIVET_STRENGTH", "builtin_mesh",
    "default_fit_job", "default_light_directions", "default_normal_map",
    "default_normal_map_texels", "default_problem", "default_scene", "default_torus", "plane",
    "rivet_height", "torus", "uv_sphere",
]
