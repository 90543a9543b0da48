"""The paper's PD-type fuzzy logic controller: faithful Mamdani inference in pure JAX.

Inputs are the scaled hub angle and hub velocity, ``e = k1 * theta`` and
``e_dot = k2 * theta_dot`` (set-point 0, so the error is the angle itself); the torque is
``u = k3 * F(e, e_dot)``, where ``F`` is the normalised control surface computed here.

**Fuzzy sets.** Each variable (angle, velocity, torque) has ``n_sets`` triangular sets
(the paper: NM NS ZE PS PM, centres -1, -0.5, 0, 0.5, 1). Set ``j`` peaks at its centre
``c_j`` with its feet on the neighbouring centres ``c_{j-1}`` and ``c_{j+1}``; the outer feet
of the outer sets are mirrored (``c_0 - (c_1 - c_0)`` and ``c_{n-1} + (c_{n-1} - c_{n-2})``),
which is scikit-fuzzy's ``trimf(x, [c_{j-1}, c_j, c_{j+1}])``. On the universe
``[c_0, c_{n-1}]`` the memberships are a partition of unity (50 % overlap). Inputs are
clipped to the universe of their variable.

**Inference** (the MATLAB Fuzzy Logic Toolbox and scikit-fuzzy defaults). Rule ``r``,
"IF angle is A_r AND velocity is V_r THEN torque is T_r", fires with strength
``w_r = min(mu_A_r(e), mu_V_r(e_dot))``; implication clips ``T_r`` at ``w_r`` (min);
aggregation takes the pointwise max. Rules sharing a consequent ``j`` therefore act through
``s_j = max_{r: T_r = j} w_r`` (0 if no rule names ``j``), and the aggregated output
membership is ``mu(u) = max_j min(s_j, mu_j(u))``. The rule table is data (``PAPER_RULES``,
name triples); the factory turns it once into static integer index arrays.

**Centroid in closed form.** ``F = int u mu(u) du / int mu(u) du`` over the torque universe,
computed exactly (no sampled universe). On the interval ``[c_j, c_{j+1}]`` of width ``h_j``
only sets ``j`` and ``j+1`` are non-zero; in the local coordinate ``t in [0, 1]``,
``mu = max(g, k)`` with ``g = min(a, 1 - t)``, ``k = min(b, t)``, ``a = s_j``,
``b = s_{j+1}``. Using ``area(max(g, k)) = area(g) + area(k) - area(min(g, k))`` (and the
same for first moments):

* ``g``: area ``a - a^2/2``, first moment ``int t g dt = (1 - (1 - a)^3) / 6``;
* ``k`` is the mirror image of ``g`` with ``b``: area ``b - b^2/2``, moment
  ``area - (1 - (1 - b)^3) / 6``;
* ``min(g, k) = min(cc, t, 1 - t)`` with ``cc = min(a, b, 1/2)``: area ``cc - cc^2``,
  moment ``area / 2`` (symmetric about ``t = 1/2``).

Then ``int mu du = sum_j h_j area_j`` and ``int u mu du = sum_j h_j (c_j area_j + h_j
moment_j)``. Where no rule fires (some corners of the input square) the output is 0; the
division is guarded by a double ``jnp.where`` so that gradients stay finite there.

``defuzz="singleton"`` is the weighted average of output-set centres,
``sum_r w_r c_{T_r} / sum_r w_r`` (0 when no rule fires).

Everything is jit/vmap/grad compatible and differentiable almost everywhere with respect to
``k1, k2, k3`` and the centres (the kinks of min/max and of the triangles are measure-zero).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.controllers.base import Controller, check_finite_scalar

SET_NAMES = ("NM", "NS", "ZE", "PS", "PM")

# Table 1 of the paper: IF angle AND velocity THEN torque.
PAPER_RULES = (
    ("NM", "ZE", "PM"),
    ("NS", "ZE", "PS"),
    ("NS", "PS", "ZE"),
    ("ZE", "NM", "PM"),
    ("ZE", "NS", "PS"),
    ("ZE", "ZE", "ZE"),
    ("ZE", "PS", "NS"),
    ("ZE", "PM", "NM"),
    ("PS", "NS", "ZE"),
    ("PS", "ZE", "NS"),
    ("PM", "ZE", "NM"),
)

_DEFUZZ_METHODS = ("centroid", "singleton")


class FuzzyParams(NamedTuple):
    """Parameters of the PD-type fuzzy controller.

    Attributes:
      k1: shape=() angle scaling, 1/rad: ``e = k1 * theta``.
      k2: shape=() velocity scaling, s/rad: ``e_dot = k2 * theta_dot``.
      k3: shape=() output scaling, N*m: ``u = k3 * F(e, e_dot)``.
      angle_centres: [n_sets] centres of the angle sets (normalised), strictly increasing.
      velocity_centres: [n_sets] centres of the velocity sets (normalised), strictly
        increasing.
      torque_centres: [n_sets] centres of the torque sets (normalised), strictly increasing.
    """

    k1: jax.Array
    k2: jax.Array
    k3: jax.Array
    angle_centres: jax.Array
    velocity_centres: jax.Array
    torque_centres: jax.Array


def fuzzy_params(
    k1: float = 1.02,
    k2: float = 0.30,
    k3: float = 1.0,
    centres: Sequence[float] = (-1.0, -0.5, 0.0, 0.5, 1.0),
    dtype: jax.typing.DTypeLike | None = None,
) -> FuzzyParams:
    """The paper's parameters (by default) as a ``FuzzyParams`` of jnp arrays.

    Args:
      k1: angle scaling, 1/rad.
      k2: velocity scaling, s/rad.
      k3: output scaling, N*m.
      centres: [n_sets] set centres used for all three variables (normalised).
      dtype: floating dtype of every leaf; default: JAX's default float dtype.

    Returns:
      The parameters; ``check`` of the controller validates their values.
    """
    dtype = float if dtype is None else dtype
    c = jnp.asarray(centres, dtype=dtype)
    return FuzzyParams(
        k1=jnp.asarray(k1, dtype=dtype),
        k2=jnp.asarray(k2, dtype=dtype),
        k3=jnp.asarray(k3, dtype=dtype),
        angle_centres=c,
        velocity_centres=c,
        torque_centres=c,
    )


class _RuleIndices(NamedTuple):
    """A rule table as static integer index arrays into the sets, each ``[n_rules]``."""

    angle: np.ndarray
    velocity: np.ndarray
    torque: np.ndarray


def _rule_indices(rules: Sequence[Sequence[str]], set_names: Sequence[str]) -> _RuleIndices:
    """Validates a rule table of name triples and converts it to index arrays.

    Raises:
      ValueError: for bad set names, or naming the index of a rule that is not a triple of
        names from ``set_names``.
    """
    names = tuple(set_names)
    if len(names) < 2 or not all(isinstance(n, str) for n in names):
        raise ValueError(f"set_names must be at least 2 strings; got {set_names!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"set_names must be distinct; got {names!r}")
    if isinstance(rules, str):
        raise ValueError(f"rules must be a sequence of (angle, velocity, torque) triples; got {rules!r}")
    position = {n: i for i, n in enumerate(names)}
    rows = []
    for r, rule in enumerate(rules):
        if isinstance(rule, str) or not isinstance(rule, Sequence) or len(rule) != 3:
            raise ValueError(
                f"rule {r} must be an (angle, velocity, torque) triple of set names; got {rule!r}"
            )
        row = []
        for name in rule:
            if not isinstance(name, str) or name not in position:
                raise ValueError(f"rule {r} names unknown set {name!r}; accepted names: {names}")
            row.append(position[name])
        rows.append(row)
    idx = np.asarray(rows, dtype=np.int32).reshape(len(rows), 3)
    return _RuleIndices(angle=idx[:, 0], velocity=idx[:, 1], torque=idx[:, 2])


def _check_defuzz(defuzz: str) -> None:
    if defuzz not in _DEFUZZ_METHODS:
        raise NotImplementedError(f"defuzz must be one of {_DEFUZZ_METHODS}; got {defuzz!r}")


def memberships(x: jax.typing.ArrayLike, centres: jax.Array) -> jax.Array:
    """Memberships of a scalar in all the triangular sets of one variable.

    Args:
      x: shape=() crisp input (normalised); clipped to ``[centres[0], centres[-1]]``.
      centres: [n_sets] strictly increasing set centres.

    Returns:
      [n_sets] memberships in [0, 1]; on the universe they sum to 1.
    """
    c = centres
    x = jnp.clip(x, c[0], c[-1])
    left = jnp.concatenate([2 * c[:1] - c[1:2], c[:-1]])  # [n_sets] left feet
    right = jnp.concatenate([c[1:], 2 * c[-1:] - c[-2:-1]])  # [n_sets] right feet
    rise = (x - left) / (c - left)
    fall = (right - x) / (right - c)
    return jnp.maximum(jnp.minimum(rise, fall), 0)


def _safe_ratio(num: jax.Array, den: jax.Array) -> jax.Array:
    """``num / den`` where ``den > 0``, else 0; NaN-free gradients (double where)."""
    fires = den > 0
    safe_den = jnp.where(fires, den, jnp.ones_like(den))
    return jnp.where(fires, num / safe_den, jnp.zeros_like(num))


def _centroid(s: jax.Array, c: jax.Array) -> jax.Array:
    """Exact centroid of ``max_j min(s_j, mu_j(u))`` over ``[c_0, c_{n-1}]`` (0 if empty).

    Args:
      s: [n_sets] clip level of each output set, in [0, 1].
      c: [n_sets] strictly increasing output-set centres.

    Returns:
      shape=() the centroid.
    """
    a, b = s[:-1], s[1:]  # [n_sets - 1] levels of the falling and the rising set
    h = c[1:] - c[:-1]  # [n_sets - 1] interval widths
    area_g = a - a * a / 2
    moment_g = (1 - (1 - a) ** 3) / 6
    area_k = b - b * b / 2
    moment_k = area_k - (1 - (1 - b) ** 3) / 6
    cc = jnp.minimum(jnp.minimum(a, b), 0.5)
    area_m = cc - cc * cc
    area = area_g + area_k - area_m  # [n_sets - 1] in local units
    moment = moment_g + moment_k - area_m / 2
    den = jnp.sum(h * area)
    num = jnp.sum(h * (c[:-1] * area + h * moment))
    return _safe_ratio(num, den)


def _surface(
    params: FuzzyParams, e: jax.typing.ArrayLike, e_dot: jax.typing.ArrayLike, idx: _RuleIndices, defuzz: str
) -> jax.Array:
    """The normalised control surface with a validated rule table (see ``fuzzy_surface``)."""
    if jnp.ndim(e) != 0 or jnp.ndim(e_dot) != 0:
        raise ValueError(f"e and e_dot must be scalars (vmap for grids); got shapes {jnp.shape(e)}, {jnp.shape(e_dot)}")
    dtype = jnp.result_type(params.angle_centres, params.velocity_centres, params.torque_centres, e, e_dot)
    mu_angle = memberships(jnp.asarray(e, dtype), params.angle_centres.astype(dtype))  # [n_sets]
    mu_vel = memberships(jnp.asarray(e_dot, dtype), params.velocity_centres.astype(dtype))  # [n_sets]
    c_out = params.torque_centres.astype(dtype)  # [n_sets]
    w = jnp.minimum(mu_angle[idx.angle], mu_vel[idx.velocity])  # [n_rules] firing strengths
    if defuzz == "centroid":
        s = jnp.zeros(c_out.shape, dtype).at[idx.torque].max(w)  # [n_sets] clip levels
        return _centroid(s, c_out)
    if defuzz == "singleton":
        return _safe_ratio(jnp.sum(w * c_out[idx.torque]), jnp.sum(w))
    raise NotImplementedError(f"defuzz must be one of {_DEFUZZ_METHODS}; got {defuzz!r}")


def fuzzy_surface(
    params: FuzzyParams,
    e: jax.typing.ArrayLike,
    e_dot: jax.typing.ArrayLike,
    *,
    rules: Sequence[Sequence[str]] = PAPER_RULES,
    defuzz: str = "centroid",
    set_names: Sequence[str] = SET_NAMES,
) -> jax.Array:
    """The normalised output ``F(e, e_dot)`` of the Mamdani system (``k1..k3`` unused).

    Args:
      params: centres of the sets (``k1``, ``k2``, ``k3`` are not used here).
      e: shape=() normalised angle error; clipped to the angle universe.
      e_dot: shape=() normalised velocity; clipped to the velocity universe.
      rules: (angle, velocity, torque) triples of names from ``set_names``.
      defuzz: ``"centroid"`` (exact, closed form) or ``"singleton"``.
      set_names: the names of the sets, in the order of the centres.

    Returns:
      shape=() normalised torque in the torque universe; 0 where no rule fires. Its dtype is
      the result type of the centres and the inputs.

    Raises:
      ValueError: for a malformed rule table or non-scalar inputs.
      NotImplementedError: for an unknown ``defuzz``.
    """
    _check_defuzz(defuzz)
    return _surface(params, e, e_dot, _rule_indices(rules, set_names), defuzz)


def fuzzy(
    *,
    rules: Sequence[Sequence[str]] = PAPER_RULES,
    set_names: Sequence[str] = SET_NAMES,
    defuzz: str = "centroid",
) -> Controller:
    """The PD-type fuzzy controller ``u = k3 * F(k1 * theta, k2 * theta_dot)``.

    The measurement is ``y = [theta (rad), theta_dot (rad/s)]`` and the torque ``u`` has
    shape ``(1,)`` (N*m). The controller is stateless: ``init`` returns ``()``.

    Args:
      rules: (angle, velocity, torque) triples of names from ``set_names``; the paper's
        Table 1 by default.
      set_names: the names of the sets, in the order of the centres in ``FuzzyParams``.
      defuzz: ``"centroid"`` (exact, closed form) or ``"singleton"``.

    Returns:
      The controller; its parameters are a ``FuzzyParams``.

    Raises:
      ValueError: naming the rule index, the unknown name and the accepted names.
      NotImplementedError: for an unknown ``defuzz``.
    """
    _check_defuzz(defuzz)
    idx = _rule_indices(rules, set_names)
    n_sets = len(tuple(set_names))

    def init(params: FuzzyParams, y0: jax.Array) -> tuple[()]:
        del params, y0
        return ()

    def step(params: FuzzyParams, state: tuple[()], y: jax.Array) -> tuple[tuple[()], jax.Array]:
        if jnp.shape(y) != (2,):
            raise ValueError(f"y must have shape (2,) (theta, theta_dot); got {jnp.shape(y)}")
        e = params.k1 * y[0]
        e_dot = params.k2 * y[1]
        u = params.k3 * _surface(params, e, e_dot, idx, defuzz)
        return state, jnp.reshape(u, (1,))

    def check(params: FuzzyParams) -> None:
        check_finite_scalar("k1", params.k1, positive=True)
        check_finite_scalar("k2", params.k2, positive=True)
        check_finite_scalar("k3", params.k3)
        for name in ("angle_centres", "velocity_centres", "torque_centres"):
            c = np.asarray(getattr(params, name))
            accepted = f"{name} must have shape ({n_sets},), be finite and strictly increasing"
            if c.shape != (n_sets,):
                raise ValueError(f"{accepted}; got shape {c.shape}")
            if not np.all(np.isfinite(c)):
                raise ValueError(f"{accepted}; got {c.tolist()}")
            if not np.all(np.diff(c) > 0):
                raise ValueError(f"{accepted}; got {c.tolist()}")

    return Controller(init, step, check)
