"""State-space plant of the flexible arm and its discretisation.

State (jaxflex convention): ``x = [theta, q_1..q_n, theta_dot, q_1_dot..q_n_dot]`` (rad, m,
rad/s, m/s), so ``n_x = 2 (n + 1)``. Inputs: hub torque ``u`` [1] (N*m) and a transverse
tip force ``w`` [1] (N). Outputs:

* measured ``y = C x = [theta, theta_dot]`` (what the controllers see);
* performance outputs ``z = Cz x = [theta, w(L), L theta + w(L)]``: hub angle (rad),
  elastic tip deflection (m), tip position (m).

Discretisation with the inputs held over each sample (zero-order hold), by two methods:

* ``"zoh"``: exact, ``expm([[A, B, E], [0, 0, 0]] dt)`` (python-control's block-expm idea),
  balanced first: ``expm(M) = D expm(D^-1 M D) D^-1`` for a diagonal ``D`` of powers of 2
  (exact in floating point) chosen so that each row and column of ``D^-1 M D`` have similar
  norms (Osborne's iteration, as LAPACK's ``gebal``). The modal coordinates make ``A``
  badly scaled (entries of ``M^-1 K`` far above the squared frequencies); unbalanced, a
  float32 ``expm`` was 1e-4 off for the paper's arm, 6 % for 6 modes, and a stiff arm
  (modes 0.3-1.3 kHz at 1 ms) went unstable or NaN (more than ``expm``'s default 16
  squarings). Balanced: 1e-7, 2e-7 and 1e-5, relative to each column's largest entry
  (tested against scipy in float64);
* ``"rk4"``: the paper's classical fourth-order Runge-Kutta. For a linear plant with held
  inputs one RK4 step is exactly ``x+ = P(hA) x + h Q(hA) [B E] [u; w]`` with
  ``P(M) = I + M + M^2/2 + M^3/6 + M^4/24`` and ``Q(M) = I + M/2 + M^2/6 + M^3/24``, so both
  methods give one linear map ``x+ = Ad x + Bd u + Ed w`` and share one rollout. The tests
  check this map against a literal stage-by-stage RK4.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import beam, checks


class LinearPlant(NamedTuple):
    """Continuous-time plant ``x' = A x + B u + E w``, ``y = C x``, ``z = Cz x``.

    Attributes:
      A: [n_x, n_x] state matrix.
      B: [n_x, 1] hub-torque input (N*m).
      E: [n_x, 1] tip-force input (N).
      C: [2, n_x] measurement map: hub angle (rad), hub velocity (rad/s).
      Cz: [3, n_x] performance outputs: hub angle (rad), tip deflection (m), tip position (m).
    """

    A: jax.Array
    B: jax.Array
    E: jax.Array
    C: jax.Array
    Cz: jax.Array


class DiscretePlant(NamedTuple):
    """Sampled plant ``x[k+1] = Ad x[k] + Bd u[k] + Ed w[k]`` with sample time ``dt``.

    Attributes:
      Ad: [n_x, n_x]; Bd: [n_x, 1]; Ed: [n_x, 1]; C: [2, n_x]; Cz: [3, n_x] (as LinearPlant).
      dt: shape () sample time (s).
    """

    Ad: jax.Array
    Bd: jax.Array
    Ed: jax.Array
    C: jax.Array
    Cz: jax.Array
    dt: jax.Array


METHODS = ("rk4", "zoh")


def check_method(method: str, name: str = "method") -> str:
    """``method`` when it is one of ``METHODS``; else ValueError naming ``name``."""
    if method not in METHODS:
        raise ValueError(f"{name} must be one of {METHODS}; got {method!r}")
    return method


def check_continuous(plant: LinearPlant, name: str = "plant") -> LinearPlant:
    """``plant`` when it is a continuous-time LinearPlant; else ValueError naming ``name``
    (a DiscretePlant's ``Ad`` read as ``A`` would give wrong results, not an error)."""
    return checks.instance(name, plant, LinearPlant, "build one with make_plant(...); a DiscretePlant is already sampled")


def check_sampled(plant: DiscretePlant, name: str = "plant") -> DiscretePlant:
    """``plant`` when it is a sampled DiscretePlant; else ValueError naming ``name``."""
    return checks.instance(name, plant, DiscretePlant, "build one with jaxflex.discretize(plant, dt, method)")


def check_plant(plant: LinearPlant | DiscretePlant, name: str = "plant") -> LinearPlant | DiscretePlant:
    """``plant`` when it is a LinearPlant or a DiscretePlant; else ValueError naming ``name``."""
    return checks.instance(name, plant, (LinearPlant, DiscretePlant), "build one with make_plant(...), and sample it with discretize(...) if needed")


def n_modes_of(plant: LinearPlant | DiscretePlant) -> int:
    """Number of assumed modes, read from the (static) state dimension (of one plant or of a
    batch of them)."""
    return check_plant(plant).C.shape[-1] // 2 - 1


def make_plant(params: beam.BeamParams | None = None, n_modes: int = 2) -> LinearPlant:
    """Continuous-time state space of the n-mode arm (differentiable in ``params``).

    Args:
      params: physical constants; default the paper's arm.
      n_modes: number of assumed modes (static int >= 1).
    """
    params = beam.BeamParams() if params is None else params
    beam.check_beam_params(params, representable=True)
    plant = _make_plant(params, beam.check_n_modes(n_modes))
    _check_finite_maps(plant, ("A", "B", "E"), f"for {params} (check the units, or simulate in float64 with jax_enable_x64, --x64)")
    return plant


def _check_finite_maps(plant: LinearPlant | DiscretePlant, names: tuple[str, ...], cause: str) -> None:
    """Refuse a concrete plant whose matrices ``names`` hold inf or NaN, naming the first such
    matrix, its dtype and ``cause`` (traced plants pass: they are checked where built concrete)."""
    for name in names:
        m = getattr(plant, name)
        if isinstance(m, jax.core.Tracer):
            return
        if not np.all(np.isfinite(np.asarray(m))):
            raise ValueError(f"the plant's {name} must be finite in {m.dtype}; got inf or NaN {cause}")


@partial(jax.jit, static_argnums=1)
def _make_plant(params: beam.BeamParams, n_modes: int) -> LinearPlant:
    mats = beam.modal_matrices(params, n_modes)
    n_q = mats.M.shape[0]
    dtype = mats.M.dtype
    minv = jnp.linalg.inv(mats.M)
    eye, zeros = jnp.eye(n_q, dtype=dtype), jnp.zeros((n_q, n_q), dtype)
    A = jnp.block([[zeros, eye], [-minv @ mats.K, -minv @ mats.D]])
    pad = jnp.zeros((n_q, 1), dtype)
    B = jnp.concatenate([pad, (minv @ mats.torque_input)[:, None]])
    E = jnp.concatenate([pad, (minv @ mats.tip_force_input)[:, None]])
    hub = jnp.zeros((2 * n_q,), dtype).at[0].set(1.0)
    hub_rate = jnp.zeros((2 * n_q,), dtype).at[n_q].set(1.0)
    C = jnp.stack([hub, hub_rate])
    tip = jnp.concatenate([mats.tip_deflection, jnp.zeros((n_q,), dtype)])
    length = jnp.asarray(params.length_m, dtype)
    Cz = jnp.stack([hub, tip, length * hub + tip])
    return LinearPlant(A, B, E, C, Cz)


def check_dt(dt: ArrayLike) -> None:
    """Value check of a concrete sample time."""
    if isinstance(dt, jax.core.Tracer):
        return
    arr = checks.real_array("dt", dt, scalar=True).astype(float)
    if arr.ndim != 0 or not np.isfinite(arr) or arr <= 0:
        raise ValueError(f"dt must be a finite scalar > 0 (seconds); got {dt}")


def discretize(plant: LinearPlant, dt: ArrayLike = 1e-3, method: str = "rk4", *, check_rk4: bool = True) -> DiscretePlant:
    """Sample the plant with inputs held over each step of ``dt`` seconds.

    Args:
      plant: continuous-time plant.
      dt: sample time (s), finite and > 0; default 1 ms (the paper's 1 kHz).
      method: ``"rk4"`` (the paper's integrator) or ``"zoh"`` (exact).
      check_rk4: refuse an RK4 step that amplifies a mode (below); ``False`` returns such a
        map as it is, to study it (``jaxflex stability`` reports its spectral radius).

    Raises:
      ValueError: naming ``plant`` when it is not a LinearPlant, ``dt`` or ``method`` out of
        range, a sampled matrix that is not finite, or (plant and ``dt`` concrete) an RK4
        step that amplifies a mode the continuous plant does not grow
        (:func:`check_rk4_step`): such a map blows up where the arm rings down.
    """
    check_continuous(plant)
    check_dt(dt)
    check_method(method)
    if check_rk4 is not False and check_rk4 is not True:
        raise ValueError(f"check_rk4 must be True or False; got {check_rk4!r}")
    if method == "rk4" and check_rk4 and not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((plant, dt))):
        check_rk4_step(plant, dt)
    sampled = _discretize(plant, dt, method)
    if not isinstance(dt, jax.core.Tracer):  # a traced dt (jit, vmap or grad over it) makes traced maps: nothing to check
        # A concrete dt stays concrete, even for a traced plant (grad over the arm's
        # constants): paper_scenario and rollout read and check it.
        sampled = sampled._replace(dt=np.asarray(dt, plant.A.dtype))
        hint = " or method = 'zoh'" if method == "rk4" else ""
        _check_finite_maps(sampled, ("Ad", "Bd", "Ed"), f"at dt = {float(dt):g} s, method = {method!r} (use a smaller dt{hint})")
    return sampled


