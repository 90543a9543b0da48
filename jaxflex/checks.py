"""Checks of plain Python options (counts, seeds, weights), shared by every public entry point.

Each returns the value as a Python ``int`` or ``float`` (so that NumPy scalars read from
arrays or files are accepted and stored as plain numbers) and raises ``ValueError`` naming the
option and the accepted range. Bools are refused everywhere: ``True`` is an ``int`` to Python
but never a count or a weight to a user. Array-valued parameters are checked by
``controllers.base.check_finite_scalar`` instead.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

SEED_RANGE = (-(2**63), 2**63)
"""Seeds are stored as 64-bit integers: ``[-2**63, 2**63)``."""


def integer(name: str, value: Any, low: int = 1, unit: str = "") -> int:
    """``value`` as an int >= ``low``; ``unit`` (e.g. ``"samples"``) is named in the message."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}{f' ({unit})' if unit else ''}; got {value!r}")
    return int(value)


def seed(name: str, value: Any) -> int:
    """``value`` as an int in ``SEED_RANGE``."""
    low, high = SEED_RANGE
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value < high:
        raise ValueError(f"{name} must be an integer in [-2**63, 2**63); got {value!r}")
    return int(value)


def number(name: str, value: Any, low: float = 0.0, *, strict: bool = False, unit: str = "") -> float:
    """``value`` as a finite float >= ``low`` (> ``low`` when ``strict``)."""
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
