r"""Local shading: lights, materials, Lambert, Blinn-Phong and Phong, and display encoding.

Everything here is pure ``jax.numpy``, differentiable, batched over any leading
axes and finite (value and gradient) for every finite input.

**Conventions.**

- All vectors are in one common space (world space in jaxnm): per-pixel normal
  ``N`` and position ``p`` ``(..., 3)``, the eye position ``(3,)``.
- ``N`` is a unit vector by contract and is *not* renormalised here. It must be
  the normal of the side that faces the viewer: back faces / double-sided
  lighting are handled upstream (the caller passes the face-forwarded normal,
  e.g. flipped where `Fragments.front_facing` is False). A zero ``N`` (e.g. a
  degenerate perturbed normal) shades to ambient only, without NaN.
- ``V = normalize(eye - p)`` points from the surface to the eye, ``L`` from the
  surface to the light (`DirectionalLight.direction` is given in that
  direction; its length is ignored).
- The output is **linear** radiance ``(..., 3)`` (not clamped, not
  gamma-encoded); use `to_display` to turn it into sRGB values for a PNG.

**The models** (per light with unit ``L`` and incident radiance
``E = color * intensity * attenuation``; ``\kappa_d``, ``\kappa_s``, ``\kappa_a``,
``n``: the `Material` diffuse, specular, ambient colours and shininess;
``a``: the optional per-pixel albedo, default 1):

.. math::
    \text{lambert} &= \kappa_a a + \sum_\ell \kappa_d\, a\, E_\ell \max(0, N\cdot L_\ell) \\
    \text{blinn\_phong} &= \text{lambert} + \sum_\ell [N\cdot L_\ell > 0]\;
        \kappa_s E_\ell \max(0, N\cdot H_\ell)^n, \quad H = \mathrm{normalize}(L + V) \\
    \text{phong} &= \text{lambert} + \sum_\ell [N\cdot L_\ell > 0]\;
        \kappa_s E_\ell \max(0, R_\ell\cdot V)^n, \quad
        R = \mathrm{reflect}(-L, N) = 2 (N\cdot L) N - L

This is the GLSL Hacker demo's fragment shader (ambient ``* tex``, diffuse
``* tex``, specular inside ``if (lambertTerm > 0.0)``), with a single light
colour for the diffuse and specular terms. The ambient term is added once,
independently of the lights. No energy normalisation of the specular lobe.

**Gradient caveats** (as tensorflow_graphics documents for its Lambertian):

- ``max(0, N.L)`` is not smooth at the terminator ``N.L = 0``: the gradient is
  that of the side the point is on (0 exactly at the kink).
- The specular terms are *discontinuous* at the terminator (the
  ``[N.L > 0]`` gate switches a non-zero highlight off); the gradient does not
  see that jump.
- ``max(0, x)^n`` is evaluated safely: ``0^0 = 1``, and where ``x <= 0`` (or is
  numerically zero) the gradient with respect to both ``x`` and ``n`` is 0,
  also for ``n < 1`` where the true derivative in ``x`` is infinite.
- Point lights: the direction is undefined when the light sits on the shaded
  point (``d = 0``); that light then contributes 0.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike
from jaxtyping import Float

from .numerics import dot as _ndot
from .numerics import safe_div, safe_normalize, spread, tiny

__all__ = [
    "DirectionalLight", "PointLight", "Lights", "Material", "FALLOFFS", "SHADING_MODELS",
    "directional_light", "stack_lights", "lambert", "blinn_phong", "phong", "shade", "to_display",
    "AnyLights", "check_shading_model"
]

SHADING_MODELS = ("lambert", "blinn_phong", "phong")

#: Point light attenuation: ``"inverse_square"`` (physical, ``1 / d^2``) or
#: ``"none"`` (constant, as in the GLSL Hacker demo).
FALLOFFS = ("inverse_square", "none")


# --------------------------------------------------------------------------------------
# pytrees
# --------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity (sun), or a stack of them.

    **Fields** (arrays; ``*B`` is an optional stack of lights, summed over by the
    shading functions and mapped over by ``jax.vmap``):
    - `direction`: (*B, 3) direction **from the surface towards the light**
      (the GLSL ``L``), in the space of ``N``; need not be unit (its length is
      ignored; a zero direction gives no light).
    - `color`: (*B, 3) linear RGB.
    - `intensity`: (*B,) scalar multiplier; the incident radiance is
      ``color * intensity`` (no attenuation).
    """

    direction: Array
    color: Array
    intensity: Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PointLight:
    """A point light (or a stack of them, see `DirectionalLight`).

    **Fields:**
    - `position`: (*B, 3) light position in the space of ``p``.
    - `color`: (*B, 3) linear RGB.
    - `intensity`: (*B,) radiant intensity; the incident radiance at distance
      ``d`` is ``color * intensity / d^2`` (``falloff="inverse_square"``) or
      ``color * intensity`` (``falloff="none"``).
    - `falloff`: static, one of `FALLOFFS`; shared by the whole stack.
    """

    position: Array
    color: Array
    intensity: Array
    falloff: str = dataclasses.field(default="inverse_square", metadata=dict(static=True))

    def __post_init__(self):  # static: checked however the light was built, never traced
        if self.falloff not in FALLOFFS:
            raise ValueError(f"PointLight: unknown falloff {self.falloff!r}; expected one of "
                             f"{', '.join(FALLOFFS)}")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Lights:
    """Several kinds of lights at once: one (possibly stacked) light per kind, or None.

    The shading result is the sum over every light in both stacks. To render
    each light of a stack separately, ``jax.vmap`` the shading function over the
    stacked light instead (see `stack_lights`).
    """

    directional: DirectionalLight | None = None
    point: PointLight | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Material:
    """Phong-family material (linear RGB).

    **Fields** (arrays; each colour is (3,) or per pixel (..., 3)):
    - `diffuse`: diffuse colour ``kappa_d`` (multiplied by the albedo).
    - `specular`: specular colour ``kappa_s`` (not multiplied by the albedo).
    - `shininess`: () exponent ``n >= 0`` of the specular lobe (or per pixel (...,)).
    - `ambient`: ambient radiance ``kappa_a`` (multiplied by the albedo), added
      once, independent of the lights.
    """

    diffuse: Array
    specular: Array
    shininess: Array
    ambient: Array


