"""From a high-poly mesh to a low-poly one: maps baked on the low-poly mesh's uv layout.

`raycast_normal_map` casts rays from the low-poly surface to the high-poly one and stores
the high-poly normals in a tangent-space map, with the semantics of Blender's Cycles
"selected to active" bake (`jaxnm.transfer.raycast`). It needs the ``bake`` extra
(``pip install -e ".[bake]"``: Embree through ``embreex``), which ``import jaxnm`` does not
load.
"""

from .raycast import RAYCAST_FRAMES as RAYCAST_FRAMES
from .raycast import BakeWarning as BakeWarning
from .raycast import RaycastBake as RaycastBake
from .raycast import raycast_normal_map as raycast_normal_map

__all__ = ["RAYCAST_FRAMES", "BakeWarning", "RaycastBake", "raycast_normal_map"]
