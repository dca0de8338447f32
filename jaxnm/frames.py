r"""Tangent-space frames for normal mapping, and the perturbed normal.

Every method returns a `Frame` ``(T, B, N)`` such that the perturbed normal for a
decoded tangent-space map vector ``m`` (``m.x`` along ``+u``, ``m.y`` along
``+v``, ``m.z`` along ``N``) is

.. math:: N' = \operatorname{normalize}(T\, m_x + B\, m_y + N\, m_z)

(`perturb_normal`). The methods (static string ``frame=`` of `compute_frame`):

- ``"cotangent"`` (`cotangent_frame`): Schüler's per-pixel cotangent frame from
  screen-space derivatives, exactly as published (2013). ``T`` and ``B`` are
  the gradients of ``u`` and ``v`` (covectors), not ``dp/du``, ``dp/dv``.
- ``"nonperspective"`` (`nonperspective_frame`): the article's "non-perspective
  optimisation", where the perpendiculars are replaced by the edges.
- ``"exact"`` (`exact_frame`): the 3x3 solution from the pixel's own triangle
  (the geometry-shader variant).
- ``"vertex"`` (`mikktspace_frame`): precomputed MikkTSpace tangents per face
  corner (`jaxnm.tangents`, what Blender, Substance, xNormal, Unity, Unreal and
  glTF bake and decode with), reconstructed per pixel as the reference prescribes.
- ``"vertex_area"`` (`vertex_tangents` + `vertex_frame`): precomputed per-vertex
  tangents with a handedness sign, Gram-Schmidt per pixel.
- ``"axis"`` (`axis_frame`): the fixed-axis approximation (GLSL Hacker); it
  ignores the uv mapping.
- ``"gram_schmidt"`` (`gram_schmidt_frame`) and ``"separate"`` (`separate_frame`):
  Schüler's frame made orthonormal, or with ``T`` and ``B`` each made unit, as
  engines often ship it.
- ``"cross"`` (`cross_frame`): the cross-product tangent quoted in the article's
  comments (devsh, 2018), with ``B = N x T``.
- ``"surface_gradient"`` (`surface_gradient_frame`): the per-pixel basis of
  Mikkelsen's surface-gradient framework (2020), orthonormal, in MikkTSpace's
  convention.
- ``"cotangent_unnormalized"``: ``"cotangent"`` with ``normalize="none"`` (the
  true gradients of u and v); ``"exact_face"``: ``"exact"`` with the triangle's
  face normal; ``"none"``: ``T = B = 0`` (no perturbation).

**Conventions.** Screen derivatives are jaxnm's (`jaxnm.interpolate`):
``dp1 = dFdx(p)`` per pixel step to the right, ``dp2 = dFdy(p)`` per pixel step
*up* in window coordinates (OpenGL). ``p`` may be the world position or the
camera-relative position ``p - eye`` (Schüler's ``-V``): only differences enter.
``N`` is the unit interpolated normal; `compute_frame` normalises it.

**Degenerate input** (zero uv derivatives, zero ``N``, background/helper
pixels, grazing views, back faces) never gives NaN or Inf, in value or
gradient: a frame whose ``T`` and ``B`` cannot be formed returns ``T = B = 0``,
so `perturb_normal` returns ``normalize(N m.z)``, the unperturbed normal (for
``m.z > 0``); where even that vanishes it returns its ``fallback``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .interpolate import Attribute
from .numerics import cross as _cross
from .numerics import dot as _ndot
from .numerics import eps, safe_norm, safe_normalize, safe_rsqrt, spread, tiny

__all__ = [
    "FRAMES", "FRAME_ALIASES", "SCREEN_FRAMES", "Frame", "FrameInputs", "FrameOptions",
    "canonical_frame", "check_frame",
    "axis_frame",
    "compute_frame", "cotangent_frame",
    "exact_frame", "face_forward", "nonperspective_frame", "perturb_normal", "vertex_frame",
    "vertex_tangents", "mikktspace_frame", "gram_schmidt_frame", "separate_frame", "cross_frame",
    "surface_gradient_frame"
]

#: The frame methods (`compute_frame`, the scene key ``frame``, ``--frame``).
FRAMES = ("cotangent", "cotangent_unnormalized", "nonperspective", "exact", "exact_face",
          "vertex", "vertex_area", "axis", "gram_schmidt", "separate", "cross",
          "surface_gradient", "none")
#: Other names users know frames by, accepted by the command line and in scene files:
#: MikkTSpace is the per-vertex tangent frame, Schüler's the screen-space cotangent frame.
FRAME_ALIASES = {"mikktspace": "vertex", "schuler": "cotangent",
                 "schueler": "cotangent", "schüler": "cotangent"}
#: The methods that take screen-space derivatives of the position and the uv.
SCREEN_FRAMES = ("cotangent", "cotangent_unnormalized", "nonperspective", "gram_schmidt",
                 "separate", "cross", "surface_gradient")
_NORMALIZE_MODES = ("max", "none")

#: A summed per-vertex tangent shorter than this fraction of the summed face weights
#: (the face tangents around the vertex cancel, e.g. on a mirrored-uv seam) is invalid.
_VERTEX_TANGENT_CANCELLATION = 1e-3


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Frame:
    """A tangent-space frame; the perturbed normal is ``normalize(T m.x + B m.y + N m.z)``.

    **Fields** (each ``(..., 3)``):
    - `T`: the vector multiplying ``m.x`` (``+u`` direction; for the cotangent
      methods a scaled gradient of ``u``).
    - `B`: the vector multiplying ``m.y`` (``+v`` direction).
    - `N`: the unperturbed normal.
    """

    T: Array
    B: Array
    N: Array

    @property
    def matrix(self) -> Array:
        """``(..., 3, 3)`` with columns ``T, B, N`` (GLSL ``mat3(T, B, N)``)."""
        return jnp.stack([self.T, self.B, self.N], -1)

    @property
    def handedness(self) -> Array:
        """``(...)`` triple product ``det[T, B, N] = (T x B) . N``; its sign is the handedness."""
        return _dot(_cross(self.T, self.B), self.N)


# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------


def _dot(a: Array, b: Array, keepdims: bool = False) -> Array:
    return _ndot(a, b, keepdims=keepdims)


def _check_normalize(normalize: str) -> None:
    if normalize not in _NORMALIZE_MODES:
        raise ValueError(f"unknown normalize mode {normalize!r}; expected one of "
                         f"{', '.join(_NORMALIZE_MODES)}")


def _check_ddy_sign(ddy_sign: int) -> None:
    if ddy_sign not in (1, -1):
        raise ValueError(f"ddy_sign must be 1 (GLSL dFdy, window y up) or -1 (HLSL ddy, y down), "
                         f"got {ddy_sign!r}")


def _max_normalize(T: Array, B: Array) -> tuple[Array, Array]:
    r"""Schüler's scale-invariant normalisation ``(T, B) / sqrt(max(T.T, B.B))``.

    ``T`` and ``B`` are first divided by their largest absolute component (a
    constant for AD, which is exact because the result does not depend on it),
    so ``T.T`` cannot underflow in float32 close-ups; ``T = B = 0`` stays zero.
    """
    aT, aB = jnp.abs(T), jnp.abs(B)
    s = jnp.maximum(jnp.maximum(jnp.maximum(aT[..., 0:1], aT[..., 1:2]), aT[..., 2:3]),
                    jnp.maximum(jnp.maximum(aB[..., 0:1], aB[..., 1:2]), aB[..., 2:3]))
    s = jax.lax.stop_gradient(s)
    ok = s > tiny(T.dtype)
    s_safe = jnp.where(ok, s, jnp.ones_like(s))
    T1, B1 = T / s_safe, B / s_safe
    m = jnp.maximum(_dot(T1, T1, True), _dot(B1, B1, True))  # in [1, 2] where ok
    inv = safe_rsqrt(jnp.where(ok, m, jnp.ones_like(m)))
    return jnp.where(ok, T1 * inv, 0.0), jnp.where(ok, B1 * inv, 0.0)


def _relative_div(T: Array, B: Array, det: Array, scale: Array) -> tuple[Array, Array]:
    """``(T, B) / det`` where ``|det| > eps * scale``, else zero (double where)."""
    ok = jnp.abs(det) > eps(det.dtype) * scale
    ok = ok & (jnp.abs(det) > tiny(det.dtype))
    d = jnp.where(ok, det, jnp.ones_like(det))
    return jnp.where(ok, T / d, 0.0), jnp.where(ok, B / d, 0.0)


def _low_precision(dtype) -> bool:
    return jnp.dtype(dtype) in (jnp.float16, jnp.bfloat16)


def _scaled_pair(a: Array, b: Array) -> tuple[Array, Array]:
    """``a`` and ``b`` divided by their largest absolute component (a constant for AD)."""
    m = jnp.maximum(jnp.max(jnp.abs(a), -1, keepdims=True),
                    jnp.max(jnp.abs(b), -1, keepdims=True))
    m = jax.lax.stop_gradient(jnp.where(m > 0, m, jnp.ones_like(m)))
    return a / m, b / m


def _prescaled(dp1: Array, dp2: Array, duv1: Array, duv2: Array):
    """``dp`` and ``duv`` each scaled by `_scaled_pair`.

    For the max-normalised frames only, and only in half precision: there ``T`` and ``B``
    are products of a position and a uv difference, and for per-pixel differences (say
    0.02 and 0.005) that product is a float16 subnormal or zero; ``T`` and ``B`` are
    bilinear in ``(dp, duv)``, so the max-normalised frame does not change, and every
    product stays a normal number. (float32 keeps the published arithmetic.)"""
    return (*_scaled_pair(dp1, dp2), *_scaled_pair(duv1, duv2))


def _cotangent_TB(N: Array, dp1: Array, dp2: Array, duv1: Array, duv2: Array,
                  normalize: str) -> tuple[Array, Array]:
    """The published solution of the linear system, then the chosen normalisation."""
    if normalize == "max" and _low_precision(dp1.dtype):
        dp1, dp2, duv1, duv2 = _prescaled(dp1, dp2, duv1, duv2)
    dp2perp = _cross(dp2, N)
    dp1perp = _cross(N, dp1)
    T = dp2perp * duv1[..., 0:1] + dp1perp * duv2[..., 0:1]
    B = dp2perp * duv1[..., 1:2] + dp1perp * duv2[..., 1:2]
    if normalize == "max":
        return _max_normalize(T, B)
    # det [dp1; dp2; N] = dp1 . (dp2 x N) = N . (dp1 x dp2): the 3x3 system's determinant
    det = _dot(dp1, dp2perp, True)
    scale = safe_norm(dp1, keepdims=True) * safe_norm(dp2, keepdims=True) * safe_norm(
        N, keepdims=True)
    return _relative_div(T, B, det, scale)


def _axis_tangent(n: Array) -> Array:
    """GLSL Hacker's tangent: the longer of ``n x (0,0,1)`` and ``n x (0,1,0)``, normalised."""
    nx, ny, nz = n[..., 0:1], n[..., 1:2], n[..., 2:3]
    zero = jnp.zeros_like(nx)
    c1 = jnp.concatenate([ny, -nx, zero], -1)  # n x z, |c1|^2 = nx^2 + ny^2
    c2 = jnp.concatenate([-nz, zero, nx], -1)  # n x y, |c2|^2 = nx^2 + nz^2
    return safe_normalize(jnp.where(ny * ny > nz * nz, c1, c2))