def rk4_amplified_omega(plant: LinearPlant, dt: float) -> float | None:
    """The fastest mode (rad/s) that one RK4 step of ``dt`` amplifies though the continuous
    plant does not grow it, or None when there is none.

    One RK4 step multiplies the mode ``exp(lambda t)`` by ``R(lambda dt)``, ``R(z) = 1 + z +
    z^2/2 + z^3/6 + z^4/24``; for a lightly damped mode ``|R| > 1`` once ``omega dt`` passes
    about 2.83, and the sampled plant blows up where the arm rings down.

    Args:
      plant: a concrete continuous-time plant.
      dt: sample time (s), finite and > 0.
    """
    check_continuous(plant)
    check_dt(dt)
    lam = np.linalg.eigvals(np.asarray(plant.A, dtype=float))
    z = lam * float(dt)
    gain = np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24)
    # An undamped mode's eigenvalues come out of eigvals with real parts of either sign at
    # round-off (+3e-15 for the undamped arm's 229 rad/s mode): that is not growth.
    bad = (gain > 1 + 1e-9) & (lam.real <= 1e-9 * np.abs(lam))
    return float(np.max(np.abs(lam[bad]))) if np.any(bad) else None


def check_rk4_step(plant: LinearPlant, dt: float) -> None:
    """Refuse an RK4 step of ``dt`` that amplifies a mode the continuous plant does not grow
    (:func:`rk4_amplified_omega`).

    Args:
      plant: a concrete continuous-time plant.
      dt: sample time (s).

    Raises:
      ValueError: naming the fastest such mode, its ``omega dt`` and the ZOH alternative
        (or naming ``dt`` when it is not a finite number > 0).
    """
    fastest = rk4_amplified_omega(plant, dt)
    if fastest is not None:
        n_modes = n_modes_of(plant)
        raise ValueError(
            f"method = 'rk4' with dt = {float(dt):g} s is unstable for this arm: its mode at {fastest / (2 * np.pi):.4g} Hz has "
            f"omega dt = {fastest * float(dt):.3g} (RK4 holds up to about 2.8). Use method = 'zoh' (exact for any dt) or dt <= {2.8 / fastest:.3g} s, "
            f"once the arm, dt and the {n_modes} mode{'s' * (n_modes != 1)} are what you meant: a unit slip (a thickness in mm, dt in ms) "
            "gives this too, and so do more modes than the sample time holds (each adds a faster one)"
        )


