"""What ``jaxnm fit`` reports: the fitted map encoded for saving, re-renders beside the
targets, the error map, held-out scores and a JSON-ready summary. Writing them to files is
`jaxnm.io.write_fit_outputs`."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..textures import encode_normal_map, linear_to_srgb, quantize
from .diagnostics import angular_error, error_report, psnr, seen_texels
from .model import render_with_map
from .prepare import Prepared, prepare
from .problem import FitJob, FitResult
from .stopping import FULL_STEP_DAMPING, STOP_TESTS

__all__ = ["FitOutputs", "fit_outputs", "fit_renders", "prepare_held_out", "score_held_out",
           "ERROR_MAP_RANGE_DEG", "stopped_in_words"]

#: The error map shows 0 to this many degrees as black to white (unseen texels dark grey).
ERROR_MAP_RANGE_DEG = 10.0


@dataclasses.dataclass
class FitOutputs:
    """Everything ``jaxnm fit`` writes, as arrays and dicts.

    - `map_texels`: (h, w, 3) the fitted map encoded as ``job.output`` says, in
      [0, 1] on the codes of a `bits`-bit PNG (``normal_map.png``).
    - `normals`, `slopes`: float unit normals and slopes (``normal_map.npz``).
    - `renders`: per target, ``target | re-render | 4 x |difference|`` as sRGB
      rows (``render_NN.png``).
    - `history`: the loss (and error) per step (``loss.json``, ``loss.png``).
    - `error_map`: (h, w) grey levels of the per-texel angular error, or None
      without a ground truth (``error_map.png``).
    - `report`: the summary (``report.json``).
    """

    map_texels: np.ndarray
    bits: int
    normals: np.ndarray
    slopes: np.ndarray
    renders: list
    history: list
    error_map: np.ndarray | None
    report: dict


def prepare_held_out(job: FitJob) -> tuple[Prepared, ...]:
    """Each held-out target of ``job`` prepared (its view rasterized once), for
    `score_held_out`. Prepared with the fit's own views, they reuse the G-buffer program
    those compiled (after the fit, `jaxnm fit` has dropped it to free memory)."""
    return tuple(prepare(dataclasses.replace(job.problem, targets=(t,)))
                 for t in job.held_out)


def score_held_out(job: FitJob, normals: np.ndarray,
                   prepared: tuple[Prepared, ...] | None = None) -> list[dict]:
    """PSNR of each held-out target rendered with ``normals`` (and, with a ground truth, of
    the ground truth's render) over the pixels that count; ``prepared``: the held-out
    targets' `prepare_held_out` (default: prepared here)."""
    out = []
    if prepared is None:
        prepared = prepare_held_out(job)
    for t, prep in zip(job.held_out, prepared, strict=True):
        fitted = np.asarray(render_with_map(prep, jnp.asarray(normals))[0][0])
        m = prep.target_mask(0)
        rec = {"name": t.name, "psnr_db_vs_target": round(psnr(fitted, t.image, m), 2)}
        if job.ground_truth is not None:
            truth = np.asarray(render_with_map(prep, jnp.asarray(job.ground_truth))[0][0])
            rec["psnr_db_vs_ground_truth_render"] = round(psnr(fitted, truth, m), 2)
        out.append(rec)
    return out


def fit_renders(prep: Prepared, normals: np.ndarray) -> list:
    """Per target of ``prep``, the row ``target | re-render with normals | 4 x |difference|``
    as sRGB (`FitOutputs.renders`)."""
    rows = []
    for v, imgs in enumerate(render_with_map(prep, jnp.asarray(normals))):
        imgs = np.asarray(imgs)
        targets = prep.target_images(v)
        for t in range(imgs.shape[0]):
            row = np.concatenate([targets[t], imgs[t], np.abs(imgs[t] - targets[t]) * 4], 1)
            rows.append(np.asarray(linear_to_srgb(np.clip(row, 0, 1))))
    return rows


def stopped_in_words(result: FitResult, options) -> str:
    """Why a fit stopped, for people: ``"reached the step limit"`` for ``"max_steps"``,
    and so on (``report.json``'s ``"stopped_because"``). A fit resumed from a checkpoint
    already past ``options.max_steps`` (no step taken) says so."""
    n = options.max_steps
    limit = f"{n} step{'' if n == 1 else 's'}{' a level' if options.coarse_to_fine else ''}"
    last = result.history[-1] if result.history else {"step": 0}
    if result.stopped == "max_steps" and last["step"] > n:
        return f"was resumed past the step limit ({limit})"
    words = {
        "converged": "converged",
        "max_steps": f"reached the step limit ({limit})",
        "time_limit": "reached the time limit",
        "interrupted": "was interrupted",
        "no_progress": "made no progress (the loss never went below the start's by more than "
                       "its rounding)",
    }
    return words.get(result.stopped, f"stopped: the solver reported {result.stopped}")


def _convergence_rule(options) -> str:
    """The stopping rule of ``options`` in words (``report.json``'s ``_convergence_rule``)."""
    o = options
    solver = (f"the solver's step test (rtol {o.rtol:g}, atol {o.atol:g}) on a full step")
    if o.ftol <= 0:
        return solver
    return (f"the loss changed by less than {o.ftol:g} (relative) over the last "
            f"{o.patience} full steps (accepted, damped less than {FULL_STEP_DAMPING:g}, "
            f"the loss not raised by more than {o.ftol:g}), or {solver}")


def fit_outputs(job: FitJob, prep: Prepared, result: FitResult, *,
                prepare_seconds: float = 0.0,
                held_out: tuple[Prepared, ...] | None = None,
                optional: bool = True, seen: np.ndarray | None = None) -> FitOutputs:
    """The outputs of a finished fit (see `FitOutputs`); ``held_out``: the held-out
    targets' `prepare_held_out`, if already made; ``seen``: the `seen_texels` the error is
    measured over, if already known (default: ``prep``'s; for a fit across processes, made
    on every process, while ``prep`` is the writing process's `local_prepared`). With
    ``optional`` False the slow parts are left out: no `renders` (`fit_renders`) and no
    held-out scores (`score_held_out`), the report listing them under ``"skipped"``."""
    problem, enc = job.problem, job.output
    n = result.normals
    texels = np.asarray(quantize(encode_normal_map(jnp.asarray(n), encoding=enc.encoding,
                                                   green=enc.green, bits=enc.bits), enc.bits))
    report = {"stopped": result.stopped,
              "stopped_because": stopped_in_words(result, job.options),
              "stop_test": result.stop_test,
              "stop_test_meaning": STOP_TESTS.get(result.stop_test, ""),
              "convergence_rule": _convergence_rule(job.options),
              "steps": sum(1 for h in result.history if h["step"] > 0),
              "fit_seconds": round(result.seconds, 2), "prepare_seconds": round(prepare_seconds, 2),
              "start_loss": result.history[0]["loss"] if result.history else None,
              "final_loss": result.best_loss,
              "start_loss_rounding": result.noise_floor,
              "identifiability": result.identifiability,
              "solver": dataclasses.asdict(job.options), "map_size": list(problem.map_size),
              "frame": problem.frame, "derivatives": problem.derivatives,
              "precision": problem.precision,
              "tangents": (problem.mesh.tangent_source or "mikktspace")
              if problem.frame == "vertex" else None,
              "map_encoding": {"encoding": enc.encoding, "green": enc.green, "bits": enc.bits,
                               "uv_origin": problem.sampling.uv_origin}}
    error_map = None
    if job.ground_truth is not None:
        if seen is None:
            seen = seen_texels(prep, problem.map_size)
        report["error"] = error_report(n, job.ground_truth, seen)
        err = angular_error(n, job.ground_truth)
        error_map = np.where(seen, np.clip(err / ERROR_MAP_RANGE_DEG, 0, 1), 0.25)
        error_map = error_map.astype(np.float32)
    rows = []
    if optional:
        rows = fit_renders(prep, n)
        if job.held_out:
            report["held_out"] = score_held_out(job, n, held_out)
    else:
        report["skipped"] = ["renders"] + (["held_out"] if job.held_out else [])
    return FitOutputs(map_texels=texels, bits=enc.bits, normals=n.astype(np.float32),
                      slopes=result.slopes.astype(np.float32), renders=rows,
                      history=result.history, error_map=error_map, report=report)
