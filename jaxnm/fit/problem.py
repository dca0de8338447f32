"""What a fit is asked to do: the problem (scene side and targets), the options, the result."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..camera import Camera
from ..frames import check_frame
from ..geometry import Mesh
from ..interpolate import check_derivatives, check_precision, require_x64
from ..scene import Scene, default_material
from ..shading import Lights, Material, check_shading_model
from ..textures import NormalMapOptions

__all__ = [
    "SOLVERS", "FitWarning", "FitTarget", "FitProblem", "FitOptions", "FitResult", "FitJob",
    "validate_problem", "problem_from_scene", "TEXEL_SUMS"
]

#: ``"lm"`` Levenberg-Marquardt, ``"gn"`` Gauss-Newton (both optimistix's, matrix-free,
#: LSMR inner solves), ``"lm-texel"`` Levenberg-Marquardt on the normal equations in texel
#: space (`jaxnm.fit.texel_lm`: memory that does not grow with the views beyond their
#: prepared pixels), ``"lbfgs"`` the first-order baseline.
SOLVERS = ("lm", "gn", "lm-texel", "lbfgs")
#: How ``"lm-texel"`` sums into the texels (`FitOptions.texel_sums`).
TEXEL_SUMS = ("auto", "scatter", "tables")


class FitWarning(UserWarning):
    """The fit input is suspicious (e.g. cannot determine the map)."""


@dataclasses.dataclass(frozen=True)
class FitTarget:
    """One target image: a view (camera + size), its lights, the image and an optional mask.

    ``image`` is **linear** RGB (H, W, 3), row 0 = top; ``mask`` (H, W) bool
    selects the pixels that count (default: all the mesh covers).
    """

    camera: Camera
    width: int
    height: int
    lights: Lights
    image: np.ndarray
    mask: np.ndarray | None = None
    name: str = ""


@dataclasses.dataclass(frozen=True)
class FitProblem:
    """The scene side of a fit: mesh, material, albedo, render options, targets, map size.

    ``sampling`` gives how the fitted map is sampled (uv origin, wrap, filter);
    its encoding is irrelevant (the fit works on unit normals).
    """

    mesh: Mesh
    material: Material
    targets: tuple[FitTarget, ...]
    map_size: tuple[int, int] = (256, 256)
    albedo: np.ndarray = dataclasses.field(
        default_factory=lambda: np.array([0.8, 0.8, 0.8], np.float32))
    shading: str = "blinn_phong"
    frame: str = "cotangent"
    derivatives: str = "fine"
    precision: str = "float32"
    double_sided: bool = True
    sampling: NormalMapOptions = NormalMapOptions(encoding="signed")
    source: str = "<fit problem>"


def problem_from_scene(scene, targets, map_size, *, source: str | None = None) -> FitProblem:
    """The `FitProblem` of fitting ``scene``'s normal map (its mesh, material, albedo, frame,
    derivative mode and map sampling options) to ``targets``. The scene's model matrix is
    applied to the mesh (the fit works in world space); a scene without a material has the
    one it renders with (`jaxnm.scene.default_material`). The scene's ``precision`` is the
    shader arithmetic the map is fitted for (the frame and the perturbation; the solver
    itself works in float32)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"problem_from_scene: scene must be a Scene (jaxnm.config.load_scene), "
                        f"got {type(scene).__name__}")
    src = scene.source if source is None else source
    if isinstance(map_size, (str, bytes)) or not np.iterable(map_size):
        raise ValueError(f"{src}: the map size must be two integers >= 2, got {map_size!r}")
    mesh = scene.mesh if scene.model is None else scene.mesh.transformed(scene.model)
    material = default_material() if scene.material is None else scene.material
    return FitProblem(mesh=mesh, material=material, targets=tuple(targets),
                      map_size=tuple(int(s) if isinstance(s, np.integer) else s
                                     for s in map_size), albedo=scene.albedo,
                      shading=scene.shading, frame=scene.frame, derivatives=scene.derivatives,
                      precision=scene.precision,
                      double_sided=scene.double_sided,
                      sampling=dataclasses.replace(scene.normal_map_options, encoding="signed",
                                                   channels=3),
                      source=src)


def _check_int(name: str, v, lo: int) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"FitOptions: {name} must be an integer >= {lo}, got {v!r}")