AnyLights = DirectionalLight | PointLight | Lights | Sequence


def stack_lights(lights: Sequence[DirectionalLight] | Sequence[PointLight]):
    """Stack single lights of one type into one light with a leading axis of length ``len(lights)``.

    The result can be passed to the shading functions (which sum over the
    stack) or mapped over with ``jax.vmap`` (one image per light).
    """
    lights = list(lights)
    if not lights:
        raise ValueError("stack_lights: need at least one light")
    kinds = {type(light) for light in lights}
    if len(kinds) != 1 or kinds.pop() not in (DirectionalLight, PointLight):
        raise ValueError("stack_lights: all lights must be of one type, DirectionalLight or "
                         f"PointLight; got {[type(light).__name__ for light in lights]}")
    if isinstance(lights[0], PointLight) and len({light.falloff for light in lights}) != 1:
        raise ValueError("stack_lights: point lights with different `falloff` cannot be "
                         "stacked; pass them in a list instead")
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *lights)


def directional_light(direction, *, color=(1.0, 1.0, 1.0), intensity=1.0) -> Lights:
    """A `Lights` holding one directional light, as a stack of one (``direction`` points
    towards the light)."""
    return Lights(directional=DirectionalLight(jnp.asarray(direction, jnp.float32)[None],
                                               jnp.asarray(color, jnp.float32)[None],
                                               jnp.reshape(jnp.asarray(intensity, jnp.float32),
                                                           (1,))))


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _expand_to(x: ArrayLike, shape: tuple[int, ...]) -> Array:
    """Right-align ``x`` with ``shape`` (explicit leading unit axes), then broadcast."""
    x = jnp.asarray(x)
    if x.ndim > len(shape):
        raise ValueError(f"shading: cannot broadcast shape {x.shape} to {shape}")
    return jnp.broadcast_to(x.reshape((1,) * (len(shape) - x.ndim) + x.shape), shape)


def _dot(a: Array, b: Array) -> Array:
    return _ndot(a, b, keepdims=True)


def _pos_pow(x: Array, n: Array) -> Array:
    """``max(x, 0) ** n`` for ``n >= 0`` with ``0 ** 0 = 1`` and finite gradients everywhere.

    Where ``x`` is not (numerically) positive the value is ``0 ** n`` and both
    gradients are 0: the double where keeps ``log(0)`` out of both the value
    and the discarded branch's cotangent.
    """
    ok = x > tiny(x.dtype)
    y = jnp.exp(n * jnp.log(jnp.where(ok, x, jnp.ones_like(x))))
    return jnp.where(ok, y, jnp.where(n == 0, 1.0, 0.0).astype(y.dtype))


