"""Whether a program is built to run on its device without waiting for the host
(`resident`), and a way to ask for that program on the CPU (`forced`).

On a GPU, XLA runs a ``while`` loop whose trip count it cannot find at compile time by
copying its condition to the host and waiting for it, every iteration; a ``conditional``
copies its predicate likewise (XLA's GPU runtime: ``WhileThunk``, ``ConditionalThunk``).
Each such wait costs a round trip that is long next to a frame's kernels. So on every
backend but the CPU the execution layer builds *resident* programs: loops with trip counts
known when the program is compiled (XLA runs those without reading anything back), selects
in place of conditionals, and no data-dependent loop as a fusion barrier. The CPU keeps its
loops and conditionals: there a condition costs nothing to read, and they skip work.

Which way a program is built is decided when it is traced, from the backend, and the choice
is part of JAX's compilation-cache key where `forced` is used (a `jax.make_user_context`),
so a program built one way is never reused for the other.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp

__all__ = ["choose", "forced", "resident"]

#: The resident path asked for whatever the backend (True / False), or None: by backend.
#: A JAX user context: part of the key of every jit cache, so that forcing retraces.
_FORCE = jax.make_user_context(default_value=None)


def resident(backend: str | None = None) -> bool:
    """Whether programs traced now run without waiting for the host: on every backend but
    the CPU (``backend``, JAX's default if None), unless `forced` says otherwise."""
    force = _FORCE.value
    if force is not None:
        return bool(force)
    backend = jax.default_backend() if backend is None else backend
    return backend != "cpu"


@contextlib.contextmanager
def forced(on: bool = True):
    """Within the block, programs are traced as `resident` says ``on`` whatever the
    backend: the tests run the accelerators' programs on the CPU this way. Part of the
    compilation-cache key, so programs already compiled the other way are not reused."""
    with _FORCE(bool(on)):
        yield


def choose(pred, on_true, on_false, *operands):
    """``on_true(*operands)`` where the scalar ``pred`` holds, else ``on_false(*operands)``
    (pytrees of the same structure): a `jax.lax.cond` where programs are not `resident`,
    which runs one branch; else both, and a select per leaf (no conditional whose predicate
    a GPU reads back). Use it where both branches are cheap next to a wait for the host."""
    if not resident():
        return jax.lax.cond(pred, on_true, on_false, *operands)
    yes, no = on_true(*operands), on_false(*operands)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), yes, no)