def _check_number(name: str, v, lo: float, *, strict: bool = False) -> None:
    ok = (not isinstance(v, bool) and isinstance(v, (int, float, np.floating))
          and math.isfinite(v) and (v > lo if strict else v >= lo))
    if not ok:
        raise ValueError(f"FitOptions: {name} must be a finite number {'>' if strict else '>='} "
                         f"{lo}, got {v!r}")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How to fit (validated when constructed).

    - `solver`: one of `SOLVERS` (default ``"lm-texel"``).
    - `max_steps`: outer iterations (per coarse-to-fine level).
    - `smoothness`: weight of the first-difference penalty on the slopes
      (residuals ``sqrt(w) * (s[i+1] - s[i])``), 0 to disable.
    - `coarse_to_fine`: number of extra coarser levels solved first (each half the
      resolution, down to 2 x 2 texels: `jaxnm.fit.level_sizes`), then upsampled as the
      next level's start.
    - `lsmr_steps`: inner LSMR iterations per (Gauss-Newton/LM) step (conjugate-gradient
      iterations for ``"lm-texel"``).
    - `rtol`, `atol`: convergence tolerances of the outer solver.
    - `seed`: initial-guess jitter seed (0 jitter by default: a flat start).
    - `init_noise`: standard deviation of the initial slopes.
    - `ftol`, `patience`: stop as converged when the loss changed by less than ``ftol``
      (relative) over the last ``patience`` *full* steps — steps the solver accepted and
      did not damp or shorten much (`jaxnm.fit.solve`, "When a fit stops"); 0 disables
      the test. The solver's own test (``rtol``/``atol`` on the steps) applies too, on
      full steps.
    - `texel_sums`: how ``"lm-texel"`` sums the pixels' contributions into the texels,
      one of `TEXEL_SUMS`: ``"scatter"`` (XLA's scatter-add: on a GPU its atomics add in
      an order that varies from run to run, and with `jaxnm.runtime.use_deterministic_ops`
      XLA sorts the indices on every call), ``"tables"`` (fixed-order sums through tables
      built once at the start of the fit from the prepared taps,
      `jaxnm.fit.texel_lm.texel_sum_tables`: the same result on every run, no sorting;
      not where the views are spread over several devices), or ``"auto"`` (the default:
      tables on a GPU or other accelerator with deterministic ops, as the command line
      runs, else scatter-adds: `jaxnm.fit.texel_sums_for` says which, and what each
      measured).
    """

    solver: str = "lm-texel"
    max_steps: int = 30
    smoothness: float = 0.0
    coarse_to_fine: int = 0
    lsmr_steps: int = 40
    rtol: float = 1e-6
    atol: float = 1e-8
    seed: int = 0
    init_noise: float = 0.0
    ftol: float = 1e-3
    patience: int = 3
    texel_sums: str = "auto"

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ValueError(f"FitOptions: unknown solver {self.solver!r}; expected one of "
                             f"{', '.join(SOLVERS)}")
        if self.texel_sums not in TEXEL_SUMS:
            raise ValueError(f"FitOptions: unknown texel_sums {self.texel_sums!r}; expected "
                             f"one of {', '.join(TEXEL_SUMS)}")
        if self.texel_sums == "tables" and self.solver != "lm-texel":
            raise ValueError(f"FitOptions: texel_sums 'tables' is for the 'lm-texel' solver, "
                             f"not {self.solver!r}")
        _check_int("max_steps", self.max_steps, 1)
        _check_int("lsmr_steps", self.lsmr_steps, 1)
        _check_int("coarse_to_fine", self.coarse_to_fine, 0)
        _check_int("seed", self.seed, 0)
        _check_number("smoothness", self.smoothness, 0.0)
        _check_number("init_noise", self.init_noise, 0.0)
        _check_number("rtol", self.rtol, 0.0)
        _check_number("atol", self.atol, 0.0)
        _check_number("ftol", self.ftol, 0.0)
        _check_int("patience", self.patience, 1)


@dataclasses.dataclass
class FitResult:
    """The fitted map and how the fit went.

    ``normals``: (h, w, 3) unit tangent-space normals (image layout, x along
    +u, y along +v, the decoded convention); ``slopes``: (h, w, 2);
    ``history``: one dict per step (level, size, step, loss, seconds; from step 1 on
    whether the solver accepted the step and how damped it was; the angular error when a
    ground truth was given); ``stopped``: why it ended (``"converged"``,
    ``"no_progress"``, ``"max_steps"``, ``"time_limit"``, ``"interrupted"`` or a
    solver's failure); ``stop_test``: the test that ended it (a key of
    `jaxnm.fit.stopping.STOP_TESTS`); ``noise_floor``: the float32 rounding of the start's
    loss, which a fit must beat to have made progress; ``identifiability``: the
    `check_identifiability` report.
    """

    normals: np.ndarray
    slopes: np.ndarray
    history: list
    seconds: float
    stopped: str
    best_loss: float
    identifiability: dict = dataclasses.field(default_factory=dict)
    stop_test: str = ""
    noise_floor: float = 0.0


def validate_problem(problem: FitProblem) -> None:
    """Raise a clear `ValueError` (naming ``problem.source``) for unusable input, before
    anything is compiled."""
    src = problem.source
    if not isinstance(problem.mesh, Mesh):
        raise ValueError(f"{src}: the mesh must be a jaxnm Mesh (jaxnm.io.load_mesh), got "
                         f"{type(problem.mesh).__name__}")
    if not isinstance(problem.material, Material):
        raise ValueError(f"{src}: the material must be a jaxnm Material "
                         f"(jaxnm.scene.default_material() is the built-in scene's), got "
                         f"{type(problem.material).__name__}")
    if problem.mesh.uv is None:
        raise ValueError(f"{src}: the mesh has no texture coordinates (uv); a normal map cannot "
                         "be fitted")
    if problem.mesh.normals is None:
        raise ValueError(f"{src}: the mesh has no vertex normals")
    try:
        check_frame(problem.frame)
        check_derivatives(problem.derivatives, allow_none=False)
        check_precision(problem.precision)
        if problem.precision == "float64":
            require_x64("precision 'float64'")
        check_shading_model(problem.shading)
    except ValueError as e:
        raise ValueError(f"{src}: {e}") from None
    if problem.frame == "none":
        raise ValueError(f"{src}: frame 'none' ignores the normal map; nothing to fit")
    if problem.sampling.space != "tangent":
        raise ValueError(f"{src}: only tangent-space maps can be fitted, not "
                         f"{problem.sampling.space!r}")
    if not problem.targets:
        raise ValueError(f"{src}: no target images")
    size = problem.map_size
    if (len(size) != 2 or any(isinstance(s, bool) or not isinstance(s, (int, np.integer))
                              or s < 2 for s in size)):
        raise ValueError(f"{src}: the map size must be two integers >= 2, got {size}")
    a_shape = jnp.shape(problem.albedo)
    if a_shape != (3,) and not (len(a_shape) == 3 and a_shape[2] == 3):
        raise ValueError(f"{src}: the albedo must be (3,) or (H, W, 3), got {a_shape}")
    for i, t in enumerate(problem.targets):
        if not isinstance(t, FitTarget):
            raise ValueError(f"{src}: target {i} must be a FitTarget, got {type(t).__name__}")
        name = t.name or f"target {i}"
        if not isinstance(t.camera, Camera):
            raise ValueError(f"{src}: {name}: the camera must be a Camera, got "
                             f"{type(t.camera).__name__}")
        if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1
               for v in (t.width, t.height)):
            raise ValueError(f"{src}: {name}: width and height must be positive integers, got "
                             f"{t.width!r} x {t.height!r}")
        img = np.asarray(t.image)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"{src}: {name}: the target must be an RGB image (H, W, 3), got "
                             f"shape {img.shape}")
        if img.shape[:2] != (t.height, t.width):
            raise ValueError(f"{src}: {name}: the target is {img.shape[1]}x{img.shape[0]} but "
                             f"its camera renders {t.width}x{t.height}")
        if not np.all(np.isfinite(img)):
            raise ValueError(f"{src}: {name}: the target has NaN or infinite values")
        if t.lights is not None and not isinstance(t.lights, Lights):
            raise ValueError(f"{src}: {name}: lights must be a jaxnm Lights "
                             f"(jaxnm.directional_light(...)), got {type(t.lights).__name__}")
        if t.lights is None or (t.lights.directional is None and t.lights.point is None):
            raise ValueError(f"{src}: {name}: no lights")
        if t.mask is not None:
            m = np.asarray(t.mask)
            if m.shape != (t.height, t.width):
                raise ValueError(f"{src}: {name}: the mask is {m.shape[1]}x{m.shape[0]}, "
                                 f"expected {t.width}x{t.height}")
            if not m.any():
                raise ValueError(f"{src}: {name}: the mask covers nothing")


@dataclasses.dataclass(frozen=True)
class FitJob:
    """A whole fit as ``jaxnm fit`` runs it: the problem and options, plus what is only
    scored (a ground-truth map, held-out targets), how to store the fitted map, and a
    time limit. Read from a fit file by `jaxnm.config.load_fit`; the built-in one is
    `jaxnm.procedural.default_fit_job`.

    - `ground_truth`: (h, w, 3) decoded unit normals, or None.
    - `held_out`: targets rendered with the fitted map and scored (PSNR), never fitted.
    - `output`: the encoding of ``normal_map.png`` (`encoding`, `green`, `bits` 8 or 16).
    - `time_limit`: seconds, or None.
    """

    problem: FitProblem
    options: FitOptions = FitOptions()
    ground_truth: np.ndarray | None = None
    held_out: tuple[FitTarget, ...] = ()
    output: NormalMapOptions = NormalMapOptions()
    time_limit: float | None = None

    def __post_init__(self):
        if self.output.bits not in (8, 16):
            raise ValueError(f"{self.problem.source}: map.bits must be 8 or 16 (PNG), got "
                             f"{self.output.bits!r}")
        if self.output.channels != 3:
            raise ValueError(f"{self.problem.source}: map.channels must be 3 (an RGB PNG)")
        if self.output.encoding not in ("unsigned", "unsigned_exact"):
            raise ValueError(f"{self.problem.source}: map.encoding must be 'unsigned' or "
                             f"'unsigned_exact' (a PNG stores unsigned values), got "
                             f"{self.output.encoding!r}")
        if self.ground_truth is not None:
            shape = np.shape(self.ground_truth)
            if shape != tuple(self.problem.map_size) + (3,):
                raise ValueError(f"{self.problem.source}: the ground truth is "
                                 f"{shape[:2]} but the map size is {self.problem.map_size}")
        tl = self.time_limit
        if tl is not None and (isinstance(tl, bool) or not isinstance(tl, (int, float))
                               or not math.isfinite(tl) or tl <= 0):
            raise ValueError(f"{self.problem.source}: the time limit must be a positive number "
                             f"of seconds, got {tl!r}")
