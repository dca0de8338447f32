r"""Fit a tangent-space normal map to target shading.

Given a mesh with uvs, one or more views, lights, a material and target images,
find the normal map whose rendering matches the targets.

**Model.** The geometry is fixed, so each view's G-buffer — visibility, the
perspective-correct position, uv, normal, their screen derivatives, the
cotangent frame and the normal map's sample plan (texel indices, filter
weights, mip level of detail) — is computed **once** (`prepare`), and kept
only for the pixels the mesh covers, as a flat list. A step then only runs
the texel-dependent stages on those pixels: build the mip chain of the current
map (once, for all views), one gather and weighted sum per pixel (4 taps
where the fixed level of detail reads a single mip level, 8 elsewhere),
perturb, shade, subtract the target. Views and their lights are batched with
``vmap`` (views padded to a common pixel and target count; views whose lights
differ in kind or count form separate batches, see `ViewBatch`).

**Parameterisation.** Each texel holds two slopes ``(s_x, s_y)``; its normal is
``normalize(s_x, s_y, 1)``: always a unit vector with positive z, with no
constraint to enforce and no singular point.

**Solvers.** ``"lm-texel"`` (the default, `jaxnm.fit.texel_lm`):
Levenberg–Marquardt on the normal equations in texel space — one pass over the
pixels per step forms each pixel's 3x3 Gauss–Newton block and the gradient,
and conjugate gradients solve the damped system from those blocks, so nothing
per pixel but 6 numbers outlives a chunk of pixels, however many views.
optimistix's ``"lm"`` Levenberg–Marquardt and ``"gn"`` Gauss–Newton, both
matrix-free: the Jacobian is a linearised function (forward-mode JVP,
transposed for the VJP) and each step is solved by lineax's iterative LSMR,
whose vectors and linearisation live in residual space; ``"lbfgs"``: the
first-order baseline, L-BFGS on the sum of squares. No dense Jacobian is ever
formed. The step is compiled once per problem shape and reused across calls.

**Identifiability.** A normal has two degrees of freedom. One light gives one
equation per texel (a cone of possible normals); two lights leave a two-fold
ambiguity; three lights whose directions (as seen from the surface) are not
coplanar determine the normal under Lambertian shading (photometric stereo).
So a fit needs at least three non-coplanar lights per texel, in some view that
sees it lit; `check_identifiability` warns otherwise. Texels in attached
shadow for most lights, or seen only at grazing angles (only coarse mip
levels), are weakly determined; the optional smoothness term regularises them.


The package, by stage: `problem` (what to fit: `FitProblem`, `FitTarget`,
`FitOptions`, `FitResult`), `prepare` (the fixed geometry, once), `model`
(`residuals` and `loss` over `ModelArgs`), `solve` (`fit_normal_map`), `stored` (a map
fitted through its storage, BC5 blocks or 8-bit codes: `fit_stored_map`),
`diagnostics` (seen texels, identifiability, errors), `report` (what
``jaxnm fit`` writes), `checkpoint` (a running fit saved, to resume it) and `distributed`
(a fit across processes, `prepare_processes`). The
built-in problem is `jaxnm.procedural.default_problem`.
"""

from .checkpoint import Checkpoint as Checkpoint
from .checkpoint import load_checkpoint as load_checkpoint
from .diagnostics import angular_error as angular_error
from .diagnostics import check_identifiability as check_identifiability
from .diagnostics import error_report as error_report
from .diagnostics import psnr as psnr
from .diagnostics import seen_texels as seen_texels
from .diagnostics import texel_influence as texel_influence
from .distributed import check_same_across_processes as check_same_across_processes
from .distributed import local_prepared as local_prepared
from .distributed import prepare_processes as prepare_processes
from .distributed import process_targets as process_targets
from .distributed import spread_over_processes as spread_over_processes
from .model import ModelArgs as ModelArgs
from .model import loss as loss
from .model import normals_to_slopes as normals_to_slopes
from .model import render_with_map as render_with_map
from .model import residuals as residuals
from .model import sample_split as sample_split
from .model import slopes_to_normals as slopes_to_normals
from .prepare import CHUNK as CHUNK
from .prepare import Prepared as Prepared
from .prepare import View as View
from .prepare import ViewBatch as ViewBatch
from .prepare import prepare as prepare
from .prepare import shard_views as shard_views
from .prepare import view_key as view_key
from .prepare import with_map_size as with_map_size
from .problem import SOLVERS as SOLVERS
from .problem import TEXEL_SUMS as TEXEL_SUMS
from .problem import FitJob as FitJob
from .problem import FitOptions as FitOptions
from .problem import FitProblem as FitProblem
from .problem import FitResult as FitResult
from .problem import FitTarget as FitTarget
from .problem import FitWarning as FitWarning
from .problem import problem_from_scene as problem_from_scene
from .problem import validate_problem as validate_problem
from .report import FitOutputs as FitOutputs
from .report import fit_outputs as fit_outputs
from .report import fit_renders as fit_renders
from .report import prepare_held_out as prepare_held_out
from .report import score_held_out as score_held_out
from .solve import StepResult as StepResult
from .solve import compile_fit as compile_fit
from .solve import fit_normal_map as fit_normal_map
from .solve import fit_step as fit_step
from .solve import level_sizes as level_sizes
from .solve import make_solver as make_solver
from .solve import preconditioner as preconditioner
from .solve import start_state as start_state
from .solve import texel_sums_for as texel_sums_for
from .stopping import STOP_TESTS as STOP_TESTS
from .stored import STORAGES as STORAGES
from .stored import StoredFit as StoredFit
from .stored import fit_stored_map as fit_stored_map

__all__ = [
    "SOLVERS", "TEXEL_SUMS", "FitOptions", "FitProblem", "FitResult", "FitTarget",
    "FitWarning", "ModelArgs",
    "Prepared", "View", "ViewBatch", "angular_error", "check_identifiability", "error_report",
    "fit_normal_map", "fit_step", "start_state", "StepResult", "compile_fit", "level_sizes",
    "loss", "make_solver", "normals_to_slopes",
    "preconditioner", "prepare", "problem_from_scene", "psnr", "render_with_map", "residuals",
    "sample_split", "seen_texels", "slopes_to_normals", "texel_influence", "validate_problem",
    "view_key", "with_map_size", "shard_views", "FitJob", "FitOutputs", "fit_outputs",
    "prepare_held_out", "score_held_out", "CHUNK", "texel_sums_for", "STOP_TESTS",
    "Checkpoint", "load_checkpoint", "fit_renders", "STORAGES", "StoredFit", "fit_stored_map",
    "process_targets", "prepare_processes",
    "spread_over_processes", "local_prepared", "check_same_across_processes",
]
