"""From a high-poly mesh to a low-poly one: maps baked on the low-poly mesh's uv layout.

`raycast_normal_map` casts rays from the low-poly surface to the high-poly one and stores
the high-poly normals in a tangent-space map, with the semantics of Blender's Cycles
"selected to active" bake (`jaxnm.transfer.raycast`). `bake_mesh_pair` (what ``jaxnm bake``
runs, `jaxnm.transfer.pair`) casts those rays, or fits the map to the high-poly mesh's
shading under views and lights it plans (`jaxnm.transfer.views`), or both, and scores the
maps under views and lights the fit never saw (`jaxnm.transfer.evaluate`); `decimate` and
`unwrap` (`jaxnm.transfer.remesh`) make the low-poly mesh from the high-poly one. It all
needs the ``bake`` extra (``pip install -e ".[bake]"``: Embree through ``embreex``, xatlas,
fast-simplification, flip-evaluator), which ``import jaxnm`` does not load.

`BakeWarning` (a `jaxnm.io.JaxnmWarning`) is what the bakers warn with when the bake goes on
but something deserves attention: rays that hit nothing, overlapping uv islands, uvs
outside the unit square, degenerate or non-manifold triangles, meshes wound the wrong way.
"""

from ._meshes import BakeWarning as BakeWarning
from .evaluate import MethodScores as MethodScores
from .evaluate import PairEvaluation as PairEvaluation
from .evaluate import evaluate_maps as evaluate_maps
from .pair import METHODS as METHODS
from .pair import RENDER_SIZES as RENDER_SIZES
from .pair import PairBake as PairBake
from .pair import PairBakeOptions as PairBakeOptions
from .pair import bake_mesh_pair as bake_mesh_pair
from .raycast import RAYCAST_FRAMES as RAYCAST_FRAMES
from .raycast import RaycastBake as RaycastBake
from .raycast import raycast_normal_map as raycast_normal_map
from .remesh import decimate as decimate
from .remesh import unwrap as unwrap
from .views import ViewPlan as ViewPlan
from .views import plan_views as plan_views

__all__ = ["RAYCAST_FRAMES", "BakeWarning", "RaycastBake", "raycast_normal_map", "METHODS",
           "RENDER_SIZES", "PairBakeOptions", "PairBake", "bake_mesh_pair", "ViewPlan",
           "plan_views", "MethodScores", "PairEvaluation", "evaluate_maps", "decimate", "unwrap"]
