"""The controller protocol shared by every controller, and the sum of two controllers.

A controller is a pair of pure functions over a parameter pytree (like
``optax.GradientTransformation``), plus a value check that runs once on concrete
parameters before tracing:

* ``init(params, y0) -> state``: ``y0`` is the first measurement ``[n_y]``.
* ``step(params, state, y) -> (state, u)``: ``y`` is the measurement ``[n_y]`` at this
  sample; ``u`` is the torque ``[n_u]`` (N*m) held over the next sample.
* ``check(params)``: raises ``ValueError`` naming the parameter and its accepted range.
  ``rollout`` calls it with the parameters as it gets them: under ``jit``, ``grad`` or
  ``vmap`` some or all leaves are tracers, and a check skips those (``is_concrete``,
  ``check_scalar_param``) so that the concrete ones are still checked. A check that reads
  a traced leaf anyway (``float`` of it) is skipped for that call.
* ``dt``: the sample time (s) the controller was built for, or ``None`` when its step does
  not depend on it. ``rollout`` refuses a plant sampled at another ``dt``.
* ``batched``: whether ``init`` and ``step`` also run a batch of scenarios at once, given
  measurements ``[n_y, B]`` with the batch as a trailing axis, and returning states and
  torques ``[n_u, B]`` with it trailing as well (``False`` by default). ``rollout`` calls
  such a controller once per step for a whole batch, and maps any other over the batch
  with ``vmap``, its state batch-first as under ``vmap`` over single rollouts. The built-in
  controllers are batched: a ring buffer laid out ``[slots, n, B]`` makes each sample's
  write and read one contiguous row, where ``vmap`` would lay it out ``[B, slots, n]`` (see
  ``jaxflex.rollout``).

The measurement of the single-link arm is ``y = [theta (rad), theta_dot (rad/s)]`` and
``n_u = 1``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from jaxflex import checks


class Controller(NamedTuple):
    """A controller: ``init``, ``step``, ``check`` and ``dt`` (see the module docstring)."""

    init: Callable[[Any, jax.Array], Any]
    step: Callable[[Any, Any, jax.Array], tuple[Any, jax.Array]]
    check: Callable[[Any], None]
    dt: float | None = None
    batched: bool = False


def same_dt(reference: float, dt: ArrayLike) -> Any:
    """``dt`` equals the sample time ``reference`` up to float32 round-off (a plant's ``dt``
    may be float32); a Python bool, or a traced one when ``dt`` is traced."""
    return abs(dt - reference) <= 1e-6 * reference


def is_concrete(tree: Any) -> bool:
    """True when no leaf of ``tree`` is a tracer, so value checks can run."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(tree))


def check_controller(name: str, controller: Any) -> Controller:
    """Refuse, by ``name``, what is not a :class:`Controller` of callables: a factory such as
    ``dfs`` or ``fuzzy`` passed uncalled, or a ``check`` left None."""
    checks.instance(name, controller, Controller, "build one with dfs(...), fuzzy(...), pd(...), by_name(...) or combine(...)")
    for field in ("init", "step", "check"):
        if not callable(getattr(controller, field)):
            raise ValueError(f"{name}.{field} must be callable (see jaxflex.controllers.base); got {getattr(controller, field)!r}")
    if controller.dt is not None:
        checks.number(f"{name}.dt", controller.dt, strict=True, unit="seconds")
    if not isinstance(controller.batched, bool):
        raise ValueError(f"{name}.batched must be True or False (see jaxflex.controllers.base); got {controller.batched!r}")
    return controller


def check_params_type(params: Any, expected: type) -> None:
    """Refuse, by name, parameters that are not an ``expected`` (a dict of gains, a bare tuple):
    they would fail deep in the step with an AttributeError."""
    if not isinstance(params, expected):
        raise ValueError(f"params must be a {expected.__name__} ({', '.join(expected._fields)}); got {type(params).__name__} {params!r}")