# --------------------------------------------------------------------------------------
# the methods
# --------------------------------------------------------------------------------------


def cotangent_frame(N: Float[ArrayLike, "*#batch 3"], dp1: Float[ArrayLike, "*#batch 3"],
                    dp2: Float[ArrayLike, "*#batch 3"], duv1: Float[ArrayLike, "*#batch 2"],
                    duv2: Float[ArrayLike, "*#batch 2"], *,
                    normalize: str = "max", ddy_sign: int = 1) -> Frame:
    r"""Schüler's cotangent frame from screen-space derivatives (exactly as published).

    .. code-block:: glsl

        vec3 dp2perp = cross(dp2, N);  vec3 dp1perp = cross(N, dp1);
        vec3 T = dp2perp * duv1.x + dp1perp * duv2.x;
        vec3 B = dp2perp * duv1.y + dp1perp * duv2.y;
        float invmax = inversesqrt(max(dot(T, T), dot(B, B)));
        return mat3(T * invmax, B * invmax, N);

    This is the adjugate of the system ``T.dp1 = du1, T.dp2 = du2, T.N = 0``
    (likewise ``B`` with ``v``) without its determinant
    ``D = det[dp1; dp2; N] = N . (dp1 x dp2)``. The true solution is
    ``T/D = grad u`` and ``B/D = grad v`` (the gradients along the plane
    orthogonal to ``N``; the exact gradients when ``N`` is the face normal).

    **Arguments:**
    - `N`: ``(..., 3)`` unit normal (not renormalised, as in the GLSL).
    - `dp1`, `dp2`: ``(..., 3)`` ``dFdx(p)``, ``dFdy(p)`` (world or camera-relative ``p``).
    - `duv1`, `duv2`: ``(..., 2)`` ``dFdx(uv)``, ``dFdy(uv)``.
    - `normalize`: ``"max"`` (published): ``(T, B) / sqrt(max(T.T, B.B))``,
      invariant to scaling uv or world space; keeps the *sign* of ``D``, which
      is positive when ``N`` faces the viewer (``dp1 x dp2`` points at the eye
      for GL's y-up derivatives). ``"none"``: ``(T, B) / D``, the true gradients:
      the bump strength then scales with uv density / geometry size. Where
      ``|D| <= eps |dp1||dp2||N|`` (grazing, degenerate) ``T = B = 0``.
    - `ddy_sign`: ``-1`` emulates a naive port to HLSL, whose ``ddy`` is
      ``-dFdy`` (window y down): ``dp2 -> -dp2`` and ``duv2 -> -duv2``. Both
      terms of ``T`` (and of ``B``) change sign while ``|D|`` does not enter,
      so with ``"max"`` the frame becomes ``(-T, -B, N)``: the handedness
      ``det[T, B, N]`` is *unchanged* (neither T nor B flips alone) and the
      tangential part of the perturbation is negated (the map rotated by 180
      degrees about N: bumps read as dents). With ``"none"`` ``D`` changes sign
      too and the frame is unchanged.

    Within one triangle, ``"fine"``, ``"coarse"`` and ``"analytic"`` derivatives give
    the same frame up to rounding: the pixel triangle lies in the facet's plane and
    uv is affine on it, so every footprint yields the facet's gradients (with
    ``N`` the face normal: exactly `exact_frame`). ``"gbuffer"`` derivatives differ
    where a quad straddles triangle edges.

    **Returns:** a `Frame` ``(T, B, N)``; ``T = B = 0`` where the uv derivatives vanish.
    """
    _check_normalize(normalize)
    _check_ddy_sign(ddy_sign)
    if ddy_sign == -1:
        dp2, duv2 = -dp2, -duv2
    T, B = _cotangent_TB(N, dp1, dp2, duv1, duv2, normalize)
    return Frame(T, B, N)


