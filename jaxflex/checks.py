"""Checks of plain Python options (counts, seeds, weights), shared by every public entry point.

Each returns the value as a Python ``int`` or ``float`` (so that NumPy scalars read from
arrays or files, and concrete 0-d NumPy or JAX arrays, are accepted and stored as plain
numbers; a float32 as the shortest decimal that reads back to it) and raises ``ValueError`` naming the
option and the accepted range. Bools are refused everywhere: ``True`` is an ``int`` to Python
but never a count or a weight to a user. ``real_array`` is the type check of array-valued
parameters (gains, centres, the arm's constants), whose ranges their own checks add.
``instance`` refuses an object of the wrong kind (a continuous plant for a sampled one, an
uncalled factory for what it builds) before it fails deep inside with an AttributeError.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import fileio

SEED_RANGE = (-(2**63), 2**63)
"""Seeds are stored as 64-bit integers: ``[-2**63, 2**63)``."""


def _plain(name: str, value: Any) -> Any:
    """A NumPy scalar or a concrete 0-d NumPy or JAX array as the Python number it holds, a
    narrow float as the shortest decimal that reads back to it (``jnp.asarray(0.6)``, a
    float32, is 0.6, not 0.6000000238418579); a bool stays a bool, to be refused. Anything
    else as it is; a traced value is refused by ``name``: an option is a constant of the run."""
    if isinstance(value, jax.core.Tracer):
        raise ValueError(f"{name} must be a concrete number, not traced under jit, vmap or grad; got {value!r}")
    if isinstance(value, (np.generic, np.ndarray, jax.Array)) and np.shape(value) == ():
        return fileio.shortest(value)
    return value


def integer(name: str, value: Any, low: int = 1, unit: str = "", high: int | None = None) -> int:
    """``value`` as an int >= ``low`` (and <= ``high``); ``unit`` (e.g. ``"samples"``) is
    named in the message."""
    value = _plain(name, value)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise ValueError(f"{name} must be an integer {bound}{f' ({unit})' if unit else ''}; got {value!r}")
    return int(value)


def flag(name: str, value: Any) -> bool:
    """``value`` as a bool: True or False (a NumPy bool too); any other value is refused by
    ``name`` (``resume="no"`` read as true)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False; got {value!r}")
    return bool(value)


def seed(name: str, value: Any) -> int:
    """``value`` as an int in ``SEED_RANGE``."""
    value = _plain(name, value)
    low, high = SEED_RANGE
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value < high:
        raise ValueError(f"{name} must be an integer in [-2**63, 2**63); got {value!r}")
    return int(value)


def number(name: str, value: Any, low: float = 0.0, *, strict: bool = False, unit: str = "") -> float:
    """``value`` as a finite float >= ``low`` (> ``low`` when ``strict``)."""
    value = _plain(name, value)
    bound = f"{'>' if strict else '>='} {low:g}"
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not math.isfinite(value)
        or value < low
        or (strict and value == low)
    ):
        raise ValueError(f"{name} must be a finite number{f' of {unit}' if unit else ''} {bound}; got {value!r}")
    return float(value)


def instance(name: str, value: Any, expected: type | tuple[type, ...], build: str) -> Any:
    """``value`` when it is an ``expected`` (a type, or a tuple of accepted types); else
    ``ValueError`` naming ``name``, the expected type(s), how to get one (``build``, e.g.
    ``"build one with jaxflex.discretize(plant, dt, method)"``) and what was given (an uncalled function by
    its name)."""
    if not isinstance(value, expected):
        what = type(value).__name__
        if callable(value) and not isinstance(value, type) and hasattr(value, "__name__"):
            what = f"the function {value.__name__} itself: call it to build one"
        names = " or ".join(t.__name__ for t in (expected if isinstance(expected, tuple) else (expected,)))
        article = "an" if names[0] in "AEIOU" else "a"
        raise ValueError(f"{name} must be {article} {names} ({build}); got {what}")
    return value


def callback(name: str, value: Any, called_with: str) -> Any:
    """``value`` when it is None or callable; else ``ValueError`` naming ``name`` and what it is
    called with, before a long run would fail at its first call."""
    if value is not None and not callable(value):
        raise ValueError(f"{name} must be None or a function called with {called_with}; got {type(value).__name__} {value!r}")
    return value


def float_dtype(name: str, dtype: Any) -> np.dtype:
    """``dtype`` (``None``: JAX's default float) as a NumPy dtype when it is a floating one;
    an integer dtype would truncate every value cast to it (a 5 ms delay to 0)."""
    try:
        resolved = jnp.zeros((), dtype).dtype
    except TypeError as err:
        raise ValueError(f"{name} must be a floating dtype (jnp.float32, jnp.float64); got {dtype!r}") from err
    if not jnp.issubdtype(resolved, jnp.floating):
        raise ValueError(f"{name} must be a floating dtype (jnp.float32, jnp.float64); got {resolved}")
    return resolved


def real_array(name: str, value: Any, *, scalar: bool = False) -> np.ndarray:
    """``value`` (a number or an array of them, concrete) as a NumPy array of a real dtype;
    ``scalar`` names a number alone as accepted (the caller checks the shape).

    Strings, bools, complex numbers and objects are refused by name: NumPy would turn
    ``"0.9"`` into a number silently, and ``"a"`` into an error that names nothing.
    """
    accepted = f"{name} must be a real number{'' if scalar else ' or an array of real numbers'}; got {value!r}"
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as err:  # ragged sequences
        raise ValueError(accepted) from err
    if not (jnp.issubdtype(arr.dtype, jnp.integer) or jnp.issubdtype(arr.dtype, jnp.floating)):  # bool is neither; bfloat16 is floating
        raise ValueError(accepted)
    return arr
