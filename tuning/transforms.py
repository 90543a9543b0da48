"""Unconstrained <-> physical controller parameters, and the controllers the tuner knows.

Gains are positive, so the optimiser works on their logarithms (scale-free for Adam). The
delay tau lives in [dt, capacity * dt] (one sample up to the delay buffer): the optimiser
works on ``z`` with ``tau = lo + (hi - lo) * sigmoid(z)``.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import checks, fileio
from jaxflex.analysis import stability
from jaxflex.controllers import Controller, DFSParams, by_name, combine
from jaxflex.controllers.fuzzy import FuzzyParams, fuzzy_params

CONTROLLERS = ("dfs", "fuzzy", "dfs+fuzzy")
DELAYS = ("linear", "cubic", "pade")
"""How a tuned DFS reads theta(t - tau): buffer interpolation ("linear", "cubic") or Pade states."""


class TunedController(NamedTuple):
    """What the tuner needs to know about one controller.

    Attributes:
      name: one of CONTROLLERS.
      controller: the jaxflex controller (DFS with a delay read by linear or cubic
        interpolation or a Pade filter, each differentiable in tau).
      to_physical: raw (unconstrained) pytree -> controller parameters.
      to_raw: controller parameters -> raw pytree.
      named: controller parameters -> {"k": .., "tau_s": .., "k1": ..} (Python floats, each
        the shortest decimal that reads back to it in its dtype: `fileio.shortest`).
      from_named: such a dict -> controller parameters (paper values for missing names).
      paper: the paper's parameters.
    """

    name: str
    controller: Controller
    to_physical: Callable[[Any], Any]
    to_raw: Callable[[Any], Any]
    named: Callable[[Any], dict[str, float]]
    from_named: Callable[[dict[str, float]], Any]
    paper: Any


def _logit(p: jax.Array) -> jax.Array:
    return jnp.log(p) - jnp.log1p(-p)


def check_capacity(capacity: int) -> int:
    """A tuned DFS's buffer capacity (samples): in [2, ``stability.MAX_HISTORY``], since tau
    is tuned from one sample to the whole buffer (1 left it no room: a division by zero) and
    the tuner's stability penalty builds the sampled loop over the buffer."""
    return checks.integer("capacity", capacity, 2, unit="samples", high=stability.MAX_HISTORY)


def tau_bounds(dt: float, capacity: int) -> tuple[float, float]:
    """The range tau may take: one sample to the buffer capacity (s)."""
    return float(dt), float(capacity * dt)


def check_tau(tau_s: float, dt: float, capacity: int) -> None:
    lo, hi = tau_bounds(dt, capacity)
    if not (np.isfinite(tau_s) and lo <= tau_s <= hi):
        raise ValueError(f"tau_s must be in [{lo:g}, {hi:g}] s (one sample to the delay buffer's capacity, {capacity} samples: capacity sets it); got {tau_s}")


def _dfs_parts(dt: float, capacity: int, delay: str, pade_order: int):
    lo, hi = tau_bounds(dt, capacity)
    build = functools.partial(by_name, "dfs", dt=dt, capacity=capacity, delay=delay, pade_order=pade_order)
    controller, paper = build()

    def to_physical(raw):
        return DFSParams(jnp.exp(raw["log_k"]), lo + (hi - lo) * jax.nn.sigmoid(raw["tau_z"]))

    def to_raw(p: DFSParams):
        k = float(np.asarray(p.k))
        tau = float(np.asarray(p.tau_s))
        if not (np.isfinite(k) and k > 0):
            raise ValueError(f"k must be finite and > 0 to be tuned on a log scale; got {k}")
        check_tau(tau, dt, capacity)
        frac = np.clip((tau - lo) / (hi - lo), 1e-6, 1 - 1e-6)
        return {"log_k": jnp.log(jnp.asarray(p.k, float)), "tau_z": _logit(jnp.asarray(frac, jnp.asarray(p.k, float).dtype))}

    named = lambda p: {"k": fileio.shortest(p.k), "tau_s": fileio.shortest(p.tau_s)}
    from_named = lambda d: build(params=d)[1]
    return controller, to_physical, to_raw, named, from_named, paper


def _fuzzy_parts(dt: float, temperature: float):
    build = functools.partial(by_name, "fuzzy", dt=dt, temperature=temperature)
    controller, paper = build()

    def to_physical(raw):
        base = fuzzy_params()
        dtype = raw["log_k1"].dtype
        return FuzzyParams(
            jnp.exp(raw["log_k1"]), jnp.exp(raw["log_k2"]), jnp.exp(raw["log_k3"]),
            base.angle_centres.astype(dtype), base.velocity_centres.astype(dtype), base.torque_centres.astype(dtype),
        )

    def to_raw(p: FuzzyParams):
        out = {}
        for name in ("k1", "k2", "k3"):
            v = float(np.asarray(getattr(p, name)))
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0 to be tuned on a log scale; got {v}")
            out[f"log_{name}"] = jnp.log(jnp.asarray(getattr(p, name), float))
        return out

    named = lambda p: {name: fileio.shortest(getattr(p, name)) for name in ("k1", "k2", "k3")}
    from_named = lambda d: build(params=d)[1]
    return controller, to_physical, to_raw, named, from_named, paper


def tuned_controller(name: str, dt: float = 1e-3, capacity: int = 64, delay: str = "linear", pade_order: int = 8, temperature: float = 0.0) -> TunedController:
    """The controller ``name`` (one of CONTROLLERS) with its parameter transforms.

    Args:
      name: one of CONTROLLERS.
      dt: sample time (s).
      capacity: delay-buffer capacity (samples, ``check_capacity``); tau is tuned in [dt, capacity dt].
      delay: how DFS reads the delayed angle (one of DELAYS); all are differentiable in tau.
      pade_order: Pade order with ``delay="pade"``.
      temperature: fuzzy smoothing temperature (0 = the faithful controller).
    """
    if delay not in DELAYS:
        raise ValueError(f"delay must be one of {DELAYS}; got {delay!r}")
    capacity = check_capacity(capacity)
    if name == "dfs":
        return TunedController(name, *_dfs_parts(dt, capacity, delay, pade_order))
    if name == "fuzzy":
        return TunedController(name, *_fuzzy_parts(dt, temperature))
    if name == "dfs+fuzzy":
        d, f = _dfs_parts(dt, capacity, delay, pade_order), _fuzzy_parts(dt, temperature)
        return TunedController(
            name,
            combine(d[0], f[0]),
            lambda raw: (d[1](raw["dfs"]), f[1](raw["fuzzy"])),
            lambda p: {"dfs": d[2](p[0]), "fuzzy": f[2](p[1])},
            lambda p: {**d[3](p[0]), **f[3](p[1])},
            lambda named: (d[4](named), f[4](named)),
            (d[5], f[5]),
        )
    raise ValueError(f"controller must be one of {CONTROLLERS}; got {name!r}")
