"""OpenGL reference renderer for jaxnm tests (Mesa llvmpipe, headless EGL).

Renders a triangle soup with real GLSL 4.50 shaders and returns, per pixel,
exactly what the fragment stage saw: ``gl_PrimitiveID``, ``gl_FrontFacing``,
``gl_FragCoord`` and every perspective-correct (``smooth``) interpolated
vertex attribute together with its fine / coarse / plain screen-space
derivatives.  Tests compare jaxnm's rasterizer against these buffers.

API
---
``gl_available() -> (bool, str)``
    ``(True, renderer_string)`` or ``(False, reason)``; never raises.  Meant
    for ``pytest.mark.skipif(not gl_available()[0], reason=...)``.

``render_gl(clip, faces, attrs, width, height, *, cull_back=False) -> dict``
    See its docstring.  All images are returned in IMAGE layout (row 0 is the
    top row), i.e. the rows read back from GL are flipped.  Quantities that
    are defined in window coordinates (``frag_coord``, ``*_dy*``) keep GL's
    convention: window y points UP, so pixel ``(row r, col c)`` of the
    returned image has ``frag_coord == (c + 0.5, height - 1 - r + 0.5)`` and
    ``k_dy = d k / d y_window = -d k / d row``.

GL state used: RGBA32F colour attachments (several passes, one per
attribute, plus one for the fixed-function outputs), a GL_DEPTH_COMPONENT32F
depth attachment (moderngl only creates DEPTH_COMPONENT24, so the texture
storage is respecified through ``glTexImage2D`` via ctypes and checked
with GL_TEXTURE_INTERNAL_FORMAT; a probe also saw DEPTH_SIZE 32 and
DEPTH_TYPE GL_FLOAT), depth test
LESS, depth cleared to 1.0, default glDepthRange(0, 1), default clip
control (lower-left origin, -1..1 NDC z), no depth clamp, viewport
(0, 0, width, height), single-sample, no blending, culling of back faces
(CCW = front) only when requested.  Each pass is ONE non-indexed
``glDrawArrays(GL_TRIANGLES)`` over the faces in order, so
``gl_PrimitiveID`` is the face index.

Measured behaviour of llvmpipe (LLVM 15.0.6, 256 bits), Mesa 22.3.6
--------------------------------------------------------------------
Window coordinates below: x right, y UP, pixel (i, j) has its centre at
(i + 0.5, j + 0.5), j counted from the bottom (image row = H - 1 - j).

1. Tie rule (pixel centre exactly on an edge): a centre exactly on an edge
   belongs to the triangle whose inward edge normal n (window coords, y up)
   satisfies ``n.x > 0 or (n.x == 0 and n.y > 0)``, i.e. LEFT edges and
   BOTTOM edges include their centres, right and top edges exclude them
   (the D3D "top-left" rule, applied with y pointing up).
   Since image row 0 is the window's top row, "bottom" is also the visual
   bottom of the returned image: in image coords (y down) the rule reads
   ``n.x > 0 or (n.x == 0 and n.y_img < 0)``.  The rule does not depend on
   the winding (CW/CCW give the same coverage).
   Evidence (clip w = 1, NDC multiples of 1/8, so the viewport transform is
   exact):
     * 8x8, shared vertical edge x = 4.5: column 4 goes to the triangle on
       the right; alone, the right triangle includes column 4 and the left
       one excludes it.
     * 8x8, shared horizontal edge y = 4.5 (image row 3): the row goes to
       the triangle above it (interior y > 4.5); alone, the triangle whose
       bottom edge is y = 4.5 includes the row, the one whose top edge it is
       excludes it.
     * 8x8, diagonals y = x and y = 8 - x: the on-edge centres go to the
       triangle with n.x > 0 (normal (1,-1) resp. (1,1)).
     * 5,572 random triangles with vertices on the half-pixel grid (16x16,
       8x16, 32x4 images; 3,805 of them have centres exactly on an edge,
       two thirds have an axis-aligned edge): the rule above predicts every
       pixel exactly (0 mismatching triangles); the alternatives
       "n.y < 0 for horizontals" / "n.x < 0" / all-inclusive /
       all-exclusive mismatch 317-380 / 779-954 / 992-1065 / 533-637
       triangles per image size.
   Exact ties need an exact viewport transform: with odd width/height,
   2/W is not dyadic, so NDC -> window coordinates is rounded.
   Sub-pixel snapping: COVERAGE uses vertex positions snapped to a 1/256 px
   grid (8 sub-pixel bits, round to nearest): moving a left edge from
   x = 4.5 by +1.5*2^-9 px (or more) excludes column 4, by +2^-9 px or less
   it does not (2^-9 is a rounding tie and rounds back onto 4.5).  The
   attribute / depth INTERPOLATION, however, uses the unsnapped float
   positions (see 5).

2. dFdxCoarse / dFdyCoarse do NOT use a fixed pixel of the quad: llvmpipe
   implements the coarse variants exactly like the fine ones (bit-identical
   outputs in 120 random renders, 3..39 px sizes, 20k fragments, plus all
   other probes).  Quads are aligned to even window coordinates counted
   from the window's bottom-left (i0 = i & ~1, j0 = j & ~1), and
       dFdxFine(i, j) = f(i0 + 1, j) - f(i0, j)   (the pixel's own row)
       dFdyFine(i, j) = f(i, j0 + 1) - f(i, j0)   (the pixel's own column)
   with f evaluated at the neighbour's pixel centre.  For odd H the image's
   top row (window j = H - 1, even) pairs with a row outside the
   framebuffer; likewise the last column for odd W.
   Evidence: perspective-textured full-viewport quad (two triangles, clip
   w = 1, 3, 0.5, 2; rational, non-affine attribute) at 8x8, 7x5, 9x7,
   16x11; error of GL's derivative against float64 candidates, relative to
   the attribute scale: own row/column with even anchor 1.1e-7 .. 2.6e-7;
   the quad's lower or upper row (left or right column) 3.2e-2 .. 1.4e-1;
   odd anchor 0.13 .. 1.07.

3. Plain dFdx / dFdy are bit-identical to dFdxFine / dFdyFine (and hence
   to the coarse ones) on llvmpipe (same 120 renders).

4. Quad neighbours outside the pixel's triangle (covered by background, by
   another triangle, outside the framebuffer, helper pixels): the value
   used for the derivative is the SAME triangle's perspective-correct
   interpolant evaluated (extrapolated) at the neighbour's centre.
   Evidence: 60 renders of 6 random perspective triangles (23x17, w in
   [0.3, 3], some clipped), error of dFdxFine/dFdyFine against the float64
   finite difference of the own triangle's interpolant, normalised by
   max(|f(a)|, |f(b)|, 1):
       neighbour in same triangle  n=12910  p99 5.4e-7  max 6.7e-6
       neighbour is background     n= 3137  p99 5.3e-6  max 9.7e-5
       neighbour in other triangle n= 2994  p99 3.0e-6  max 2.2e-3
       neighbour outside the fb    n=  181  p99 2.1e-6  max 9.6e-6
   whereas "difference of the values GL shows at the two pixels" is off by
   ~1 (median 0.9 - 1.1) when the neighbour is not in the same triangle.
   The 2.2e-3 outlier is an extreme extrapolation (neighbour barycentrics
   (90, -32, -57), close to the w = 0 horizon), i.e. float32 conditioning.

5. Precision of the smooth interpolation vs. the float64 perspective-
   correct interpolant at the pixel centre (solve sum b_i (X_i - xn W_i) = 0,
   sum b_i (Y_i - yn W_i) = 0, sum b_i = 1 from the UNSNAPPED float32 clip
   positions), attributes uniform in [-1, 1], ~115k fragments of 900 random
   triangles inside the viewport (32x32 / 64x48, w = 1, w in [0.5, 2],
   w in [0.2, 5]):
       per-fragment abs error: median 1.2e-7, p99 ~1e-6, p99.9 3e-6 - 6e-6,
       max 2.5e-5 - 7.7e-5 (the worst ones all on slivers: area < 15 px^2,
       longest_edge^2 / area > 45); triangles with
       longest_edge^2 / area < 20: max 1.6e-6 - 4.9e-6.
       Clipped triangles (NDC up to +-1.5): max 4.4e-5.
   Relative to the attribute range: ~1e-6 typical, <= 5e-6 for well-shaped
   triangles.  Using snapped (1/256 px) positions in the reference instead
   makes the error 1e-2 - 3e-2, which shows interpolation is unsnapped.
   gl_FragCoord.z vs. 0.5 * z_ndc + 0.5 (float64): median 2.5e-8,
   p99 3e-7, max 6e-6 - 4.3e-5 (the largest on slivers).  gl_FragCoord.xy is
   exactly (i + 0.5, j + 0.5).
   Suggested tolerances: values atol ~1e-5 * attribute scale (1e-4 if
   slivers are present); depth atol ~1e-6 (5e-5 with slivers);
   derivatives atol ~2x the value tolerance, looser at silhouettes under
   strong perspective (see 4).

Depth precision check: with the 32F attachment, a triangle 2^-25 nearer in
window depth (at depth 0.125) wins the LESS test in either draw order;
with moderngl's default DEPTH_COMPONENT24 it loses when drawn second.
"""