def nonperspective_frame(N: Array, dp1: Array, dp2: Array, duv1: Array, duv2: Array, *,
                         normalize: str = "max", ddy_sign: int = 1) -> Frame:
    r"""The article's "non-perspective optimisation" of `cotangent_frame`.

    The perpendiculars are replaced by the edges themselves
    (``dp2perp -> dp1``, ``dp1perp -> dp2``):

    .. math:: T = dp_1\, du_1 + dp_2\, du_2, \qquad B = dp_1\, dv_1 + dp_2\, dv_2,

    i.e. ``T = J J^T grad u`` with ``J = [dp1 dp2]`` the screen-to-surface
    Jacobian. It is exact (up to scale) only where ``J^T J`` is a multiple of
    the identity, ``dp1 _|_ dp2`` and ``|dp1| = |dp2|``: the surface is seen
    without *any* foreshortening (parallel to the image plane). Under
    perspective, and also for a tilted surface under an orthographic camera,
    it is wrong. ``T`` and ``B`` are not made orthogonal to ``N``. (The frame
    from devsh's comment on the article, ``normalize(dFdx(v) dFdy(p) - dFdx(p)
    dFdy(v))`` orthogonalised against ``N`` and ``B = N x T``, is a different
    shortcut: its ``T`` is the exact direction of ``dp/du``, but it assumes an
    orthogonal, unstretched mapping; both agree with `cotangent_frame` in that case.)

    **Arguments:** as `cotangent_frame`. ``normalize="none"`` divides by
    ``|dp1 x dp2|`` (``= |dp1|^2`` in the exact case). ``ddy_sign=-1`` has no
    effect: every term is a product ``dp2 * duv2``.

    **Returns:** a `Frame` ``(T, B, N)``.
    """
    _check_normalize(normalize)
    _check_ddy_sign(ddy_sign)
    if ddy_sign == -1:
        dp2, duv2 = -dp2, -duv2
    if normalize == "max" and _low_precision(dp1.dtype):
        dp1, dp2, duv1, duv2 = _prescaled(dp1, dp2, duv1, duv2)
    T = dp1 * duv1[..., 0:1] + dp2 * duv2[..., 0:1]
    B = dp1 * duv1[..., 1:2] + dp2 * duv2[..., 1:2]
    if normalize == "max":
        T, B = _max_normalize(T, B)
    else:
        area = safe_norm(_cross(dp1, dp2), keepdims=True)
        scale = safe_norm(dp1, keepdims=True) * safe_norm(dp2, keepdims=True)
        T, B = _relative_div(T, B, area, scale)
    return Frame(T, B, N)


