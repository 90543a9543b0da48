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
At a kink JAX splits each ``min``/``max`` tie half and half, and an input exactly on a set
centre ties several at once, so there the gradient is neither one-sided derivative, even
where the two agree: at the origin the surface's slope is -1.5 in each input from either
side, but reverse mode returns -0.375. A run starting at rest (``theta = theta_dot = 0``, as
the paper scenario does) has its first sample there; the gradients in ``k1`` and ``k2`` do
not see it (they multiply a zero input), nor do those in ``k3`` and the torque centres; the
two zero centres do: over 40 ms of the paper scenario, reverse mode gives a quarter of the
derivative of the tip ISE in ``angle_centres[2]`` and 6 % less than it in
``velocity_centres[2]`` (tested; moved off the tie, 0.01 away, both are exact). The tuner
tunes ``k1``-``k3`` only. A smooth controller (``T > 0``) has no kinks.

**Smooth mode** (``temperature=T > 0`` in ``fuzzy``, ``fuzzy_surface``, ``memberships``). One
code path: each non-smooth operation is a primitive that branches once, at trace time, on the
Python float ``T``; at ``T == 0`` it is the exact operation, so ``T = 0`` is the faithful
controller, the very same program. ``T`` is in normalised units: membership degrees for the
triangles, AND, aggregation and centroid; the normalised input for the clip to the universe.
With ``softplus_T(x) = T log(1 + exp(x / T))``:

* triangles: ``min(rise, fall)`` by the Boltzmann min ``sum_i x_i softmax(-x / T)_i``, then
  the clip to [0, 1] by ``softplus_T(y) - softplus_T(y - 1)``; the input clip by
  ``c_0 + softplus_T(x - c_0) - softplus_T(x - c_{n-1})``. Memberships lie in (0, 1).
* rule AND: ``a b / M_T(a, b)``, ``M_T`` the Boltzmann max: in ``[min, max]``, within
  ``0.28 T`` of the min like the Boltzmann min, but also at most twice the min and 0 when an
  antecedent is 0 (else rules that should not fire get O(T) strengths, which the centroid, a
  ratio, turns into O(1) errors where little else fires).
* aggregation over rules sharing a consequent: the Boltzmann max.
* centroid: the same closed form, ``min(a, b, 1/2)`` becoming ``cap_T(AND_T(a, b))`` with
  ``cap_T(m) = m - softplus_T(m - 1/2) + softplus_T(-1/2)``: 0 at 0 and at most ``max(a, b)``,
  so each interval's density ``g + k - min(cc, t, 1 - t)`` stays >= 0 and the output stays in
  the universe (lifting 0 gives negative areas, unbounded outputs for rule tables that leave
  consequents unnamed).
* no-rule default: ``T^2`` is added to the denominator (a mass at ``u = 0``), so the output
  tends to 0 where the faithful controller fires nothing (smooth strengths are positive there,
  ``~T exp(-d / T)``); elsewhere a relative ``T^2 / area``. The double-``where`` guard stays.