from __future__ import annotations

import ctypes

import numpy as np

__all__ = ["gl_available", "render_gl"]

# --------------------------------------------------------------------------
# Shaders
# --------------------------------------------------------------------------

VERTEX_SHADER = """
#version 450 core
layout(location = 0) in vec4 in_clip;
layout(location = 1) in vec4 in_attr;
layout(location = 0) smooth out vec4 v_attr;
void main() {
    v_attr = in_attr;
    gl_Position = in_clip;
}
"""

# Fixed-function outputs: gl_FragCoord, gl_PrimitiveID, gl_FrontFacing.
# The primitive id is stored as a float (exact below 2**24 faces); the
# second target's .y channel is a coverage flag (background stays 0).
META_FRAGMENT_SHADER = """
#version 450 core
layout(location = 0) out vec4 out_coord;   // FragCoord.xyz, float(PrimitiveID)
layout(location = 1) out vec4 out_flags;   // FrontFacing, covered, FragCoord.w, 0
void main() {
    out_coord = vec4(gl_FragCoord.xyz, float(gl_PrimitiveID));
    out_flags = vec4(gl_FrontFacing ? 1.0 : 0.0, 1.0, gl_FragCoord.w, 0.0);
}
"""

# One attribute (padded to vec4) and all its derivatives.
ATTR_FRAGMENT_SHADER = """
#version 450 core
layout(location = 0) smooth in vec4 v_attr;
layout(location = 0) out vec4 out_value;
layout(location = 1) out vec4 out_dx_fine;
layout(location = 2) out vec4 out_dy_fine;
layout(location = 3) out vec4 out_dx_coarse;
layout(location = 4) out vec4 out_dy_coarse;
layout(location = 5) out vec4 out_dx;
layout(location = 6) out vec4 out_dy;
void main() {
    out_value = v_attr;
    out_dx_fine = dFdxFine(v_attr);
    out_dy_fine = dFdyFine(v_attr);
    out_dx_coarse = dFdxCoarse(v_attr);
    out_dy_coarse = dFdyCoarse(v_attr);
    out_dx = dFdx(v_attr);
    out_dy = dFdy(v_attr);
}
"""