def check_shading_model(model: str) -> None:
    """Raise a `ValueError` unless ``model`` is one of `SHADING_MODELS`."""
    if model not in SHADING_MODELS:
        raise ValueError(f"shade: unknown shading model {model!r}; expected one of "
                         f"{', '.join(SHADING_MODELS)}")


def _incident(light, p: Array) -> tuple[Array, Array]:
    """Unit direction to the light and incident radiance, each (..., 3), for ONE light."""
    shape = p.shape
    if isinstance(light, DirectionalLight):
        L = _expand_to(safe_normalize(jnp.asarray(light.direction, p.dtype)), shape)
        radiance = jnp.asarray(light.color, p.dtype) * jnp.asarray(light.intensity, p.dtype)
        return L, _expand_to(radiance, shape)
    if isinstance(light, PointLight):
        d = _expand_to(jnp.asarray(light.position, p.dtype), shape) - p
        L = safe_normalize(d)
        radiance = jnp.asarray(light.color, p.dtype) * jnp.asarray(light.intensity, p.dtype)
        radiance = _expand_to(radiance, shape)
        if light.falloff == "inverse_square":
            radiance = radiance * spread(safe_div(1.0, _dot(d, d)))
        return L, radiance
    raise TypeError(f"shading: expected a DirectionalLight, PointLight, Lights or a sequence "
                    f"of them, got {type(light).__name__}")


def _light_stacks(lights) -> list:
    """Flatten the accepted light arguments into a list of (possibly stacked) single-type lights."""
    if isinstance(lights, (DirectionalLight, PointLight)):
        return [lights]
    if isinstance(lights, Lights):
        return [x for x in (lights.directional, lights.point) if x is not None]
    if isinstance(lights, (list, tuple)):
        return [x for item in lights for x in _light_stacks(item)]
    raise TypeError(f"shading: expected a DirectionalLight, PointLight, Lights or a sequence of "
                    f"them, got {type(lights).__name__}")


def _flatten_stack(light):
    """A stacked light with its stack axes flattened to one leading axis, or None if single."""
    vec = light.direction if isinstance(light, DirectionalLight) else light.position
    vec, color, intensity = (jnp.asarray(x) for x in (vec, light.color, light.intensity))
    if vec.shape[-1:] != (3,) or color.shape[-1:] != (3,):
        raise ValueError(f"{type(light).__name__}: direction/position and color must be "
                         f"(*B, 3), got {vec.shape} and {color.shape}")
    batch = jnp.broadcast_shapes(vec.shape[:-1], color.shape[:-1], intensity.shape)
    if not batch:
        return None
    n = 1
    for b in batch:
        n *= b
    vec = _expand_to(vec, batch + (3,)).reshape(n, 3)
    color = _expand_to(color, batch + (3,)).reshape(n, 3)
    intensity = _expand_to(intensity, batch).reshape(n)
    if isinstance(light, DirectionalLight):
        return DirectionalLight(vec, color, intensity)
    return PointLight(vec, color, intensity, light.falloff)


def _shade(model: str, N, p, eye, lights, material: Material, albedo) -> Array:
    check_shading_model(model)
    N, p = jnp.asarray(N), jnp.asarray(p)
    dtype = jnp.result_type(N, p)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.float32
    shapes = [N.shape, p.shape] + ([] if albedo is None else [jnp.shape(albedo)])
    shape = jnp.broadcast_shapes(*shapes)
    if shape[-1:] != (3,):
        raise ValueError(f"shade: N and p must be (..., 3), got {N.shape} and {p.shape}")
    N = _expand_to(N.astype(dtype), shape)
    p = _expand_to(p.astype(dtype), shape)
    a = (jnp.ones(shape, dtype) if albedo is None
         else _expand_to(jnp.asarray(albedo, dtype), shape))
    V = safe_normalize(_expand_to(jnp.asarray(eye, dtype), shape) - p)
    kd = _expand_to(jnp.asarray(material.diffuse, dtype), shape)
    ks = _expand_to(jnp.asarray(material.specular, dtype), shape)
    ka = _expand_to(jnp.asarray(material.ambient, dtype), shape)
    n = jnp.asarray(material.shininess, dtype)
    if n.ndim:  # per-pixel shininess (...,) -> (..., 1)
        n = _expand_to(n[..., None], shape[:-1] + (1,))

    def one_light(light):
        L, E = _incident(light, p)
        # (`spread`: per-pixel scalars scaling colours, see there)
        ndl = _dot(N, L)
        lit = ndl > 0
        out = kd * a * E * spread(jnp.where(lit, ndl, 0.0))
        if model == "lambert":
            return out
        if model == "blinn_phong":
            H = safe_normalize(L + V)
            x = _dot(N, H)
        else:  # phong: reflect(-L, N) . V
            R = 2.0 * spread(ndl) * N - L
            x = _dot(R, V)
        spec = ks * E * spread(_pos_pow(x, n))
        return out + jnp.where(lit, spec, 0.0)

    total = ka * a
    for light in _light_stacks(lights):
        flat = _flatten_stack(light)
        if flat is None:
            total = total + one_light(light)
        else:
            total = total + jnp.sum(jax.vmap(one_light)(flat), axis=0)
    return total


