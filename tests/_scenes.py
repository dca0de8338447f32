"""What several test modules render alike, so that they run the same compiled programs.

Each distinct program (image size, outputs, options, array shapes) costs seconds to
compile; a repeat costs next to nothing, in another module too (the suite's persistent
compilation cache, `conftest.py`). Tests that check logic rather than scale therefore
render the built-in scene at one of two sizes and ask for one list of outputs, and each
reads the outputs it checks.
"""

from __future__ import annotations

from jaxnm.procedural import default_scene

#: The built-in scene's size where `jaxnm.render` runs on the whole image (below
#: `jaxnm._exec.pixels.PACK_MIN_PIXELS`).
WHOLE = 96
#: ... and the smallest where it runs on the packed covered pixels (256 x 256 pixels).
PACKED = 256

#: The outputs the shared renders ask for (in any order, one set of options: `render`
#: lists them in `jaxnm.gbuffer.OUTPUTS`' order).
OUTPUTS = ("color", "mask", "triangle_id", "front_facing", "depth", "position", "normal",
           "perturbed_normal", "tangent", "bitangent")


def builtin_scene(size: int = WHOLE):
    """`jaxnm.procedural.default_scene` at ``size`` x ``size``."""
    return default_scene(width=size, height=size)
