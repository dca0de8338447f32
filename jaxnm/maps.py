r"""The other normal-map types: object-space normal maps, bump maps, derivative maps.

Tangent-space normal maps live in `jaxnm.frames` (cotangent frame +
``perturb_normal``); this module has the alternatives the source articles
compare them with. Each function returns a unit normal per pixel and is
finite in value and gradient everywhere (degenerate inputs fall back to a
documented normal instead of NaN).

**Texture-space conventions.** Height maps are (H, W) arrays in image layout
(row 0 = **top**). Texture coordinates follow OpenGL: the uv origin is the
bottom-left corner, ``u`` increases to the right (with the column) and ``v``
increases **upwards**, i.e. towards image row ``r - 1``. A tangent-space
normal ``(x, y, z)`` therefore has ``+x`` along ``+u`` and ``+y`` along ``+v``
("green up", OpenGL convention), ``z`` along the surface normal.

**Screen-space conventions.** ``dp_dx``, ``dh_dx``, ``duv_dx`` are derivatives
per pixel step along window x (right); ``dp_dy``, ``dh_dy``, ``duv_dy`` per step
along window y (**up**), as `jaxnm.interpolate` returns them. The surface
gradient formula below is unchanged when *all* y derivatives change sign
together, so any consistent convention (e.g. HLSL's downward ``ddy``) gives
the same normal; only mixing conventions is wrong.

**Surface gradient bump mapping** (Mikkelsen, "Bump Mapping Unparametrized
Surfaces on the GPU", 2010). With ``sigma_x = dp/dx``, ``sigma_y = dp/dy``:

.. math::
    R_1 = \sigma_y \times N, \quad R_2 = N \times \sigma_x, \quad
    \det = \sigma_x \cdot R_1, \\
    \nabla_S h = \operatorname{sign}(\det)\,(h_x R_1 + h_y R_2), \qquad
    N' = \operatorname{normalize}(|\det|\, N - s\, \nabla_S h).

``\nabla_S h / \det`` is the gradient of the height field along the surface
(the component in the tangent plane), so ``N'`` is the normal of the
displaced surface ``p + s h N`` to first order (for locally flat surfaces).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from .numerics import cross as _cross
from .numerics import dot as _ndot
from .numerics import safe_div, safe_normalize

__all__ = [
    "WRAP_MODES",
    "normal_matrix",
    "object_space_normal",
    "bump_normal",
    "derivative_map_normal",
    "height_to_normal_map",
    "height_to_derivative_map",
]

#: Boundary handling of the finite differences of a height map:
#: ``"repeat"`` (periodic, tiling texture) or ``"clamp"`` (no wrap-around: the
#: border texels use one-sided differences, so a linear ramp is exact everywhere).
WRAP_MODES = ("repeat", "clamp")


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _to_shape(x: Array, shape: tuple[int, ...]) -> Array:
    """Right-align ``x`` with ``shape`` (explicit leading unit axes), then broadcast."""
    if x.ndim > len(shape):
        raise ValueError(f"maps: cannot broadcast shape {x.shape} to {shape}")
    return jnp.broadcast_to(x.reshape((1,) * (len(shape) - x.ndim) + x.shape), shape)


def _per_pixel_scalar(x: ArrayLike, batch: tuple[int, ...], name: str) -> Array:
    """A per-pixel scalar given as (...) or (..., 1), returned as (..., 1)."""
    x = _float(x)
    if x.ndim == len(batch) + 1 and x.shape[-1] == 1:
        x = x[..., 0]
    if x.ndim > len(batch):
        raise ValueError(f"maps: `{name}` must be (...) or (..., 1) for vectors of shape "
                         f"{batch + (3,)}, got {x.shape}")
    return _to_shape(x, batch)[..., None]


def _cofactor(m: Array) -> Array:
    """Cofactor matrix of (3, 3) ``m``: ``det(m) * inverse(m).T``, also for singular ``m``."""
    r0, r1, r2 = m[0], m[1], m[2]
    return jnp.stack([_cross(r1, r2), _cross(r2, r0), _cross(r0, r1)])


def _check_wrap(wrap: str) -> None:
    if wrap not in WRAP_MODES:
        raise ValueError(f"unknown wrap mode {wrap!r}; expected one of {', '.join(WRAP_MODES)}")


def _texel_gradient(height: ArrayLike, wrap: str) -> tuple[Array, Array]:
    """Central differences ``(dh/du, dh/dv)`` per texel, (H, W) each; v up (row above - below)."""
    _check_wrap(wrap)
    h = _float(height)
    if h.ndim != 2:
        raise ValueError(f"height map must be (H, W), got shape {h.shape}")
    if wrap == "repeat":
        right, left = jnp.roll(h, -1, axis=1), jnp.roll(h, 1, axis=1)
        above, below = jnp.roll(h, 1, axis=0), jnp.roll(h, -1, axis=0)
    else:
        # pad by linear extrapolation: the central difference at a border texel then equals
        # the one-sided difference into the image (numpy.gradient's default)
        def pad(x, axis):
            if x.shape[axis] < 2:
                return jnp.concatenate([x, x, x], axis)
            first, second = jnp.take(x, jnp.array([0]), axis), jnp.take(x, jnp.array([1]), axis)
            last, prev = jnp.take(x, jnp.array([-1]), axis), jnp.take(x, jnp.array([-2]), axis)
            return jnp.concatenate([2 * first - second, x, 2 * last - prev], axis)

        hp = pad(h, 1)
        right, left = hp[:, 2:], hp[:, :-2]
        vp = pad(h, 0)
        above, below = vp[:-2], vp[2:]
    return 0.5 * (right - left), 0.5 * (above - below)


# --------------------------------------------------------------------------------------
# object-space normal maps
# --------------------------------------------------------------------------------------


def normal_matrix(model: ArrayLike) -> Array:
    """The normal matrix ``inverse(A).T`` of a model matrix (its upper-left 3x3 block ``A``).

    **Arguments:**
    - `model`: (3, 3) or (4, 4) model (object-to-world) matrix, column-vector
      convention as in `jaxnm.camera`.

    **Returns:** (3, 3). Normals transform as ``n_world ~ normal_matrix @ n_object``
    (then normalise). Computed as ``cofactor(A) / det(A)``; for a singular ``A``
    (a zero scale) it returns the cofactor matrix itself, which still maps
    normals onto the right directions where those are defined.
    """
    m = _float(model)
    if m.shape not in ((3, 3), (4, 4)):
        raise ValueError(f"normal_matrix: `model` must be (3, 3) or (4, 4), got {m.shape}")
    a = m[:3, :3]
    cof = _cofactor(a)
    det = jnp.dot(a[0], cof[0], precision=jax.lax.Precision.HIGHEST)
    return safe_div(cof, det, fallback=cof)


def object_space_normal(m: ArrayLike, *, model_normal_matrix: ArrayLike | None = None,
                        fallback: ArrayLike | None = None) -> Array:
    """Normal from an object-space (model-space) normal map.

    The decoded map vector *is* the surface normal in object space: no tangent
    frame, no interpolated normal. It is mapped to world space by the normal
    matrix and normalised.

    **Arguments:**
    - `m`: (..., 3) decoded map vectors (``2 * rgb - 1``; need not be unit).
    - `model_normal_matrix`: optional (3, 3) *normal matrix*, the inverse
      transpose of the model matrix's linear part (see `normal_matrix`); a
      (4, 4) matrix is taken to be ``inverse(model).T`` and its upper-left block
      used. None means identity (object space = world space).
    - `fallback`: (..., 3) normal returned where the transformed vector is zero
      (e.g. the interpolated geometric normal); zero vector by default.

    **Returns:** (..., 3) unit normals.
    """
    m = _float(m)
    if m.shape[-1:] != (3,):
        raise ValueError(f"object_space_normal: `m` must be (..., 3), got {m.shape}")
    if model_normal_matrix is not None:
        nm = jnp.asarray(model_normal_matrix, m.dtype)
        if nm.shape not in ((3, 3), (4, 4)):
            raise ValueError("object_space_normal: `model_normal_matrix` must be (3, 3) or "
                             f"(4, 4), got {nm.shape}")
        m = jnp.einsum("ij,...j->...i", nm[:3, :3], m, precision=jax.lax.Precision.HIGHEST)
    return safe_normalize(m, fallback=fallback)


# --------------------------------------------------------------------------------------
# bump and derivative maps
# --------------------------------------------------------------------------------------


def bump_normal(N: ArrayLike, dp_dx: ArrayLike, dp_dy: ArrayLike, dh_dx: ArrayLike,
                dh_dy: ArrayLike, *, scale: ArrayLike = 1.0) -> Array:
    r"""Bump-mapped normal from screen-space derivatives of the height (surface gradient).

    Mikkelsen's surface-gradient formula (module docstring):
    ``N' = normalize(|det| N - scale * sign(det) (dh_dx R1 + dh_dy R2))`` with
    ``R1 = dp_dy x N``, ``R2 = N x dp_dx``, ``det = dp_dx . R1``.

    **Arguments:**
    - `N`: (..., 3) unit interpolated (face-forwarded) normal.
    - `dp_dx`, `dp_dy`: (..., 3) screen derivatives of the position.
    - `dh_dx`, `dh_dy`: (...) or (..., 1) screen derivatives of the height, in
      the same y convention as `dp_dy`: screen differences of the sampled
      height, or the chain rule of its uv gradient (`derivative_map_normal`).
    - `scale`: bump strength: the displacement is ``scale * h`` along ``N``.

    **Returns:** (..., 3) unit perturbed normal. Where the screen footprint is
    degenerate (``det = 0``: zero position derivatives, a surface seen edge-on)
    the surface gradient is undefined and `N` is returned unchanged (with
    finite gradients); where the height derivatives are zero, ``N' = N``.
    """
    N = _float(N)
    shape = jnp.broadcast_shapes(N.shape, jnp.shape(dp_dx), jnp.shape(dp_dy))
    if shape[-1:] != (3,):
        raise ValueError(f"bump_normal: N, dp_dx, dp_dy must be (..., 3), got {N.shape}, "
                         f"{jnp.shape(dp_dx)}, {jnp.shape(dp_dy)}")
    N = _to_shape(N, shape)
    sx = _to_shape(jnp.asarray(dp_dx, N.dtype), shape)
    sy = _to_shape(jnp.asarray(dp_dy, N.dtype), shape)
    hx = _per_pixel_scalar(dh_dx, shape[:-1], "dh_dx").astype(N.dtype)
    hy = _per_pixel_scalar(dh_dy, shape[:-1], "dh_dy").astype(N.dtype)
    r1 = _cross(sy, N)
    r2 = _cross(N, sx)
    det = _ndot(sx, r1, keepdims=True)
    # sign(0) = 0 and |.|' = sign: at det = 0 both terms vanish and the fallback returns N
    surf_grad = jnp.sign(det) * (hx * r1 + hy * r2)
    return safe_normalize(jnp.abs(det) * N - jnp.asarray(scale, N.dtype) * surf_grad,
                          fallback=N)


def derivative_map_normal(N: ArrayLike, dp_dx: ArrayLike, dp_dy: ArrayLike, duv_dx: ArrayLike,
                          duv_dy: ArrayLike, dhduv: ArrayLike, *,
                          scale: ArrayLike = 1.0) -> Array:
    """Normal from a derivative map: the stored height gradient, chained to screen space.

    ``dh_dx = dhduv . duv_dx`` and ``dh_dy = dhduv . duv_dy``, then `bump_normal`.
    No tangent frame is needed.

    **Arguments:**
    - `N`, `dp_dx`, `dp_dy`: as for `bump_normal`.
    - `duv_dx`, `duv_dy`: (..., 2) screen derivatives of the texture coordinates.
    - `dhduv`: (..., 2) the sampled map value ``(dh/du, dh/dv)`` per unit of u
      and v (v up), e.g. from `height_to_derivative_map`.
    - `scale`: bump strength, as for `bump_normal`.

    **Returns:** (..., 3) unit perturbed normal.
    """
    g = _float(dhduv)
    for name, x in (("duv_dx", duv_dx), ("duv_dy", duv_dy), ("dhduv", g)):
        if jnp.shape(x)[-1:] != (2,):
            raise ValueError(f"derivative_map_normal: `{name}` must be (..., 2), got "
                             f"{jnp.shape(x)}")
    batch = jnp.broadcast_shapes(g.shape, jnp.shape(duv_dx), jnp.shape(duv_dy))
    g = _to_shape(g, batch)
    dh_dx = _ndot(g, _to_shape(jnp.asarray(duv_dx, g.dtype), batch))
    dh_dy = _ndot(g, _to_shape(jnp.asarray(duv_dy, g.dtype), batch))
    return bump_normal(N, dp_dx, dp_dy, dh_dx, dh_dy, scale=scale)


# --------------------------------------------------------------------------------------
# height-map conversions
# --------------------------------------------------------------------------------------


def height_to_normal_map(height: ArrayLike, *, scale: ArrayLike = 1.0,
                         wrap: str = "repeat") -> Array:
    r"""Tangent-space normal map of a height (bump) map, by central differences in texel space.

    .. math::
        n = \operatorname{normalize}\left(-s\,\frac{\partial h}{\partial u},\;
            -s\,\frac{\partial h}{\partial v},\; 1\right),\quad
        \frac{\partial h}{\partial u} \approx \frac{h_{r,c+1} - h_{r,c-1}}{2},\quad
        \frac{\partial h}{\partial v} \approx \frac{h_{r-1,c} - h_{r+1,c}}{2}

    (derivatives per texel; ``v`` up, so the row *above* minus the row below).
    This is ``normalize(cross((1, 0, s h_u), (0, 1, s h_v)))``, the classic
    conversion, with central instead of forward differences.

    **Arguments:**
    - `height`: (H, W) heights, image layout (row 0 = top).
    - `scale`: bumpiness ``s``, height units per texel.
    - `wrap`: one of `WRAP_MODES` (static).

    **Returns:** (H, W, 3) unit tangent-space normals (decoded, in [-1, 1]; "green
    up"). Encode to RGB as ``0.5 * n + 0.5`` when saving.
    """
    du, dv = _texel_gradient(height, wrap)
    s = jnp.asarray(scale, du.dtype)
    n = jnp.stack([-s * du, -s * dv, jnp.ones_like(du)], axis=-1)
    return safe_normalize(n)


def height_to_derivative_map(height: ArrayLike, *, scale: ArrayLike = 1.0,
                             wrap: str = "repeat") -> Array:
    """Derivative map of a height map: ``scale * (dh/du, dh/dv)`` per unit of u and v.

    Central differences as in `height_to_normal_map` (v up), converted from
    per texel to per unit of texture coordinate (``u`` spans the W columns,
    ``v`` the H rows), so that `derivative_map_normal` applies the chain rule
    with ``duv_dx``, ``duv_dy`` in uv units per pixel, and the result is the
    normal of the surface displaced by ``scale * h`` (world units) along ``N``.

    **Arguments:**
    - `height`: (H, W) heights, image layout (row 0 = top).
    - `scale`: height multiplier (world units per height unit).
    - `wrap`: one of `WRAP_MODES` (static).

    **Returns:** (H, W, 2) ``(dh/du, dh/dv)``. Stored in a texture, these need
    a known range (the maximum slope) to be quantised.
    """
    du, dv = _texel_gradient(height, wrap)
    rows, cols = du.shape
    s = jnp.asarray(scale, du.dtype)
    return jnp.stack([s * cols * du, s * rows * dv], axis=-1)
