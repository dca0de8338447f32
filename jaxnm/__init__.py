"""jaxnm: a differentiable software rasterizer in JAX for normal-mapping research."""

from .camera import Camera as Camera
from .camera import look_at as look_at
from .camera import orthographic as orthographic
from .camera import perspective as perspective
from .camera import to_clip as to_clip
from .interpolate import Attribute as Attribute
from .interpolate import Barycentrics as Barycentrics
from .interpolate import barycentrics as barycentrics
from .interpolate import interpolate as interpolate
from .raster import Fragments as Fragments
from .raster import rasterize as rasterize

__version__ = "0.1.0"
