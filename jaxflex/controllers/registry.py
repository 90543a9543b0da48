"""Controllers by name: ``by_name("dfs+fuzzy", dt=1e-3)`` -> ``(controller, params)``.

The one place where a controller named in a configuration (``jaxflex bench``, the Monte
Carlo runner, ``jaxflex reproduce``, a tuned.json, the tuner) becomes a jaxflex controller
and its parameter pytree. Parameters are given by name (``k``, ``tau_s``, ``k1``, ``k2``,
``k3``); a missing name takes the paper's value (DFS: k = 55 N*m/rad, tau = 5 ms; fuzzy:
k1 = 1.02, k2 = 0.30, k3 = 1.0 with the paper's rules and centres).
"""

from __future__ import annotations

import math
from types import MappingProxyType
from typing import Any, Mapping

import jax
import jax.numpy as jnp

from jaxflex import checks
from jaxflex.controllers.base import Controller, OpenLoopParams, check_finite_scalar, combine, open_loop
from jaxflex.controllers.dfs import DFSParams, dfs
from jaxflex.controllers.fuzzy import check_defuzz, check_temperature, fuzzy, fuzzy_params
from jaxflex.delay import check_capacity
from jaxflex.pade import check_order

NAMES = ("open_loop", "dfs", "fuzzy", "dfs+fuzzy")
DELAYS = ("nearest", "linear", "cubic", "pade")
"""How DFS reads theta(t - tau): a ring-buffer read (``dfs(interpolation=...)``) or Pade states."""
PAPER_PARAMS = MappingProxyType({"k": 55.0, "tau_s": 0.005, "k1": 1.02, "k2": 0.30, "k3": 1.0})
PARAMETERS = MappingProxyType({"open_loop": (), "dfs": ("k", "tau_s"), "fuzzy": ("k1", "k2", "k3"), "dfs+fuzzy": ("k", "tau_s", "k1", "k2", "k3")})
"""The parameter names each controller uses."""
CONFIG_OPTIONS = ("capacity", "delay", "pade_order", "fuzzy_temperature")
"""The keys under which a tuner or Monte Carlo config, tuned.json and summary.json record how the
controller was built (``by_name``'s ``capacity``, ``delay``, ``pade_order`` and ``temperature``)."""


def param_values(params: Mapping[str, Any] | None, what: str = "params") -> dict[str, float]:
    """Every parameter by name: the given values as floats, the paper's for the others.

    Raises:
      ValueError: naming ``what[key]`` for an unknown name or a value that is not a finite
        number (bools and strings included).
    """
    if params is not None and not isinstance(params, Mapping):
        raise ValueError(f"{what} must be a mapping of parameter values by name ({{'k': 55.0, 'tau_s': 0.005}}); got {params!r}")
    given = dict(params or {})
    unknown = sorted(set(given) - set(PAPER_PARAMS))
    if unknown:
        raise ValueError(f"{what}: unknown parameter name(s) {unknown}; accepted: {list(PAPER_PARAMS)}")
    values = dict(PAPER_PARAMS)
    for key, value in given.items():
        try:
            number = None if isinstance(value, (bool, str, bytes)) else float(value)
        except (TypeError, ValueError):
            number = None
        if number is None or not math.isfinite(number):
            raise ValueError(f"{what}[{key!r}] must be a finite number; got {value!r}")
        values[key] = number
    return values


def by_name(
    name: str,
    *,
    dt: float,
    params: Mapping[str, Any] | None = None,
    capacity: int = 64,
    delay: str = "nearest",
    pade_order: int = 4,
    defuzz: str = "centroid",
    temperature: float = 0.0,
    dtype: jax.typing.DTypeLike | None = None,
) -> tuple[Controller, Any]:
    """The controller ``name`` and its parameters.

    Args:
      name: one of ``NAMES``: ``"open_loop"``, ``"dfs"``, ``"fuzzy"`` or ``"dfs+fuzzy"``
        (``combine`` of the two; parameters ``(DFSParams, FuzzyParams)``).
      dt: sample time of the loop (s).
      params: parameter values by name (``PARAMETERS``); missing names take the paper's
        values (``PAPER_PARAMS``), names the controller does not use are ignored, and
        any other name is refused.
      capacity: DFS delay-buffer capacity (samples).
      delay: how DFS reads the delayed angle, one of ``DELAYS``: ``"nearest"``,
        ``"linear"`` or ``"cubic"`` (``dfs(interpolation=delay)``), or ``"pade"``
        (``dfs(approximation="pade", pade_order=pade_order)``).
      pade_order: Pade order, with ``delay="pade"`` only.
      defuzz, temperature: the fuzzy controller's (``fuzzy(defuzz=..., temperature=...)``).
      dtype: dtype of every parameter leaf; ``None``: DFS gains as Python floats and fuzzy
        leaves in JAX's default float dtype.

    Returns:
      ``(controller, params)``; the parameters are not checked (``controller.check``).

    Raises:
      ValueError: naming ``name``, ``delay``, ``params`` or an option and the accepted
        values (the options are checked whether ``name`` reads them or not).
    """
    if name not in NAMES:
        raise ValueError(f"name must be one of {NAMES}; got {name!r}")
    check_finite_scalar("dt", dt, positive=True)  # DFS's own check: every name takes a sample time
    if delay not in DELAYS:
        raise ValueError(f"delay must be one of {DELAYS}; got {delay!r}")
    # every option, whether this controller reads it or not (a Pade order of -5 passed unseen)
    check_capacity(capacity)
    check_order(pade_order, "pade_order")
    check_defuzz(defuzz)
    check_temperature(temperature)
    values = param_values(params)
    if dtype is not None:
        dtype = checks.float_dtype("dtype", dtype)
    scalar = float if dtype is None else (lambda v: jnp.asarray(v, dtype))
    parts = []
    if name in ("dfs", "dfs+fuzzy"):
        controller = dfs(dt, capacity, approximation="pade", pade_order=pade_order) if delay == "pade" else dfs(dt, capacity, interpolation=delay)
        parts.append((controller, DFSParams(scalar(values["k"]), scalar(values["tau_s"]))))
    if name in ("fuzzy", "dfs+fuzzy"):
        parts.append((fuzzy(defuzz=defuzz, temperature=temperature), fuzzy_params(values["k1"], values["k2"], values["k3"], dtype=dtype)))
    if not parts:
        return open_loop(), OpenLoopParams()
    if len(parts) == 1:
        return parts[0]
    (first, first_params), (second, second_params) = parts
    return combine(first, second), (first_params, second_params)