def gram_schmidt_frame(N: Array, dp1: Array, dp2: Array, duv1: Array, duv2: Array, *,
                       ddy_sign: int = 1) -> Frame:
    r"""Schüler's frame (`cotangent_frame`) made orthonormal by Gram-Schmidt.

    .. math:: T' = \operatorname{normalize}(T - N (N \cdot T)), \qquad
              B' = \operatorname{normalize}(B - N (N \cdot B) - T' (T' \cdot B))

    ``T'`` is the direction of ``grad u``; ``B'`` is the part of ``grad v``
    orthogonal to it, which is the direction of ``dp/dv`` (``dp/dv`` is
    orthogonal to ``grad u``). So it is neither of the two conventions where the
    uv is sheared: the gradient frame's ``B`` and MikkTSpace's ``T`` differ from
    it by the shear angle. Engines orthonormalise so that the transpose is the
    inverse (the article's comments discuss why that is not so otherwise).

    **Arguments:** as `cotangent_frame` (``normalize="max"``).

    **Returns:** an orthonormal `Frame` (``T = B = 0`` where Schüler's are zero);
    it keeps the sign of Schüler's ``T`` and ``B`` (negative on back faces).
    """
    f = cotangent_frame(N, dp1, dp2, duv1, duv2, ddy_sign=ddy_sign)
    T = safe_normalize(f.T - N * _dot(N, f.T, True))
    b = f.B - N * _dot(N, f.B, True)
    B = safe_normalize(b - T * _dot(T, b, True))
    return Frame(T, B, N)


def separate_frame(N: Array, dp1: Array, dp2: Array, duv1: Array, duv2: Array, *,
                   ddy_sign: int = 1) -> Frame:
    r"""Schüler's frame with ``T`` and ``B`` normalised separately.

    ``T = normalize(grad u)``, ``B = normalize(grad v)`` (each with the sign of
    ``D`` as in `cotangent_frame`): the directions of the gradient frame, but each
    of unit length, where Schüler divides both by the longer one. Where ``u`` and
    ``v`` are scaled unequally (a stretched uv) the map's x and y are then weighted
    as if they were not.

    **Arguments:** as `cotangent_frame` (``normalize="max"``).

    **Returns:** a `Frame` with unit ``T``, ``B`` (not orthogonal where the uv is sheared).
    """
    f = cotangent_frame(N, dp1, dp2, duv1, duv2, ddy_sign=ddy_sign)
    return Frame(safe_normalize(f.T), safe_normalize(f.B), N)


def _dp_du_direction(dp1: Array, dp2: Array, duv1: Array, duv2: Array) -> tuple[Array, Array]:
    """``dp1 dv2 - dp2 dv1`` (``= D_uv dp/du`` with ``D_uv = du1 dv2 - du2 dv1``) and ``D_uv``."""
    t = dp1 * duv2[..., 1:2] - dp2 * duv1[..., 1:2]
    det = duv1[..., 0:1] * duv2[..., 1:2] - duv2[..., 0:1] * duv1[..., 1:2]
    return t, det


def cross_frame(N: Array, dp1: Array, dp2: Array, duv1: Array, duv2: Array, *,
                ddy_sign: int = 1) -> Frame:
    r"""The cross-product tangent from the comments on Schüler's article (devsh, 2018).

    The comment's GLSL reads

    .. code-block:: glsl

        vec3 t = dFdx(uv.y) * dFdy(p) - dFdx(p) * dFdy(uv.y);
        T = normalize(t - N * dot(N, t));  B = cross(N, T);

    **Its sign.** With ``J = [dp1 dp2]`` and the uv Jacobian
    ``M = [[du1, du2], [dv1, dv2]]`` (``D_uv = det M``), ``dp/du = J M^{-1} e_1
    = (dp1 dv2 - dp2 dv1) / D_uv``, so the comment's ``t`` is
    ``-D_uv dp/du``. With GL's y-up derivatives a front face with an unmirrored
    uv has ``D_uv > 0``: as written, ``T`` is ``-dp/du`` and ``B = N x T`` is
    ``-dp/dv``'s direction, the map turned by 180 degrees (bumps read as dents).
    With y-down derivatives (HLSL ``ddy``, Vulkan) ``D_uv < 0`` and the comment is
    right. This function is written for jaxnm's y-up derivatives:
    ``t = dp1 dv2 - dp2 dv1`` (``ddy_sign=-1`` gives the comment's expression on
    GL derivatives). ``B = N x T`` carries no handedness, so where the uv is
    mirrored (``D_uv < 0`` on a front face) ``T`` is reversed and ``B`` is right.

    ``T`` is the exact direction of ``dp/du`` (projected on the plane normal to
    ``N``) and ``B`` the right-handed normal to it: MikkTSpace's orthonormal
    convention for unmirrored uv (see `surface_gradient_frame` for the signed one).

    **Arguments:** as `cotangent_frame`.

    **Returns:** an orthonormal `Frame`; ``T = B = 0`` where ``t`` vanishes.
    """
    _check_ddy_sign(ddy_sign)
    if ddy_sign == -1:
        dp2, duv2 = -dp2, -duv2
    t, _ = _dp_du_direction(dp1, dp2, duv1, duv2)
    T = safe_normalize(t - N * _dot(N, t, True))
    return Frame(T, _cross(N, T), N)