# --------------------------------------------------------------------------------------
# public shading functions
# --------------------------------------------------------------------------------------


def lambert(N: ArrayLike, p: ArrayLike, eye: ArrayLike, lights: AnyLights, material: Material,
            *, albedo: ArrayLike | None = None) -> Array:
    """Ambient + Lambertian diffuse: ``ka a + sum kd a E max(0, N.L)``.

    Arguments as for `shade` (`eye` is unused; `material.specular` and
    `material.shininess` too).
    """
    return _shade("lambert", N, p, eye, lights, material, albedo)


def blinn_phong(N: ArrayLike, p: ArrayLike, eye: ArrayLike, lights: AnyLights,
                material: Material, *, albedo: ArrayLike | None = None) -> Array:
    """Lambert + Blinn's half-vector specular ``ks E max(0, N.H)^n``, gated by ``N.L > 0``.

    ``H = normalize(L + V)``. Arguments as for `shade`.
    """
    return _shade("blinn_phong", N, p, eye, lights, material, albedo)


def phong(N: ArrayLike, p: ArrayLike, eye: ArrayLike, lights: AnyLights, material: Material,
          *, albedo: ArrayLike | None = None) -> Array:
    """Lambert + Phong specular ``ks E max(0, reflect(-L, N).V)^n``, gated by ``N.L > 0``.

    As the GLSL Hacker demo's ``if (lambertTerm > 0.0) { ... }``. Arguments as for `shade`.
    """
    return _shade("phong", N, p, eye, lights, material, albedo)


def shade(model: str, N: Float[ArrayLike, "*#batch 3"], p: Float[ArrayLike, "*#batch 3"],
          eye: Float[ArrayLike, "*#batch 3"], lights: AnyLights, material: Material, *,
          albedo: Float[ArrayLike, "*#batch 3"] | None = None) -> Float[Array, "... 3"]:
    """Shade with `model`, a static string in `SHADING_MODELS` (see the module docstring).

    **Arguments:**
    - `model`: ``"lambert"``, ``"blinn_phong"`` or ``"phong"``.
    - `N`: (..., 3) unit, face-forwarded normal per pixel.
    - `p`: (..., 3) position per pixel (same space as the lights and the eye).
    - `eye`: (3,) eye position.
    - `lights`: a `DirectionalLight` or `PointLight` (single or stacked), a
      `Lights`, or a list/tuple of them; the result sums over all of them.
    - `material`: a `Material`.
    - `albedo`: optional (..., 3) per-pixel colour multiplying the diffuse and
      ambient terms (e.g. a sampled colour texture); default 1.

    **Returns:** (..., 3) linear radiance, in the broadcast shape of `N`, `p`
    and `albedo`.
    """
    return _shade(model, N, p, eye, lights, material, albedo)


# --------------------------------------------------------------------------------------
# display
# --------------------------------------------------------------------------------------


def to_display(linear: ArrayLike, *, exposure: ArrayLike = 1.0) -> Array:
    """Linear radiance to sRGB-encoded display values in [0, 1] (for PNG output).

    **Arguments:**
    - `linear`: (..., C) linear values.
    - `exposure`: linear multiplier applied before clamping to [0, 1].

    **Returns:** the sRGB encoding (IEC 61966-2-1) of ``clip(exposure * linear, 0, 1)``,
    same shape; quantise to uint8 at save time. Differentiable (gradient 0 where
    clamped, one-sided at exactly 0 and 1).
    """
    linear = jnp.asarray(linear)
    if not jnp.issubdtype(linear.dtype, jnp.floating):
        linear = linear.astype(jnp.float32)
    x = linear * jnp.asarray(exposure, linear.dtype)
    x = jnp.where(x < 0.0, 0.0, jnp.where(x > 1.0, 1.0, x))  # clamp; gradient 1 at 0 and 1
    from .textures import linear_to_srgb  # (textures imports nothing from here)

    return linear_to_srgb(x)
