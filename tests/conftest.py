"""Shared test configuration: strict JAX numerics, small scenes, optional GL."""

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402

jax.config.update("jax_numpy_rank_promotion", "raise")

from hypothesis import settings  # noqa: E402

# Deterministic property tests: the same examples on every run and in CI.
settings.register_profile("jaxnm", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("jaxnm")