_ATTR_SUFFIXES = ("", "_dx_fine", "_dy_fine", "_dx_coarse", "_dy_coarse", "_dx", "_dy")

# GL enums
_GL_TEXTURE_2D = 0x0DE1
_GL_TEXTURE_BINDING_2D = 0x8069
_GL_DEPTH_COMPONENT = 0x1902
_GL_DEPTH_COMPONENT32F = 0x8CAC
_GL_FLOAT = 0x1406
_GL_TEXTURE_INTERNAL_FORMAT = 0x1003
_GL_NO_ERROR = 0

# --------------------------------------------------------------------------
# Context (created lazily, once per process)
# --------------------------------------------------------------------------

_STATE: dict = {}


class _RawGL:
    """The few raw GL entry points moderngl does not expose (via EGL)."""

    def __init__(self) -> None:
        egl = None
        for name in ("libEGL.so.1", "libEGL.so"):
            try:
                egl = ctypes.CDLL(name)
                break
            except OSError:
                continue
        if egl is None:
            raise OSError("cannot load libEGL")
        gpa = egl.eglGetProcAddress
        gpa.restype = ctypes.c_void_p
        gpa.argtypes = [ctypes.c_char_p]

        def fn(name, restype, *argtypes):
            ptr = gpa(name.encode())
            if not ptr:
                raise OSError(f"eglGetProcAddress({name}) failed")
            return ctypes.CFUNCTYPE(restype, *argtypes)(ptr)

        u, i = ctypes.c_uint, ctypes.c_int
        self.glGetError = fn("glGetError", u)
        self.glBindTexture = fn("glBindTexture", None, u, u)
        self.glGetIntegerv = fn("glGetIntegerv", None, u, ctypes.POINTER(i))
        self.glTexImage2D = fn(
            "glTexImage2D", None, u, i, i, i, i, i, u, u, ctypes.c_void_p
        )
        self.glGetTexLevelParameteriv = fn(
            "glGetTexLevelParameteriv", None, u, i, u, ctypes.POINTER(i)
        )

    def make_depth32f(self, glo: int, width: int, height: int) -> None:
        """Respecify texture ``glo`` as GL_DEPTH_COMPONENT32F storage."""
        prev = ctypes.c_int(0)
        self.glGetIntegerv(_GL_TEXTURE_BINDING_2D, ctypes.byref(prev))
        while self.glGetError() != _GL_NO_ERROR:  # drain stale errors
            pass
        self.glBindTexture(_GL_TEXTURE_2D, glo)
        self.glTexImage2D(
            _GL_TEXTURE_2D, 0, _GL_DEPTH_COMPONENT32F, width, height, 0,
            _GL_DEPTH_COMPONENT, _GL_FLOAT, None,
        )
        fmt = ctypes.c_int(0)
        self.glGetTexLevelParameteriv(
            _GL_TEXTURE_2D, 0, _GL_TEXTURE_INTERNAL_FORMAT, ctypes.byref(fmt)
        )
        err = self.glGetError()
        self.glBindTexture(_GL_TEXTURE_2D, prev.value)
        if err != _GL_NO_ERROR or fmt.value != _GL_DEPTH_COMPONENT32F:
            raise RuntimeError(
                f"could not create a DEPTH_COMPONENT32F texture "
                f"(GL error {err:#x}, internal format {fmt.value:#x})"
            )