def check_finite_scalar(name: str, value: Any, *, positive: bool = False, nonnegative: bool = False, unit: str = "") -> float:
    """Value check on a concrete scalar parameter; returns it as a float.

    Raises:
      ValueError: naming ``name``, the accepted range and the ``unit`` (if given) when
        ``value`` is not a finite real scalar (and positive / non-negative where asked).
    """
    unit = f" ({unit})" if unit else ""
    arr = checks.real_array(name, value, scalar=True)
    if arr.ndim != 0:
        raise ValueError(f"{name} must be a scalar{unit}; got shape {arr.shape}")
    v = float(arr)
    if positive and not (v > 0 and v < float("inf")):
        raise ValueError(f"{name} must be finite and > 0{unit}; got {v}")
    if nonnegative and not (v >= 0 and v < float("inf")):
        raise ValueError(f"{name} must be finite and >= 0{unit}; got {v}")
    if not (abs(v) < float("inf")):
        raise ValueError(f"{name} must be finite{unit}; got {v}")
    return v


def check_scalar_param(name: str, value: Any, *, positive: bool = False) -> float | None:
    """``check_finite_scalar`` of a controller parameter that may be traced (a leaf ``jit``,
    ``grad`` or ``vmap`` traces): ``None`` for a tracer, whose value is not known yet, though
    its shape is (a vector k under ``jit`` was blamed on the controller's torque shape)."""
    if isinstance(value, jax.core.Tracer):
        if value.ndim != 0:
            raise ValueError(f"{name} must be a scalar; got shape {value.shape} (traced)")
        return None
    return check_finite_scalar(name, value, positive=positive)


def check_params(controller: Controller, params: Any) -> None:
    """``controller.check(params)``, with some leaves possibly traced: the built-in checks
    skip tracers and check the rest; a check that cannot (it reads a tracer's value) is
    skipped when any leaf is traced."""
    try:
        controller.check(params)
    except jax.errors.JAXTypeError:
        if is_concrete(params):
            raise


class OpenLoopParams(NamedTuple):
    """The open loop has no parameters."""


def open_loop() -> Controller:
    """The uncontrolled arm: ``u = 0``."""

    def init(params: OpenLoopParams, y0: jax.Array) -> tuple[()]:
        del params, y0
        return ()

    def step(params: OpenLoopParams, state: tuple[()], y: jax.Array) -> tuple[tuple[()], jax.Array]:
        del params
        return state, jnp.zeros((1,) + jnp.shape(y)[1:], y.dtype)

    return Controller(init, step, lambda params: None, batched=True)


def combine(first: Controller, second: Controller) -> Controller:
    """The sum of two controllers: ``u = u_first + u_second``.

    Parameters and states are pairs ``(first, second)``. The sum runs at the parts' ``dt``.

    Raises:
      ValueError: when either is not a Controller, or the two were built for different
        sample times.
    """
    check_controller("first", first)
    check_controller("second", second)
    if first.dt is not None and second.dt is not None and not same_dt(first.dt, second.dt):
        raise ValueError(f"cannot combine controllers built for dt = {first.dt:g} s and dt = {second.dt:g} s: build both with one dt")

    def init(params: tuple[Any, Any], y0: jax.Array) -> tuple[Any, Any]:
        return first.init(params[0], y0), second.init(params[1], y0)

    def step(params: tuple[Any, Any], state: tuple[Any, Any], y: jax.Array) -> tuple[tuple[Any, Any], jax.Array]:
        s1, u1 = first.step(params[0], state[0], y)
        s2, u2 = second.step(params[1], state[1], y)
        return (s1, s2), u1 + u2

    def check(params: tuple[Any, Any]) -> None:
        if not (isinstance(params, tuple) and not hasattr(params, "_fields") and len(params) == 2):  # a NamedTuple of two fields is one part's
            raise ValueError(
                "params of a combined controller must be a pair (first's params, second's params), "
                f"as (DFSParams(...), fuzzy_params()) for combine(dfs(), fuzzy()); got {type(params).__name__} {params!r}"
            )
        first.check(params[0])
        second.check(params[1])

    return Controller(init, step, check, first.dt if first.dt is not None else second.dt, first.batched and second.batched)
