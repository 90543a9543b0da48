"""Shared test helpers."""

from __future__ import annotations

import jax
import numpy as np


def tree_allclose(a, b, rtol: float = 1e-12, atol: float = 0.0) -> None:
    """Same tree structure, then assert_allclose leaf by leaf."""
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for la, lb in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(la), np.asarray(lb), rtol=rtol, atol=atol)