def surface_gradient_frame(N: Array, dp1: Array, dp2: Array, duv1: Array, duv2: Array, *,
                           ddy_sign: int = 1) -> Frame:
    r"""The per-pixel tangent basis of Mikkelsen's surface-gradient framework (2020).

    Mikkelsen, "Surface Gradient-Based Bump Mapping Framework" (JCGT 9(3), 2020)
    writes every bump as a surface gradient ``g`` and resolves
    ``N' = normalize(N - g)``. A tangent-space map value ``m`` is the height
    derivative ``(dh/ds, dh/dt) = (-m_x / m_z, -m_y / m_z)`` along the basis, so
    ``g = -(m_x T + m_y B) / m_z`` and ``N - g = (m_x T + m_y B + m_z N) / m_z``:
    for ``m_z > 0`` `perturb_normal` with this frame gives the resolved normal.
    Without vertex tangents the paper builds the basis from screen derivatives:
    the surface derivatives ``sigma_x = dp1 - N (N . dp1)``, ``sigma_y``
    likewise, combined by the inverse uv Jacobian, which gives the direction of
    ``dp/du`` on the plane normal to ``N``:

    .. math:: T = \operatorname{normalize}(\operatorname{sign}(D_{uv})\,
              (\sigma_x dv_2 - \sigma_y dv_1)), \qquad
              B = s\, N \times T,\quad s = \operatorname{sign}(D_{uv})
              \operatorname{sign}(N \cdot (dp_1 \times dp_2))

    with ``D_uv = du1 dv2 - du2 dv1``. ``s`` is the uv's handedness on the
    surface (``sign((dp/du x dp/dv) . N)``), so mirrored uvs are decoded as
    MikkTSpace decodes them: on a plane this is MikkTSpace's orthonormal frame
    exactly, from screen derivatives alone (whereas `cross_frame` has no ``s``).

    **Arguments:** as `cotangent_frame`.

    **Returns:** an orthonormal `Frame`, oriented by the surface (not by the view);
    ``T = B = 0`` where the uv derivatives are degenerate.
    """
    _check_ddy_sign(ddy_sign)
    if ddy_sign == -1:
        dp2, duv2 = -dp2, -duv2
    t, det = _dp_du_direction(dp1, dp2, duv1, duv2)
    sd = jnp.where(det < 0, -1.0, 1.0).astype(t.dtype)
    T = safe_normalize(sd * (t - N * _dot(N, t, True)))
    facing = jnp.where(_dot(N, _cross(dp1, dp2), True) < 0, -1.0, 1.0).astype(t.dtype)
    B = (sd * facing) * _cross(N, T)
    ok = jnp.abs(det) > 0
    return Frame(jnp.where(ok, T, 0.0), jnp.where(ok, B, 0.0), N)


def exact_frame(tri_p: Array, tri_uv: Array, N: Array | None = None, *,
                use_face_normal: bool = False, normalize: str = "max") -> Frame:
    r"""The cotangent frame from the triangle's own edges (the geometry-shader variant).

    With ``dp_1 = p_1 - p_0``, ``dp_2 = p_2 - p_0`` (and ``duv`` likewise) this
    solves the article's 3x3 system

    .. math:: T \cdot dp_1 = du_1, \quad T \cdot dp_2 = du_2, \quad T \cdot n = 0

    (``B`` likewise with ``v``) by the same perpendiculars as `cotangent_frame`:
    ``T = (cross(dp2, n) du1 + cross(n, dp1) du2) / D`` with ``D = n . (dp1 x dp2)``.
    With ``n`` the face normal, ``T = grad u`` and ``B = grad v`` within the
    triangle's plane, exactly, whatever the camera.

    **Arguments:**
    - `tri_p`: ``(..., 3, 3)`` the triangle's corner positions
      (`jaxnm.interpolate.triangle_corners`).
    - `tri_uv`: ``(..., 3, 2)`` the corner uvs.
    - `N`: ``(..., 3)`` unit interpolated normal, or None for the face normal.
      It is the frame's ``N``, and builds the perpendiculars unless
      ``use_face_normal``.
    - `use_face_normal`: build the perpendiculars with the unit face normal
      ``normalize(dp1 x dp2)`` even when `N` is given (``N`` stays the frame's
      normal: faceted T and B, smooth N).
    - `normalize`: ``"max"`` or ``"none"`` as in `cotangent_frame`. ``D`` is
      positive when ``n`` is on the counter-clockwise side of the triangle,
      independently of the view.

    **Returns:** a `Frame`; zero ``T``, ``B`` for degenerate triangles.
    """
    _check_normalize(normalize)
    tri_p = jnp.asarray(tri_p)
    tri_uv = jnp.asarray(tri_uv)
    dp1 = tri_p[..., 1, :] - tri_p[..., 0, :]
    dp2 = tri_p[..., 2, :] - tri_p[..., 0, :]
    duv1 = tri_uv[..., 1, :] - tri_uv[..., 0, :]
    duv2 = tri_uv[..., 2, :] - tri_uv[..., 0, :]
    face_n = None
    if N is None or use_face_normal:
        # in half precision a small triangle's |dp1 x dp2|^2 underflows: scale the edges first
        e1, e2 = _scaled_pair(dp1, dp2) if _low_precision(dp1.dtype) else (dp1, dp2)
        face_n = safe_normalize(_cross(e1, e2))
    n = N if face_n is None else face_n
    T, B = _cotangent_TB(n, dp1, dp2, duv1, duv2, normalize)
    return Frame(T, B, face_n if N is None else N)