def _get_state() -> dict:
    """Create (once) and return the shared context, programs and raw GL."""
    if "error" in _STATE:
        raise RuntimeError(_STATE["error"])
    if "ctx" in _STATE:
        return _STATE
    try:
        import moderngl

        ctx = moderngl.create_context(standalone=True, backend="egl", require=450)
        raw = _RawGL()
        meta_prog = ctx.program(
            vertex_shader=VERTEX_SHADER, fragment_shader=META_FRAGMENT_SHADER
        )
        attr_prog = ctx.program(
            vertex_shader=VERTEX_SHADER, fragment_shader=ATTR_FRAGMENT_SHADER
        )
        # Smoke test the 32F depth path once.
        tex = ctx.depth_texture((1, 1))
        try:
            raw.make_depth32f(tex.glo, 1, 1)
        finally:
            tex.release()
    except Exception as exc:  # noqa: BLE001 - reported through gl_available
        _STATE["error"] = f"{type(exc).__name__}: {exc}"
        raise RuntimeError(_STATE["error"]) from exc
    _STATE.update(
        moderngl=moderngl,
        ctx=ctx,
        raw=raw,
        meta_prog=meta_prog,
        attr_prog=attr_prog,
        renderer=f"{ctx.info['GL_RENDERER']} {ctx.info['GL_VERSION']}",
    )
    return _STATE


def gl_available() -> tuple[bool, str]:
    """Return ``(True, renderer string)`` or ``(False, reason)``; never raises."""
    try:
        st = _get_state()
        return True, st["renderer"]
    except Exception as exc:  # noqa: BLE001
        return False, str(exc) or type(exc).__name__


# --------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------


def _pad4(a: np.ndarray) -> np.ndarray:
    out = np.zeros((a.shape[0], 4), np.float32)
    out[:, : a.shape[1]] = a
    return out