@partial(jax.jit, static_argnums=2)
def _discretize(plant: LinearPlant, dt: ArrayLike, method: str) -> DiscretePlant:
    n_x = plant.A.shape[0]
    dtype = plant.A.dtype
    dt = jnp.asarray(dt, dtype)
    inputs = jnp.concatenate([plant.B, plant.E], axis=1)  # [n_x, 2]
    if method == "zoh":
        block = jnp.zeros((n_x + 2, n_x + 2), dtype)
        block = block.at[:n_x, :n_x].set(plant.A).at[:n_x, n_x:].set(inputs)
        scale = _balancing_scales(block * dt)
        balanced = block * dt * scale[None, :] / scale[:, None]
        phi = jax.scipy.linalg.expm(balanced, max_squarings=64) / scale[None, :] * scale[:, None]
        Ad, Gd = phi[:n_x, :n_x], phi[:n_x, n_x:]
    else:
        ha = dt * plant.A
        eye = jnp.eye(n_x, dtype=dtype)
        # Horner form of the Taylor polynomials P and Q of the module docstring.
        q = eye + ha @ (eye / 2 + ha @ (eye / 6 + ha / 24))
        Ad = eye + ha @ q
        Gd = dt * q @ inputs
    return DiscretePlant(Ad, Gd[:, :1], Gd[:, 1:], plant.C, plant.Cz, dt)


def _balancing_scales(M: jax.Array, sweeps: int = 30) -> jax.Array:
    """Powers of 2 ``d`` [n] such that ``D^-1 M D`` (``D = diag(d)``) has each row's and
    column's off-diagonal 1-norms within a factor of about 2 of each other: Osborne's
    iteration, one index at a time (updating all at once falls into a 2-cycle), ``sweeps``
    passes over the indices. A zero row or column keeps the scale 1.

    Any ``d`` gives an exact similarity, so the scales are held constant for derivatives.
    """
    n = M.shape[0]
    magnitude = jnp.abs(jax.lax.stop_gradient(M)) * (1 - jnp.eye(n, dtype=M.dtype))

    one = jnp.ones((n,), M.dtype)

    def update(step, exponent):
        i = step % n
        d = jnp.ldexp(one, exponent)  # exact powers of 2 (exp2 is not, in float32 on the CPU)
        row = jnp.sum(magnitude[i] * d) / d[i]
        col = jnp.sum(magnitude[:, i] / d) * d[i]
        both = (row > 0) & (col > 0)
        ratio = jnp.where(both, row, 1) / jnp.where(both, col, 1)
        return exponent.at[i].add(jnp.round(0.5 * jnp.log2(ratio)).astype(exponent.dtype))

    return jnp.ldexp(one, jax.lax.fori_loop(0, sweeps * n, update, jnp.zeros((n,), jnp.int32)))
