"""When a fit stops: the tests that end it, in the order a step applies them (`decide`).

From step 1 on, every step records whether the solver *accepted* the point it evaluated,
how *damped* the move to that point was (the share of the move the solver held back, in
[0, 1]) and the decrease of the loss its model *predicted* for it. For Levenberg–Marquardt
(``"lm"``, ``"lm-texel"``) the damping is the damping's share of the curvature along the
move ``d``, ``lambda |d|^2 / (d.H d + lambda |d|^2)`` (1: a short gradient step, 0: the
Gauss–Newton step), and the prediction the Gauss–Newton model's; for L-BFGS, how much the
backtracking line search shortened its first trial, and the gradient's linear
prediction; Gauss–Newton takes every step at full length. What the model *promised*
(`promised`) is the prediction undamped: ``predicted / (1 - damping)``.

The fit has **converged** (``"ftol"``, `stop_test`) when over the level's last ``patience``
steps the loss changed by less than ``ftol`` (relative) *and* at none of them did the
solver's model promise a larger decrease. The solver's own test (``rtol``/``atol``: a tiny
accepted move and loss change) counts only on an accepted step damped less than
`FULL_STEP_DAMPING`.

Why: a damped or backtracking solver moves the loss little because it holds its steps
back, not because little is left to gain. Levenberg–Marquardt from a start whose
curvature is far below its first damping takes steps of length ``|g| / lambda``
(optimistix starts at ``lambda = 1`` whatever the problem's scale), and the loss barely
moves until the damping has come down (docs/guides/fitting.md has an example). A
backtracking L-BFGS keeps the loss exactly flat while it halves its trial step, and
Gauss–Newton far from the answer can raise the loss before it lowers it. In all these the
model, undamped, promises far more than the loss gave, so the fit goes on. At the answer
both are small — also when the solver rejects every step because float32 cannot resolve
a smaller loss (a rejected step changes nothing; its model promised next to nothing) — so
the fit stops.

Changes and promises below the loss's **noise floor** (`noise_floor`: the float32
rounding of its sum and of the residuals it sums) count as nothing: at the end of a
noise-free fit, float32 cannot resolve anything smaller. A fit that ends on its own
(converged, the solver's test, or ``max_steps``) without lowering the loss below its
start's by more than the start's noise floor reports ``stopped == "no_progress"``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import optimistix as optx

from ._processes import local_rows, sum_over_processes
from .distributed import spread_over_processes
from .prepare import Prepared
from .problem import FitOptions

__all__ = ["FULL_STEP_DAMPING", "STOP_TESTS", "decide", "loss_terms", "noise_floor", "promised",
           "stop_test"]

#: The solver's own tolerance test (a tiny move and loss change) counts only on an accepted
#: step damped less than this: a damped step is tiny because it is damped.
FULL_STEP_DAMPING = 0.5

#: The tests that can end a fit (`FitResult.stop_test`), with what they mean.
STOP_TESTS = {
    "ftol": "over the level's last `patience` steps the loss changed by less than ftol "
            "(relative), and the solver's model, undamped, promised no larger decrease at "
            "any of them",
    "solver_tolerance": "the solver's own test (rtol, atol on the step's move and loss "
                        "change) passed on an accepted step damped less than "
                        f"{FULL_STEP_DAMPING:g}",
    "solver_failure": "the solver reported a failure",
    "max_steps": "every step of every level was taken",
    "time_limit": "the time limit passed",
    "should_stop": "the caller's `should_stop` asked to stop",
    "keyboard_interrupt": "KeyboardInterrupt (Ctrl-C)",
}


def promised(rec: dict) -> float:
    """The decrease of the loss the solver's model promised for the step of ``rec`` (a
    history record from step 1 on) had the solver not damped it: ``predicted / (1 -
    damping)`` (infinite for a move damped to nothing). For a line search's shortened step
    this is its full step's linear prediction; for Levenberg-Marquardt it lies between the
    undamped Gauss-Newton step's predicted decrease and twice that (exactly so on a
    quadratic with one curvature)."""
    held = 1.0 - rec["damping"]
    return rec["predicted"] / held if held > 0 else math.inf


def stop_test(records: list[dict], options: FitOptions,
              floor: Callable[[float], float] | None = None) -> str | None:
    """The convergence test (the module's docstring) on one level's ``records``
    (history entries, the level's start first): ``"ftol"`` when over the last
    ``options.patience`` steps the loss changed by less than ``options.ftol`` (relative)
    and at none of them did the solver's model, undamped (`promised`), predict a larger
    decrease; None otherwise, and always with ``ftol`` 0. ``floor``: the loss's noise floor
    as a function of the loss (`noise_floor`): changes and promises below it count as
    nothing."""
    ftol, patience = options.ftol, options.patience
    if ftol <= 0 or len(records) <= patience:
        return None

    def small(x: float, loss_value: float) -> bool:
        return x <= max(ftol * abs(loss_value), floor(loss_value) if floor else 0.0)

    window = records[-1 - patience:]
    before = window[0]["loss"]
    if (small(abs(before - window[-1]["loss"]), before)
            and all(small(promised(rec), prev["loss"]) for prev, rec in zip(window, window[1:]))):
        return "ftol"
    return None


def noise_floor(loss_value: float, terms: int, mean_square: float) -> float:
    """The rounding in a float32 loss ``0.5 |r|^2`` of ``terms`` residuals, whose targets'
    values have the mean square ``mean_square``: ``eps32 (sqrt(terms) |loss| + 8 sqrt(2
    |loss| mean_square))``. The first term is the float32 sum's (``terms`` roundings of
    random sign); the second the residuals' own, each a few roundings of the image value
    it subtracts (its factor 8 covers what noise-free fits end at: docs/guides/fitting.md).
    A loss change below it cannot be told from rounding."""
    eps = float(np.finfo(np.float32).eps)
    loss_value = abs(loss_value)
    return eps * (math.sqrt(terms) * loss_value + 8.0 * math.sqrt(2.0 * loss_value * mean_square))


def loss_terms(prep: Prepared) -> tuple[int, float]:
    """The number of residuals of ``prep``'s loss and the mean square of its targets' values
    (for `noise_floor`; on the host, so no XLA program is compiled for it)."""
    terms = sum(b.images.size for b in prep.batches)
    square = np.array([sum(float(np.sum(np.square(local_rows(b.images)[1], dtype=np.float64)))
                           for b in prep.batches)])
    if spread_over_processes(prep):
        square = sum_over_processes(square)
    return terms, float(square[0]) / max(terms, 1)


def decide(rec: dict, records: list[dict], options: FitOptions, floor: Callable[[float], float],
           *, done: bool, result, late: bool, asked: Callable[[], bool]) -> tuple[str, str]:
    """``(stopped, test)`` after the step of history record ``rec`` (``records``: its
    level's, ``rec`` last): the first test that holds, in this order: the time limit
    (``late``), the solver's failure (``result``) or its own test (``done`` on an accepted
    step damped less than `FULL_STEP_DAMPING`), `stop_test`, the caller's request
    (``asked()``, called only when nothing before held); ``("max_steps", "max_steps")``
    when none does."""
    k = rec["step"]
    if late:
        return "time_limit", "time_limit"
    if k > 0 and done and result != optx.RESULTS.successful:
        return str(result), "solver_failure"
    if k > 0 and done and rec["accepted"] and rec["damping"] < FULL_STEP_DAMPING:
        return "converged", "solver_tolerance"
    if stop_test(records, options, floor) is not None:
        return "converged", "ftol"
    if asked():
        return "interrupted", "should_stop"
    return "max_steps", "max_steps"