def render_gl(
    clip,
    faces,
    attrs: dict[str, np.ndarray],
    width: int,
    height: int,
    *,
    cull_back: bool = False,
) -> dict[str, np.ndarray]:
    """Rasterize ``faces`` with OpenGL (llvmpipe) and return fragment data.

    Args:
      clip: (V, 4) clip-space positions, written unchanged to gl_Position.
      faces: (F, 3) vertex indices; face f is drawn as primitive f.
      attrs: name -> (V, C) float per-vertex attributes, 1 <= C <= 4,
        interpolated with ``smooth`` (perspective-correct) qualifiers.
      width, height: framebuffer size in pixels (odd sizes are fine).
      cull_back: if True, cull back faces (front = CCW in window coords,
        y up; in the returned image layout, y down, that is CW).

    Returns a dict of numpy arrays in image layout (row 0 = top row):
      "triangle_id": (H, W) int32, gl_PrimitiveID, -1 for background.
      "front_facing": (H, W) bool, gl_FrontFacing (False for background).
      "depth": (H, W) float32, gl_FragCoord.z (1.0 for background).
      "frag_coord": (H, W, 2) float32, gl_FragCoord.xy in window coords
        (y up), i.e. (col + 0.5, height - 1 - row + 0.5) (0 for background).
      for each attribute k, all (H, W, C) float32, 0 for background:
        k: interpolated value;
        k + "_dx_fine", k + "_dy_fine": dFdxFine / dFdyFine;
        k + "_dx_coarse", k + "_dy_coarse": dFdxCoarse / dFdyCoarse;
        k + "_dx", k + "_dy": dFdx / dFdy.
      Derivatives are per window pixel with window y UP.

    Raises RuntimeError if no GL context can be created.
    """
    st = _get_state()
    mgl, ctx, raw = st["moderngl"], st["ctx"], st["raw"]
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError("width and height must be positive")

    clip = np.asarray(clip, np.float32)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if clip.ndim != 2 or clip.shape[1] != 4:
        raise ValueError(f"clip must be (V, 4), got {clip.shape}")
    num_v = clip.shape[0]
    if faces.size and (faces.min() < 0 or faces.max() >= num_v):
        raise ValueError("face index out of range")
    if faces.shape[0] >= 2**24:
        raise ValueError("too many faces for exact float primitive ids")
    attr_arrays = {}
    for name, a in attrs.items():
        a = np.asarray(a, np.float32)
        if a.ndim == 1:
            a = a[:, None]
        if a.ndim != 2 or a.shape[0] != num_v or not 1 <= a.shape[1] <= 4:
            raise ValueError(f"attribute {name!r} must be (V, C), C in 1..4")
        attr_arrays[name] = a
    reserved = {"triangle_id", "front_facing", "depth", "frag_coord"}
    for name in attr_arrays:
        for sfx in _ATTR_SUFFIXES:
            if name + sfx in reserved:
                raise ValueError(f"attribute name {name!r} collides with outputs")

    flat = faces.reshape(-1)  # non-indexed: 3 vertices per face, in order
    n_verts = int(flat.size)
    out: dict[str, np.ndarray] = {}

    to_release = []

    def keep(obj):
        to_release.append(obj)
        return obj

    def read_rgba(tex) -> np.ndarray:
        data = np.frombuffer(tex.read(alignment=1), np.float32)
        return data.reshape(height, width, 4)[::-1].copy()  # GL row 0 = bottom

    try:
        depth = keep(ctx.depth_texture((width, height)))
        raw.make_depth32f(depth.glo, width, height)
        n_targets = 7 if attr_arrays else 2
        targets = [
            keep(ctx.texture((width, height), 4, dtype="f4"))
            for _ in range(n_targets)
        ]
        fbo = keep(ctx.framebuffer(color_attachments=targets, depth_attachment=depth))
        # moderngl refuses empty buffers: upload one dummy vertex if F == 0.
        sel = flat if n_verts else np.zeros(1, np.int64)
        if not num_v:
            clip = np.zeros((1, 4), np.float32)
        pos_buf = keep(ctx.buffer(np.ascontiguousarray(clip[sel]).tobytes()))

        fbo.use()
        ctx.viewport = (0, 0, width, height)
        ctx.disable(mgl.BLEND)
        ctx.enable(mgl.DEPTH_TEST)
        ctx.depth_func = "<"
        ctx.front_face = "ccw"
        if cull_back:
            ctx.enable(mgl.CULL_FACE)
            ctx.cull_face = "back"
        else:
            ctx.disable(mgl.CULL_FACE)

        def draw(prog, attr_buf):
            content = [(pos_buf, "4f", "in_clip")]
            if attr_buf is not None:
                content.append((attr_buf, "4f", "in_attr"))
            vao = keep(ctx.vertex_array(prog, content))
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            if n_verts:
                vao.render(mgl.TRIANGLES, vertices=n_verts)

        # Pass 0: fixed-function outputs (targets 0 and 1).
        draw(st["meta_prog"], None)
        coord = read_rgba(targets[0])
        flags = read_rgba(targets[1])
        covered = flags[..., 1] > 0.5
        out["triangle_id"] = np.where(covered, coord[..., 3], -1).astype(np.int32)
        out["front_facing"] = covered & (flags[..., 0] > 0.5)
        out["depth"] = np.where(covered, coord[..., 2], np.float32(1.0)).astype(
            np.float32
        )
        out["frag_coord"] = np.where(covered[..., None], coord[..., :2], 0).astype(
            np.float32
        )

        # One pass per attribute (7 targets each).
        for name, a in attr_arrays.items():
            c = a.shape[1]
            padded = _pad4(a) if num_v else np.zeros((1, 4), np.float32)
            attr_buf = keep(ctx.buffer(np.ascontiguousarray(padded[sel]).tobytes()))
            draw(st["attr_prog"], attr_buf)
            for sfx, tex in zip(_ATTR_SUFFIXES, targets):
                img = read_rgba(tex)[..., :c]
                out[name + sfx] = np.where(covered[..., None], img, 0).astype(
                    np.float32
                )
    finally:
        for obj in reversed(to_release):
            obj.release()
        ctx.disable(mgl.CULL_FACE)
    return out