def vertex_tangents(positions: Array, normals: Array, uv: Array, faces: Array) -> Array:
    r"""Per-vertex tangents with handedness, the traditional (Lengyel / MikkTSpace-like) way.

    Per triangle, with edges ``e_1, e_2``, uv edges ``(du_i, dv_i)`` and
    ``r = du_1 dv_2 - du_2 dv_1``, the tangent ``dp/du`` and bitangent
    ``dp/dv`` are

    .. math:: t = (e_1 dv_2 - e_2 dv_1) / r, \qquad b = (e_2 du_1 - e_1 du_2) / r.

    Their *unit* directions are accumulated at the triangle's three vertices,
    weighted by the triangle's world-space area (so neither sliver triangles nor
    the uv density decide the average). Triangles with a degenerate uv mapping
    (``|r| <= eps (|duv_1|^2 + |duv_2|^2)``) contribute nothing. The sum is
    made orthogonal to the unit vertex normal (Gram-Schmidt) and normalised;
    the handedness is ``w = sign((N x T) . b_sum)`` (``+1`` when that is 0).

    A vertex whose summed tangent is shorter than 1e-3 times its summed weights (no valid
    triangle, tangents parallel to ``N``, or cancelling tangents on a shared mirrored-uv
    seam) gets the deterministic fallback `axis_frame` tangent of its normal (zero if the
    normal is zero).

    **Arguments:**
    - `positions`: ``(V, 3)``; `normals`: ``(V, 3)``; `uv`: ``(V, 2)``; `faces`: ``(F, 3)`` int.

    **Returns:** ``(V, 4)``: unit tangent ``xyz`` and handedness ``w = +-1``.
    Interpolate it and pass it to `vertex_frame`.
    """
    positions = jnp.asarray(positions)
    uv = jnp.asarray(uv, positions.dtype)
    faces = jnp.asarray(faces, jnp.int32)
    n = safe_normalize(jnp.asarray(normals, positions.dtype))
    p = positions[faces]  # (F, 3, 3)
    t = uv[faces]  # (F, 3, 2)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    r = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    valid = jnp.abs(r) > eps(positions.dtype) * (_dot(d1, d1) + _dot(d2, d2))
    sgn = jnp.where(valid, jnp.sign(r), 0.0)[:, None]
    t_dir = safe_normalize((e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * sgn)
    b_dir = safe_normalize((e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * sgn)
    area = 0.5 * safe_norm(_cross(e1, e2))
    wgt = jnp.where(valid, area, 0.0)[:, None]
    idx = faces.reshape(-1)
    num_v = positions.shape[0]

    def scatter(x):  # (F, C) per face -> (V, C), added at each of the 3 corners
        x3 = jnp.broadcast_to(x[:, None, :], (x.shape[0], 3, x.shape[1])).reshape(-1, x.shape[1])
        return jnp.zeros((num_v, x.shape[1]), x.dtype).at[idx].add(x3)

    t_sum = scatter(wgt * t_dir)
    b_sum = scatter(wgt * b_dir)
    w_sum = scatter(wgt)
    t_perp = t_sum - n * _dot(n, t_sum, True)
    ok = (safe_norm(t_perp, keepdims=True) > _VERTEX_TANGENT_CANCELLATION * w_sum) & (w_sum > 0)
    fallback = _axis_tangent(n)
    T = jnp.where(ok, safe_normalize(t_perp, fallback=fallback), fallback)
    hand = jnp.where(_dot(_cross(n, T), b_sum, True) < 0, -1.0, 1.0).astype(T.dtype)
    return jnp.concatenate([T, hand], -1)


def vertex_frame(T_interp: Array, w_interp: Array, N: Array) -> Frame:
    r"""Frame from an interpolated per-vertex tangent (see `vertex_tangents`).

    ``T = normalize(T_i - N (N . T_i))`` (re-orthogonalised per pixel, as the
    interpolated tangent is neither unit nor orthogonal to the interpolated
    normal), ``B = sign(w) (N x T)`` with ``sign(0) = +1``, ``N = normalize(N)``.
    Where the projected tangent vanishes the `axis_frame` tangent is used.

    **Arguments:**
    - `T_interp`: ``(..., 3)`` interpolated tangent.
    - `w_interp`: ``(...)`` or ``(..., 1)`` interpolated handedness.
    - `N`: ``(..., 3)`` interpolated normal.

    **Returns:** an orthonormal `Frame`, all zero where ``N`` is zero.
    """
    T_interp = jnp.asarray(T_interp)
    w_interp = jnp.asarray(w_interp)
    if w_interp.ndim == T_interp.ndim:
        w_interp = w_interp[..., 0]
    n = safe_normalize(N)
    t = T_interp - n * _dot(n, T_interp, True)
    T = safe_normalize(t, fallback=_axis_tangent(n))
    T = jnp.where(_dot(n, n, True) > 0, T, 0.0)
    s = jnp.where(w_interp < 0, -1.0, 1.0).astype(T.dtype)[..., None]
    return Frame(T, s * _cross(n, T), n)


def mikktspace_frame(T_interp: Array, w_interp: Array, N_interp: Array) -> Frame:
    r"""The pixel-shader side of MikkTSpace: the frame a tangent-space map baked in
    MikkTSpace must be decoded with.

    .. math:: B = \operatorname{sign}(w)\, N \times T, \qquad
              n' = \operatorname{normalize}(m_x T + m_y B + m_z N)

    with ``T`` and ``N`` the interpolated tangent and normal *as interpolated*
    (neither normalised nor re-orthogonalised: the reference's "bakers that follow
    it" decode this way), ``sign(0) = +1``.

    **Arguments:**
    - `T_interp`: ``(..., 3)`` interpolated per-corner tangent (`jaxnm.tangents`).
    - `w_interp`: ``(...)`` or ``(..., 1)`` interpolated sign.
    - `N_interp`: ``(..., 3)`` interpolated vertex normal.

    **Returns:** a `Frame` for `perturb_normal` (not orthonormal in general).
    """
    T = jnp.asarray(T_interp)
    w = jnp.asarray(w_interp)
    if w.ndim == T.ndim:
        w = w[..., 0]
    N = jnp.asarray(N_interp)
    s = jnp.where(w < 0, -1.0, 1.0).astype(T.dtype)[..., None]
    return Frame(T, s * _cross(N, T), N)


def axis_frame(N: Array) -> Frame:
    r"""GLSL Hacker's fixed-axis approximation; ignores the uv mapping entirely.

    ``c1 = N x (0,0,1)``, ``c2 = N x (0,1,0)``, ``T = normalize(the longer one)``
    (``c2`` on a tie), ``B = normalize(N x T)``, ``N = normalize(N)``. ``T``
    jumps where ``|c1| = |c2|`` (the visible seam lines of the method).

    **Returns:** an orthonormal `Frame` (zero where ``N`` is zero).
    """
    n = safe_normalize(N)
    T = _axis_tangent(n)
    return Frame(T, safe_normalize(_cross(n, T)), n)


# --------------------------------------------------------------------------------------
# using frames
# --------------------------------------------------------------------------------------


def perturb_normal(frame: Frame, m: Float[ArrayLike, "*#batch 3"], *,
                   fallback: Float[ArrayLike, "*#batch 3"] | None = None) -> Float[Array, ...]:
    r"""``normalize(T m.x + B m.y + N m.z)`` (GLSL ``normalize(TBN * map)``).

    **Arguments:**
    - `frame`: a `Frame` ``(..., 3)``.
    - `m`: ``(..., 3)`` decoded tangent-space map vector.
    - `fallback`: ``(..., 3)`` returned where the sum is (numerically) zero;
      defaults to ``normalize(frame.N)`` (the unperturbed normal; zero if N is).

    **Returns:** ``(..., 3)`` unit perturbed normals.
    """
    m = jnp.asarray(m)
    # (`spread`: a gradient with respect to the map without reductions over the minor axis)
    v = frame.T * spread(m[..., 0:1]) + frame.B * spread(m[..., 1:2]) + frame.N * spread(
        m[..., 2:3])
    if fallback is None:
        fallback = safe_normalize(frame.N)
    return safe_normalize(v, fallback=fallback)


def face_forward(frame: Frame, front_facing: Array) -> Frame:
    r"""Flip ``T``, ``B`` *and* ``N`` of back-facing fragments (double-sided surfaces).

    The perturbed normal of a back-facing fragment becomes exactly the negative
    of the front side's: a thin sheet whose front has a bump has a dent at the
    back, and the back is lit with the reversed normal. The handedness
    ``det[T, B, N]`` changes sign, as it must: seen from behind, the uv layout
    is mirrored (a decal seen through glass); for vertex tangents this is
    ``w -> -w`` with ``B = w (N x T)`` for the flipped ``N`` and ``T``. Flipping
    ``N`` alone would keep the bump a bump on both sides.

    The input must be *oriented by the surface*: ``T``, ``B`` along ``+grad u``,
    ``+grad v`` on both sides. All methods are, when built from the unflipped
    interpolated normal, except `cotangent_frame` with ``normalize="max"``,
    whose ``T``, ``B`` carry ``sign(N . (dp1 x dp2))``, negative on back
    faces; `compute_frame` re-orients it first (net effect: only its ``N``
    flips). This is three.js' recipe (``normal *= faceDirection`` before the
    frame is built, then ``tbn[0], tbn[1] *= faceDirection``).

    **Arguments:**
    - `frame`: ``(..., 3)`` fields.
    - `front_facing`: ``(...)`` bool (`Fragments.front_facing`).
    """
    s = jnp.where(jnp.asarray(front_facing)[..., None], 1.0, -1.0).astype(frame.N.dtype)
    return Frame(frame.T * s, frame.B * s, frame.N * s)


_SCREEN_VARIANTS = {"gram_schmidt": gram_schmidt_frame, "separate": separate_frame,
                    "cross": cross_frame, "surface_gradient": surface_gradient_frame}
# the frames whose T and B carry the sign of the screen orientation (negative on back faces)
_VIEW_ORIENTED = ("gram_schmidt", "separate", "cross")


def _value(x):
    return x.value if isinstance(x, Attribute) else jnp.asarray(x)


def _derivs(attr, name: str, frame: str):
    if not isinstance(attr, Attribute) or attr.ddx is None or attr.ddy is None:
        raise ValueError(f"compute_frame(frame={frame!r}) needs `{name}` as an Attribute with "
                         "ddx and ddy (interpolate with derivatives other than 'none')")
    return attr.ddx, attr.ddy


def check_frame(frame: str) -> None:
    """Raise a `ValueError` unless ``frame`` is one of `FRAMES`."""
    if frame not in FRAMES:
        raise ValueError(f"unknown frame {frame!r}; expected one of {', '.join(FRAMES)}"
                         + _alias_hint(frame))


def _alias_hint(frame) -> str:
    """``"; 'mikktspace' is called 'vertex' here"`` where ``frame`` is an alias."""
    name = canonical_frame(frame, strict=False) if isinstance(frame, str) else None
    return f" ({frame!r} is called {name!r} here)" if name and name != frame else ""


def canonical_frame(name: str, *, strict: bool = True) -> str | None:
    """The frame method (one of `FRAMES`) that ``name`` means: ``name`` itself, or the frame
    it is another name for (`FRAME_ALIASES`, case and ``-``/``_`` ignored). An unknown name
    raises a one-line `ValueError` listing the frames and the aliases (returns None
    instead with ``strict=False``)."""
    key = name.strip().lower().replace("-", "_")
    found = key if key in FRAMES else FRAME_ALIASES.get(key)
    if found is None and strict:
        aliases = ", ".join(f"{a} = {f}" for a, f in FRAME_ALIASES.items() if a.isascii())
        raise ValueError(f"unknown frame {name!r}; expected one of {', '.join(FRAMES)} "
                         f"(or {aliases})")
    return found


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FrameInputs:
    """What `compute_frame` builds a frame from at each pixel, besides the normal. Each frame
    reads its own fields; the others may be None.

    **Fields:**
    - `p_attr`, `uv_attr`: position (world or camera-relative) and uv `Attribute`s with
      derivatives: the `SCREEN_FRAMES`.
    - `tri_p`, `tri_uv`: ``(..., 3, 3)``, ``(..., 3, 2)`` corners of each pixel's triangle
      (`jaxnm.interpolate.triangle_corners`): ``"exact"``, ``"exact_face"``.
    - `tangent`: ``(..., 4)`` interpolated tangent and sign: per-corner MikkTSpace tangents
      (`jaxnm.tangents`) for ``"vertex"``, `vertex_tangents` for ``"vertex_area"``.
    - `front_facing`: ``(...)`` bool, needed where `FrameOptions.double_sided`.
    """

    p_attr: Attribute | None = None
    uv_attr: Attribute | None = None
    tri_p: Array | None = None
    tri_uv: Array | None = None
    tangent: Array | Attribute | None = None
    front_facing: Array | None = None


@dataclasses.dataclass(frozen=True)
class FrameOptions:
    """How `compute_frame` builds a frame (static; checked when constructed).

    **Fields:**
    - `normalize`: see `cotangent_frame` (also for ``"nonperspective"`` and ``"exact"``;
      ``"cotangent_unnormalized"`` always uses ``"none"``).
    - `ddy_sign`: see `cotangent_frame` (the `SCREEN_FRAMES`).
    - `double_sided`: apply `face_forward` to back-facing fragments (after re-orienting
      the published cotangent frame, see there); needs `FrameInputs.front_facing`.
    """

    normalize: str = "max"
    ddy_sign: int = 1
    double_sided: bool = False

    def __post_init__(self):
        _check_normalize(self.normalize)
        _check_ddy_sign(self.ddy_sign)


def compute_frame(frame: str, N: Array | Attribute, *, inputs: FrameInputs = FrameInputs(),
                  options: FrameOptions = FrameOptions()) -> Frame:
    r"""Build the frame named by `frame` (one of `FRAMES`, static) per pixel.

    **Arguments:**
    - `N`: ``(..., 3)`` interpolated normal (or its `Attribute`); normalised here.
    - `inputs`: a `FrameInputs` with what the frame reads (`SCREEN_FRAMES`: the position
      and uv with derivatives; ``"exact"``: the triangle's corners; ``"vertex"``,
      ``"vertex_area"``: the interpolated tangent).
    - `options`: a `FrameOptions`.

    **Returns:** a `Frame` for `perturb_normal`. Where `N` is (numerically)
    zero, e.g. background pixels, every method returns ``T = B = N = 0``, so
    `perturb_normal` gives the zero vector there (not NaN).
    """
    check_frame(frame)
    normalize = options.normalize
    if frame == "cotangent_unnormalized":
        frame, normalize = "cotangent", "none"
    use_face_normal = frame == "exact_face"
    if use_face_normal:
        frame = "exact"
    n = safe_normalize(_value(N))
    out = _frame_of(frame, n, N, inputs, normalize, options.ddy_sign, use_face_normal)
    has_n = _dot(n, n, True) > 0
    out = Frame(jnp.where(has_n, out.T, 0.0), jnp.where(has_n, out.B, 0.0), out.N)
    if options.double_sided:
        if inputs.front_facing is None:
            raise ValueError("compute_frame with FrameOptions(double_sided=True) needs "
                             "FrameInputs.front_facing")
        if (frame == "cotangent" and normalize == "max") or frame in _VIEW_ORIENTED:
            s = jnp.where(jnp.asarray(inputs.front_facing)[..., None], 1.0,
                          -1.0).astype(out.T.dtype)
            out = Frame(out.T * s, out.B * s, out.N)
        out = face_forward(out, inputs.front_facing)
    return out


def _frame_of(frame: str, n: Array, N, inputs: FrameInputs, normalize: str, ddy_sign: int,
              use_face_normal: bool) -> Frame:
    """`compute_frame`'s frame before the background is zeroed and back faces turned:
    ``n`` is the unit normal, ``N`` the normal as given."""
    if frame == "none":
        return Frame(jnp.zeros_like(n), jnp.zeros_like(n), n)
    if frame in ("cotangent", "nonperspective") or frame in _SCREEN_VARIANTS:
        dp1, dp2 = _derivs(inputs.p_attr, "p_attr", frame)
        duv1, duv2 = _derivs(inputs.uv_attr, "uv_attr", frame)
        if frame in _SCREEN_VARIANTS:
            return _SCREEN_VARIANTS[frame](n, dp1, dp2, duv1, duv2, ddy_sign=ddy_sign)
        fn = cotangent_frame if frame == "cotangent" else nonperspective_frame
        return fn(n, dp1, dp2, duv1, duv2, normalize=normalize, ddy_sign=ddy_sign)
    if frame == "exact":
        if inputs.tri_p is None or inputs.tri_uv is None:
            raise ValueError("compute_frame(frame='exact') needs FrameInputs.tri_p and tri_uv "
                             "(see jaxnm.interpolate.triangle_corners)")
        return exact_frame(inputs.tri_p, inputs.tri_uv, n, use_face_normal=use_face_normal,
                           normalize=normalize)
    if frame in ("vertex", "vertex_area"):
        if inputs.tangent is None:
            raise ValueError(f"compute_frame(frame={frame!r}) needs FrameInputs.tangent "
                             "(interpolated tangents and signs, (..., 4))")
        t = _value(inputs.tangent)
        if frame == "vertex_area":
            return vertex_frame(t[..., :3], t[..., 3], n)
        # MikkTSpace decodes with the interpolated normal as it is, not normalised
        return mikktspace_frame(t[..., :3], t[..., 3], jnp.where(_dot(n, n, True) > 0,
                                                                 _value(N), 0.0))
    return axis_frame(n)