The surface is C-infinity in ``e, e_dot`` and every leaf of ``FuzzyParams``, odd, with finite
gradients everywhere (underflow included). Each primitive is uniformly within O(T) of the exact
one; the centroid divides by the area under the output membership, so the error is about
``T / area``. On a 101 x 101 grid of the square (paper's parameters) max ``|F_T - F|`` is
1.15-1.5 ``T`` where a rule fires with >= 0.1 and ``|e|, |e_dot| <= 0.9`` (2.5-5.2 ``T`` for
the singleton average, whose denominator is a sum of strengths), and over the grid
0.575, 0.484, 0.291, 0.116, 0.043 for ``T`` = 0.1, 0.03, 0.01, 0.003, 0.001 (-> ~``45 T``,
next to the jumps below, where only 0.04 fires). Two limits:

* the faithful surface jumps (by 0.5-0.75) where the rules stop firing: the edges of the
  no-rule corners ``[0.5, 1]^2``, ``[-1, -0.5]^2`` and isolated points such as ``(-0.5, 1)``.
  No continuous surface converges there; the smooth one keeps the firing side's values about
  ``T log(1 / T) / 2`` into the no-rule side, then falls to 0.
* for ``|e|, |e_dot|`` below about ``T`` the smooth slope is about half the faithful one (two
  rules tie for each of NS and PS, and a smooth max of tied arguments moves at half speed):
  ``F(a, 0) / a`` is -1.50 faithful; at ``T = 0.02`` -0.72 for ``a <= 0.001``, -0.80 at 0.01, -1.09 at 0.03.

Sensible ``T``: 0.01-0.05 when ``e, e_dot`` reach O(0.1-1) (max error 0.012-0.076 where rules
fire well, curvature O(1 / T)); keep ``T`` well below the amplitudes the loss depends on.
Accepted: 0 or ``T`` in ``[MIN_TEMPERATURE, MAX_TEMPERATURE] = [1e-5, 1]`` (see there why):
over that range surface and gradients are finite in float32 and float64, and at 1e-5 the
float32 surface is still within 1.16 ``T`` of the faithful one where rules fire.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import checks
from jaxflex.controllers.base import Controller, check_params_type, check_scalar_param, is_concrete

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

    Raises:
      ValueError: naming a concrete argument that is not a real number (or, for
        ``centres``, a 1-D, finite, strictly increasing array of at least 2), or one beyond
        the range of ``dtype``.
    """
    dtype = checks.float_dtype("dtype", dtype)
    biggest = float(jnp.finfo(dtype).max)
    for name, value in (("k1", k1), ("k2", k2), ("k3", k3), ("centres", centres)):
        if is_concrete(value):  # traced values (jit, grad, vmap) are checked where they are used
            arr = checks.real_array(name, value, scalar=name != "centres").astype(float)
            if np.any(np.isfinite(arr) & (np.abs(arr) > biggest)):  # cast, they would become infinite
                raise ValueError(f"{name} must lie in [-{biggest:.4g}, {biggest:.4g}] to be held in {dtype.name} "
                                 f"(dtype=jnp.float64 with jax_enable_x64); got {value!r}")
    c = jnp.asarray(centres, dtype=dtype)
    _check_set_centres(c)
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
    if isinstance(set_names, str) or not isinstance(set_names, Iterable):
        raise ValueError(f"set_names must be a sequence of at least 2 strings; got {set_names!r}")
    names = tuple(set_names)
    if len(names) < 2 or not all(isinstance(n, str) for n in names):
        raise ValueError(f"set_names must be at least 2 strings; got {set_names!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"set_names must be distinct; got {names!r}")
    if isinstance(rules, str) or not isinstance(rules, Sequence):
        raise ValueError(f"rules must be a sequence of (angle, velocity, torque) triples; got {rules!r}")
    if len(rules) == 0:
        raise ValueError("rules must hold at least one (angle, velocity, torque) triple (with none the torque is always 0: the open loop)")
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


def _check_centre_array(name: str, centres: jax.typing.ArrayLike, n_sets: int, build: str = "") -> None:
    """Refuse, by name, set centres that are not ``[n_sets]``, finite and strictly increasing
    (concrete values only: traced ones pass). A tuple or list is refused: in a parameter
    pytree each of its numbers would be a leaf of its own, which the surface does not read.
    ``build`` adds to that message how else to get an array."""
    if isinstance(centres, (tuple, list)):
        raise ValueError(f"{name} must be an array (jnp.asarray(...){build}); got {type(centres).__name__} {centres!r}")
    if not is_concrete(centres):
        return
    c = checks.real_array(name, centres)
    accepted = f"{name} must have shape ({n_sets},), be finite and strictly increasing"
    if c.shape != (n_sets,):
        raise ValueError(f"{accepted}; got shape {c.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.diff(c) > 0)):
        raise ValueError(f"{accepted}; got {c.tolist()}")


def _check_set_centres(centres: jax.typing.ArrayLike) -> None:
    """Refuse ``centres`` that are not a 1-D, finite, strictly increasing array of at least 2
    (any number of sets: a controller checks its own count)."""
    shape = jnp.shape(centres)
    if len(shape) != 1 or shape[0] < 2:
        raise ValueError(f"centres must be a 1-D array of at least 2 set centres; got shape {shape}")
    _check_centre_array("centres", centres, shape[0])


def _check_centres(params: FuzzyParams, n_sets: int) -> None:
    for name in ("angle_centres", "velocity_centres", "torque_centres"):
        _check_centre_array(name, getattr(params, name), n_sets, ", or build the parameters with fuzzy_params(centres=...)")


def check_defuzz(defuzz: str) -> None:
    """Refuse, by name, a ``defuzz`` that is not one of the defuzzifiers."""
    if defuzz not in _DEFUZZ_METHODS:
        raise ValueError(f"defuzz must be one of {_DEFUZZ_METHODS}; got {defuzz!r}")


MIN_TEMPERATURE = 1e-5
"""The smallest smooth temperature. Below it float32 round-off of the surface (~1e-7) is no
longer small against ``T``: at ``T = 1e-8`` the float32 surface is 17 ``T`` from the faithful
one where rules fire (1.15 ``T`` in float64), and below ~1e-38 ``T`` itself is 0 in float32
(NaN gradients, a wrong torque). At 1e-5 both dtypes are within 1.16 ``T`` there (tested),
with gradients ~2 / ``T``; use ``T = 0``, the faithful controller, for less smoothing."""

MAX_TEMPERATURE = 1.0
"""The largest smooth temperature. ``T`` is in membership degrees, whose whole range is
[0, 1]: at ``T = 1`` the smoothing error (0.64 centroid, 0.81 singleton, where rules fire) is
already the surface's own size (max ``|F|`` 0.67, 0.9), and above it the surface only shrinks
towards 0 (and ``T^2`` overflows a Python float from ~1.3e154)."""


def check_temperature(temperature: float, name: str = "temperature") -> float:
    """Validates a (static) temperature; returns it as a Python float.

    Args:
      temperature: 0 (the faithful controller) or a real in ``[MIN_TEMPERATURE,
        MAX_TEMPERATURE]`` (NumPy scalars and ints are accepted).
      name: how the message names it (``fuzzy_temperature`` in configurations).

    Raises:
      ValueError: naming ``name`` and the accepted values otherwise.
    """
    accepted = f"{name} must be 0 (the faithful controller) or a Python float in [{MIN_TEMPERATURE:g}, {MAX_TEMPERATURE:g}] (the smooth mode)"
    if isinstance(temperature, bool) or not isinstance(temperature, numbers.Real):
        raise ValueError(f"{accepted}; got {temperature!r}")
    t = float(temperature)
    if not (t == 0 or MIN_TEMPERATURE <= t <= MAX_TEMPERATURE):
        raise ValueError(f"{accepted}; got {temperature!r}")
    return t


def _select_op(exact, takes_b):
    """``exact`` (``jnp.minimum`` or ``jnp.maximum``) computed as one compare and one select.

    XLA lowers ``jnp.minimum`` and ``jnp.maximum`` to IEEE 754-2019 ``minimum``/``maximum``
    (a NaN in either argument wins, -0 < +0), which x86 has no instruction for: LLVM expands
    each into a min, compares and blends. ``where(b < a, b, a)`` is one ``vminps``. The two
    agree except that a NaN in ``b`` is dropped and a zero result may carry the other sign;
    ``_surface`` puts NaN back where one could arise. The derivative is ``exact``'s (a tie
    splits half and half), so values and derivatives are ``exact``'s, up to those two cases
    and the rounding of XLA's fusion of the compiled program.
    """

    @jax.custom_jvp
    def op(a: jax.Array, b: jax.typing.ArrayLike) -> jax.Array:
        return jnp.where(takes_b(a, b), b, a)

    @op.defjvp
    def op_jvp(primals, tangents):
        return op(*primals), jax.jvp(exact, primals, tangents)[1]

    return op


_select_min = _select_op(jnp.minimum, lambda a, b: b < a)
_select_max = _select_op(jnp.maximum, lambda a, b: b > a)


# -- Smooth primitives. Each is the exact operation at temperature 0 (branch taken once, at
# -- trace time, on the Python float) and a C-infinity one with an O(temperature) error bound,
# -- uniform in its arguments, for temperature > 0.


def _softplus(x: jax.Array, temperature: float) -> jax.Array:
    """The smooth ``max(x, 0)`` for ``T > 0``: ``T * log(1 + exp(x / T))`` (stable form),
    with ``max(x, 0) < softplus <= max(x, 0) + T log 2``, the gap largest at the kink."""
    return temperature * jnp.logaddexp(x / temperature, 0.0)


def _clip(x: jax.Array, lo: jax.typing.ArrayLike, hi: jax.typing.ArrayLike, temperature: float) -> jax.Array:
    """``clip(x, lo, hi)``; ``lo + softplus(x - lo) - softplus(x - hi)`` for ``T > 0``.

    Smooth: strictly inside ``(lo, hi)`` (the softplus has slope in (0, 1)), within
    ``T log 2`` of the exact clip (the gap largest at the kinks ``lo`` and ``hi``).
    """
    if temperature == 0:
        return _select_min(_select_max(x, lo), hi)
    return lo + _softplus(x - lo, temperature) - _softplus(x - hi, temperature)


def _min(a: jax.Array, b: jax.Array, temperature: float) -> jax.Array:
    """``min(a, b)`` of any signs; the Boltzmann operator ``sum_i x_i softmax(-x / T)_i`` for
    ``T > 0``.

    Smooth: a weighted mean, so within ``[min(a, b), max(a, b)]``; exact at ties; at most
    ``max_d d sigmoid(-d / T) < 0.28 T`` above the min, exponentially close once
    ``|a - b| >> T``; bounded gradient. (LogSumExp, ``-T log(exp(-a/T) + exp(-b/T))``, leaves
    ``[min, max]`` by up to ``T log 2``; mellowmax stays inside but is ``T log 2`` off away from
    ties, where the Boltzmann operator is exponentially close.)
    """
    if temperature == 0:
        return _select_min(a, b)
    return b + (a - b) * jax.nn.sigmoid((b - a) / temperature)


def _min_levels(a: jax.Array, b: jax.Array, temperature: float) -> jax.Array:
    """``min(a, b)`` of levels ``a, b >= 0``; for ``T > 0`` ``a b / M`` with ``M`` the Boltzmann
    max of ``a, b`` (exact for the exact max, since ``min * max = a b``).

    Smooth; within ``[min(a, b), max(a, b)]``, at most ``0.28 T`` above the min and exact at
    ties, like the Boltzmann min; but also relative: at most ``2 min(a, b)`` (``M >= max / 2``),
    and ``min(0, b) = 0``, so a rule with a zero antecedent does not fire. (The Boltzmann min
    of ``(0, b)`` is ``b sigmoid(-b / T)``, up to ``0.28 T``; the centroid, a ratio, turns
    such O(T) strengths of rules that should not fire into O(1) errors where little else
    fires.) Bounded gradient; a double ``where`` guards ``m -> 0`` (reached by underflow).
    """
    if temperature == 0:
        return _select_min(a, b)
    m = b + (a - b) * jax.nn.sigmoid((a - b) / temperature)  # Boltzmann max, >= max(a, b) / 2
    # The derivative of b / m holds b / m^2: below sqrt(tiny) m^2 underflows to 0 (NaN
    # gradient). There the (negligible) exact min takes over, a jump of less than sqrt(tiny).
    normal = m > math.sqrt(jnp.finfo(m.dtype).tiny)
    safe_m = jnp.where(normal, m, jnp.ones_like(m))
    return jnp.where(normal, a * (b / safe_m), jnp.minimum(a, b))


def _cap(x: jax.Array, hi: float, temperature: float) -> jax.Array:
    """``min(x, hi)`` for ``x >= 0`` and ``hi > 0``; for ``T > 0`` a softplus form that keeps 0
    fixed, ``x - (softplus(x - hi) - softplus(-hi))``: increasing, in ``[0, x]``, within
    ``T log 2`` of the exact cap."""
    if temperature == 0:
        return _select_min(x, hi)
    return x - (_softplus(x - hi, temperature) - temperature * math.log1p(math.exp(-hi / temperature)))


def _group_max(w: Sequence[jax.Array], groups: np.ndarray, n_groups: int, temperature: float) -> list[jax.Array]:
    """``s_j = max_{r: groups[r] = j} w_r``, 0 for an empty group, for ``w >= 0``.

    For ``T > 0`` the Boltzmann operator ``sum_r w_r softmax(w / T)_r`` over each group:
    within the group's [min, max], at most ``(n - 1) T / e`` below its max.

    The rule table is static, so each group is a fixed chain of operations on scalars (no
    gather or scatter: under ``vmap`` every value is one contiguous batch array).

    Args:
      w: n_rules non-negative values, each shape ().
      groups: [n_rules] static group of each value, in ``[0, n_groups)``.
      n_groups: number of groups.
      temperature: see ``fuzzy``.

    Returns:
      n_groups (smooth) group maxima, each shape ().
    """
    out = []
    for j in range(n_groups):
        members = [w_r for w_r, g in zip(w, np.asarray(groups).tolist()) if g == j]
        if not members:
            out.append(jnp.zeros_like(w[0]))
            continue
        top = members[0]
        for w_r in members[1:]:
            top = _select_max(top, w_r)
        if temperature == 0 or len(members) == 1:
            out.append(top)
            continue
        top = jax.lax.stop_gradient(top)  # the softmax shift (as jax.nn.softmax)
        weights = [jnp.exp((w_r - top) / temperature) for w_r in members]
        num, den = members[0] * weights[0], weights[0]
        for w_r, e_r in zip(members[1:], weights[1:]):
            num, den = num + w_r * e_r, den + e_r
        out.append(num / den)
    return out


def _no_fire_mass(temperature: float) -> float:
    """``T^2``: the mass of a default output at ``u = 0``, added to the denominator of the
    centroid (an area, normalised torque units) or of the singleton average (a strength)
    for ``T > 0``, so that the output tends to 0 where the faithful controller fires nothing
    (see the module docstring)."""
    return temperature**2


def memberships(x: jax.typing.ArrayLike, centres: jax.Array, *, temperature: float = 0.0) -> jax.Array:
    """Memberships of a crisp input in all the triangular sets of one variable.

    Args:
      x: crisp input (normalised), a scalar or an array of them; clipped to
        ``[centres[0], centres[-1]]``.
      centres: [n_sets] strictly increasing set centres.
      temperature: 0 for the exact triangles; ``T > 0`` for the smooth ones (see ``fuzzy``).

    Returns:
      [n_sets, *x.shape] memberships in [0, 1] (in (0, 1) for ``T > 0``); for ``T = 0`` on the universe
      they sum to 1 (for ``T > 0`` to within O(T)).

    Raises:
      ValueError: for centres that are not a 1-D, finite, strictly increasing array of at
        least 2, or a ``temperature`` out of its range (``check_temperature``).
    """
    t = check_temperature(temperature)
    _check_set_centres(centres)
    return jnp.stack(_membership_list(x, centres, t))


def _membership_list(x: jax.typing.ArrayLike, c: jax.Array, t: float) -> list[jax.Array]:
    """``memberships`` as a list of n_sets scalars (see there): one fixed chain of scalar
    operations per set, so that under ``vmap`` each membership is one contiguous batch array."""
    n = c.shape[0]
    x = _clip(x, c[0], c[-1], t)
    # How far x is across each interval [c_j, c_{j+1}]: the rising edge of set j + 1 and one
    # minus the falling edge of set j (one division per interval rather than two per set).
    frac = [(x - c[j]) / (c[j + 1] - c[j]) for j in range(n - 1)]
    out = []
    for j in range(n):
        # The outer feet are mirrored: set 0 rises from c_0 - (c_1 - c_0), set n - 1 falls to
        # c_{n-1} + (c_{n-1} - c_{n-2}).
        rise = 1 + frac[0] if j == 0 else frac[j - 1]
        fall = 2 - frac[n - 2] if j == n - 1 else 1 - frac[j]
        peak = _min(rise, fall, t)  # <= 1 at T = 0; the smooth min may pass 1 by O(T)
        # T = 0: the faithful triangle (its upper clip is inactive).
        out.append(_select_max(peak, jnp.zeros_like(peak)) if t == 0 else _clip(peak, 0.0, 1.0, t))
    return out


def _safe_ratio(num: jax.Array, den: jax.Array) -> jax.Array:
    """``num / den`` where ``den != 0`` (it is >= 0: where a rule fires), else 0; NaN-free
    gradients (double where). A NaN ``den`` (a NaN measurement) gives NaN, not 0: the run
    then reports itself diverged instead of running open loop."""
    fires = den != 0
    safe_den = jnp.where(fires, den, jnp.ones_like(den))
    return jnp.where(fires, num / safe_den, jnp.zeros_like(num))


def _centroid(s: jax.Array, c: jax.Array, temperature: float = 0.0) -> jax.Array:
    """Exact centroid of ``max_j min(s_j, mu_j(u))`` over ``[c_0, c_{n-1}]`` (0 if empty).

    Args:
      s: n_sets clip levels of the output sets, in [0, 1] (an array [n_sets] or a sequence of
        scalars).
      c: [n_sets] strictly increasing output-set centres.
      temperature: 0 for the exact centroid; ``T > 0`` smooths ``min(a, b, 1/2)`` and adds
        the no-fire mass to the denominator (see the module docstring).

    Returns:
      shape=() the centroid.
    """
    den = num = None
    for j in range(len(s) - 1):  # interval [c_j, c_{j+1}], summed left to right
        a, b = s[j], s[j + 1]  # levels of the falling and the rising set
        h = c[j + 1] - c[j]  # interval width
        area_g = a - a * a / 2
        moment_g = (1 - (1 - a) ** 3) / 6
        area_k = b - b * b / 2
        moment_k = area_k - (1 - (1 - b) ** 3) / 6
        cc = _cap(_min_levels(a, b, temperature), 0.5, temperature)  # in [0, max(a, b)]: density >= 0
        area_m = cc - cc * cc
        area = area_g + area_k - area_m  # in local units
        moment = moment_g + moment_k - area_m / 2
        den_j, num_j = h * area, h * (c[j] * area + h * moment)
        den, num = (den_j, num_j) if den is None else (den + den_j, num + num_j)
    if temperature > 0:
        den = den + _no_fire_mass(temperature)
    return _safe_ratio(num, den)


def _surface(
    params: FuzzyParams,
    e: jax.typing.ArrayLike,
    e_dot: jax.typing.ArrayLike,
    idx: _RuleIndices,
    defuzz: str,
    temperature: float,
) -> jax.Array:
    """The normalised control surface with validated arguments (see ``fuzzy_surface``)."""
    if jnp.ndim(e) != 0 or jnp.ndim(e_dot) != 0:
        raise ValueError(f"e and e_dot must be scalars (vmap for grids); got shapes {jnp.shape(e)}, {jnp.shape(e_dot)}")
    t = temperature
    dtype = jnp.result_type(params.angle_centres, params.velocity_centres, params.torque_centres, e, e_dot)
    # Scalars throughout, indexed by the static rule table: fixed arithmetic, no gathers,
    # scatters or reductions (benchmarks/README.md: 11x faster closed loop under vmap on CPU
    # than with gathers and scatters, in the same rollout).
    mu_angle = _membership_list(jnp.asarray(e, dtype), params.angle_centres.astype(dtype), t)  # n_sets
    mu_vel = _membership_list(jnp.asarray(e_dot, dtype), params.velocity_centres.astype(dtype), t)  # n_sets
    c_out = params.torque_centres.astype(dtype)  # [n_sets]
    w = [_min_levels(mu_angle[i], mu_vel[j], t) for i, j in zip(idx.angle.tolist(), idx.velocity.tolist())]  # firing strengths
    if defuzz == "centroid":
        s = _group_max(w, idx.torque, c_out.shape[0], t)  # n_sets clip levels
        out = _centroid(s, c_out, t)
    else:  # "singleton" (the callers validate defuzz)
        den, num = None, None
        for w_r, k in zip(w, idx.torque.tolist()):
            den, num = (w_r, w_r * c_out[k]) if den is None else (den + w_r, num + w_r * c_out[k])
        if t > 0:
            den = den + _no_fire_mass(t)
        out = _safe_ratio(num, den)
    # The select min and max drop a NaN in one argument (_select_op), so NaN is put back here
    # where one could arise: a NaN input (a NaN measurement must give a NaN torque, and the
    # run report itself diverged) or centres that check() refuses, which reach here traced
    # (not finite, or not strictly increasing: inf - inf or 0 / 0 in the memberships). The
    # centres' test is shared by a batch: scalars under vmap unless the centres are batched.
    centres_ok = None
    for c in (params.angle_centres.astype(dtype), params.velocity_centres.astype(dtype), c_out):
        ok = jnp.isfinite(c[0]) & jnp.isfinite(c[-1])
        for j in range(c.shape[0] - 1):
            ok = ok & (c[j] < c[j + 1])
        centres_ok = ok if centres_ok is None else centres_ok & ok
    return jnp.where(jnp.isnan(e) | jnp.isnan(e_dot) | ~centres_ok, jnp.nan, out)


def fuzzy_surface(
    params: FuzzyParams,
    e: jax.typing.ArrayLike,
    e_dot: jax.typing.ArrayLike,
    *,
    rules: Sequence[Sequence[str]] = PAPER_RULES,
    defuzz: str = "centroid",
    set_names: Sequence[str] = SET_NAMES,
    temperature: float = 0.0,
) -> jax.Array:
    """The normalised output ``F(e, e_dot)`` of the Mamdani system (``k1..k3`` unused).

    Args:
      params: centres of the sets (``k1``, ``k2``, ``k3`` are not used here).
      e: shape=() normalised angle error; clipped to the angle universe.
      e_dot: shape=() normalised velocity; clipped to the velocity universe.
      rules: (angle, velocity, torque) triples of names from ``set_names``.
      defuzz: ``"centroid"`` (exact, closed form) or ``"singleton"``.
      set_names: the names of the sets, in the order of the centres.
      temperature: 0 (default) for the faithful controller; ``T > 0`` for the smooth mode
        (see ``fuzzy``).

    Returns:
      shape=() normalised torque in the torque universe; 0 where no rule fires (for
      ``T > 0``: shrunk towards 0 where little fires). Its dtype is the result type of the
      centres and the inputs.

    Raises:
      ValueError: for a malformed rule table, centres that are not an array or not strictly
        increasing, inputs that are not real numbers or not scalars, a ``temperature`` out of its range (``check_temperature``), or an
        unknown ``defuzz``.
    """
    check_defuzz(defuzz)
    t = check_temperature(temperature)
    idx = _rule_indices(rules, set_names)
    check_params_type(params, FuzzyParams)
    for name, value in (("e", e), ("e_dot", e_dot)):
        if is_concrete(value):
            checks.real_array(name, value, scalar=True)
    _check_centres(params, len(tuple(set_names)))
    return _surface(params, e, e_dot, idx, defuzz, t)


def fuzzy(
    *,
    rules: Sequence[Sequence[str]] = PAPER_RULES,
    set_names: Sequence[str] = SET_NAMES,
    defuzz: str = "centroid",
    temperature: float = 0.0,
) -> Controller:
    """The PD-type fuzzy controller ``u = k3 * F(k1 * theta, k2 * theta_dot)``.

    The measurement is ``y = [theta (rad), theta_dot (rad/s)]`` and the torque ``u`` has
    shape ``(1,)`` (N*m). The controller is stateless: ``init`` returns ``()``.

    Args:
      rules: (angle, velocity, torque) triples of names from ``set_names``; the paper's
        Table 1 by default.
      set_names: the names of the sets, in the order of the centres in ``FuzzyParams``.
      defuzz: ``"centroid"`` (exact, closed form) or ``"singleton"``.
      temperature: a static Python float, 0 or in ``[MIN_TEMPERATURE, MAX_TEMPERATURE]`` =
        ``[1e-5, 1]``, in normalised units (membership degrees;
        the normalised input for the clip to the universe). 0 (default): the faithful
        Mamdani controller, the same program as without the argument. ``T > 0``: the smooth
        mode of the module docstring, C-infinity in ``y`` and in every leaf of
        ``FuzzyParams``, within about ``T / area`` of the faithful surface where rules fire.
        For gradient-based tuning 0.01-0.05, when ``e, e_dot`` reach O(0.1-1) (with the
        paper's centres a kink is smoothed over ~``T`` of input; for amplitudes below ~``T``
        the small-signal gain is about half the faithful one); above ~0.1 the triangles
        lose their shape.

    Returns:
      The controller; its parameters are a ``FuzzyParams``.

    Raises:
      ValueError: naming the rule index, the unknown name and the accepted names; naming
        ``temperature`` and its range (0 or in ``[1e-5, 1]``); or for an unknown ``defuzz``.
    """
    check_defuzz(defuzz)
    temperature = check_temperature(temperature)
    idx = _rule_indices(rules, set_names)
    n_sets = len(tuple(set_names))

    # Reverse mode recomputes the surface from (e, e_dot) rather than storing its ~140
    # intermediates per sample: less memory, and 3x faster closed-loop gradients on CPU
    # (benchmarks/README.md). Values and gradients are unchanged.
    surface = jax.checkpoint(lambda params, e, e_dot: _surface(params, e, e_dot, idx, defuzz, temperature))

    def init(params: FuzzyParams, y0: jax.Array) -> tuple[()]:
        del params, y0
        return ()

    def step(params: FuzzyParams, state: tuple[()], y: jax.Array) -> tuple[tuple[()], jax.Array]:
        if jnp.ndim(y) not in (1, 2) or jnp.shape(y)[0] != 2:
            raise ValueError(f"y must have shape (2,) (theta, theta_dot), or (2, B) for a batch; got {jnp.shape(y)}")
        e = params.k1 * y[0]
        e_dot = params.k2 * y[1]
        # The surface is elementwise: vmap over a batch maps each of its operations onto the
        # batch array, with no change to the arithmetic.
        each = surface if jnp.ndim(e) == 0 else jax.vmap(surface, in_axes=(None, 0, 0))
        u = params.k3 * each(params, e, e_dot)
        return state, u[None]

    def check(params: FuzzyParams) -> None:
        check_params_type(params, FuzzyParams)
        check_scalar_param("k1", params.k1, positive=True)
        check_scalar_param("k2", params.k2, positive=True)
        check_scalar_param("k3", params.k3)
        _check_centres(params, n_sets)

    return Controller(init, step, check, batched=True)
