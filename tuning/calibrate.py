"""Fit the arm's constants to what was measured on it: natural frequencies (a tap test) and,
optionally, modal damping ratios (a ring-down); both can come from a free-vibration record
through :mod:`tuning.identify`.

Frequencies: nonlinear least squares (``scipy.optimize.least_squares``, trust region) over the
logarithms of the fitted fields of :class:`~jaxflex.beam.BeamParams`, on the residuals
``log(f_model / f_measured)``, so that a 1 % error weighs the same at every mode. The model is
the assumed-mode model that jaxflex simulates, with the number of modes it will be simulated
with, so the calibrated arm's simulated frequencies are the measured ones (not those of the
exact beam equation, which the assumed modes approach from above as modes are added). The
Jacobian is ``jax.jacfwd`` of the same model. The fit runs in float64 whatever the caller's
JAX setting (a scoped ``jax.enable_x64``).

Frequencies alone do not determine every field: without a hub or a payload the cantilever's
frequencies depend on ``E``, ``rho`` and the thickness only through ``E h^2 / rho``. A fit whose
fields are not told apart by the measured frequencies (a Jacobian of rank below the number of
fields) is refused, naming them.

Damping: with the calibrated model's frequencies ``w_i``, Rayleigh damping gives mode ``i``
the ratio ``alpha / (2 w_i) + beta w_i / 2`` exactly (the modes of ``M`` and ``K`` diagonalise
``alpha M + beta K``). Two or more measured ratios fit ``alpha, beta >= 0`` by non-negative
least squares; a single ratio (of mode 1) sets ``damping_ratio`` (jaxflex's convention: that
ratio in flexible modes 1 and 2 of the free hub's 2-mode model) to the value that gives mode 1
of the calibrated model the measured ratio.
"""

from __future__ import annotations

import numbers
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from jaxflex import beam, checks
from jaxflex.plant import check_dt, check_method, make_plant, rk4_amplified_omega
from jaxflex.scenarios import ScenarioSpec

FITTABLE = tuple(name for name in beam.BeamParams._fields if name not in ("damping_ratio", "rayleigh_alpha", "rayleigh_beta"))
"""The arm's physical constants: every field of ``BeamParams`` but the damping."""
DEFAULT_FIT = ("youngs_modulus_pa", "hub_inertia_kg_m2")
"""Fitted by default, as many as there are frequencies (the hub's inertia only with the hub
free: held still, it does not move)."""
MAX_FACTOR = 1e3
"""A fitted field stays within this factor of its starting value (a bound of the search): a
fit that reaches it is refused, since it points at a unit slip rather than at the arm."""
RANK_RTOL = 1e-8
"""Singular values of the log-Jacobian below this fraction of the largest count as zero."""


MISFIT_PERCENT = 5.0
"""A calibrated model that misses a measured frequency or damping ratio by more than this (%)
gets a note (``Calibration.notes``)."""


class Calibration(NamedTuple):
    """The outcome of :func:`calibrate`.

    Attributes:
      beam: the calibrated arm (the starting one with the fitted fields, and the damping when
        ratios were given, replaced).
      n_modes: number of assumed modes of the model fitted (simulate with this many).
      hub: ``"free"`` or ``"clamped"``, the condition the frequencies were measured in.
      fit: the fitted fields.
      start: their starting values.
      measured_hz: [n_f] the measured frequencies.
      before_hz: [n_f] the model's frequencies with the starting arm.
      after_hz: [n_f] the model's frequencies with the calibrated arm.
      measured_damping: [n_d] the measured damping ratios of modes 1..n_d (n_d may be 0).
      after_damping: [n_f] the calibrated model's damping ratio in each measured mode.
      sensitivity: [len(fit)] each fitted field's change in %, to first order, for independent
        errors of 1 % in the measured frequencies: large values (say above 10) mean the
        frequencies determine that field poorly, however well the model then matches them.
      evaluations: model evaluations the least-squares search took.
    """

    beam: beam.BeamParams
    n_modes: int
    hub: str
    fit: tuple[str, ...]
    start: tuple[float, ...]
    measured_hz: np.ndarray
    before_hz: np.ndarray
    after_hz: np.ndarray
    measured_damping: np.ndarray
    after_damping: np.ndarray
    sensitivity: np.ndarray
    evaluations: int

    @property
    def error_after_percent(self) -> np.ndarray:
        """[n_f] the calibrated model's error in each frequency, in % of the measured."""
        return 100.0 * (self.after_hz / self.measured_hz - 1.0)

    @property
    def damping_error_percent(self) -> np.ndarray:
        """[n_d] the calibrated model's error in each measured damping ratio, in % of it (a
        Rayleigh pair cannot give every set of ratios: 1 % and 85 % come out 28 % and 75 %)."""
        return 100.0 * (self.after_damping[: self.measured_damping.size] / self.measured_damping - 1.0)

    @property
    def notes(self) -> list[str]:
        """What to check before trusting the calibrated arm (``jaxflex calibrate`` prints each
        as a ``note:``; ``calibration.json`` holds them): a damping ratio or a frequency that the
        calibrated model misses by more than ``MISFIT_PERCENT``, a field the frequencies
        determine poorly (a sensitivity over 10) and a field moved more than 10x from its start
        (frequencies in rad/s given as Hz move the modulus 39x)."""
        notes = []
        missed = abs(self.damping_error_percent)
        if missed.size and missed.max() > MISFIT_PERCENT:  # 0.01, 0.85 became 0.28, 0.75 with no word
            worst = int(missed.argmax())
            notes.append(f"the model misses the damping ratio of mode {worst + 1} by {missed[worst]:.3g} % (over {MISFIT_PERCENT:g} %): Rayleigh damping, "
                         "alpha / (2 omega) + beta omega / 2 with alpha, beta >= 0, cannot give these ratios; check them (a ratio of 0.01 is 1 %; a heavily "
                         "damped mode found in a record may be noise or an aliased mode)")
        loose = [name for name, sensitivity in zip(self.fit, self.sensitivity) if sensitivity > 10]
        if loose:
            notes.append(f"the measured frequencies determine {', '.join(loose)} poorly (over 10 % per 1 % error in them): fit fewer fields, or measure more modes")
        moved = [name for name, start in zip(self.fit, self.start) if not 0.1 <= float(getattr(self.beam, name)) / start <= 10]
        if moved:
            notes.append(f"{', '.join(moved)} moved by more than 10x from the starting arm: check the units (Hz, not rad/s; SI constants in [beam]) and the hub condition (--hub)")
        errors = abs(self.error_after_percent)
        if errors.max() > MISFIT_PERCENT:  # free-hub frequencies fitted as clamped left -34 % and +51 % with no word
            worst = int(errors.argmax())
            notes.append(f"the calibrated arm still misses mode {worst + 1} by {errors[worst]:.3g} % (over {MISFIT_PERCENT:g} %): fitting {', '.join(self.fit)} "
                         f"cannot match these frequencies; check the hub condition (--hub: was the arm held {self.hub}?), that they are the first modes in order, and their units")
        return notes

    def as_dict(self) -> dict[str, Any]:
        """Plain numbers for JSON."""
        return {
            "n_modes": self.n_modes,
            "hub": self.hub,
            "fitted": {
                name: {"start": start, "calibrated": float(getattr(self.beam, name)), "percent_per_percent_frequency_error": float(s)}
                for name, start, s in zip(self.fit, self.start, self.sensitivity)
            },
            "measured_hz": self.measured_hz.tolist(),
            "model_before_hz": self.before_hz.tolist(),
            "model_after_hz": self.after_hz.tolist(),
            "error_after_percent": self.error_after_percent.tolist(),
            "measured_damping": self.measured_damping.tolist(),
            "model_damping": self.after_damping.tolist(),
            "damping_error_percent": self.damping_error_percent.tolist(),
            "evaluations": self.evaluations,
            "notes": self.notes,
            "beam": {k: (None if v is None else float(v)) for k, v in self.beam._asdict().items()},
        }


def _numbers(name: str, values: Any, high: float | None = None) -> np.ndarray:
    """``values`` (a number or a 1-D sequence) as float64, each finite, > 0 (and < ``high``)."""
    arr = checks.real_array(name, values).astype(np.float64)
    if arr.ndim > 1:
        raise ValueError(f"{name} must be a sequence of numbers; got shape {arr.shape}")
    arr = arr.reshape(-1)
    if np.any(~np.isfinite(arr) | (arr <= 0) | (arr >= (np.inf if high is None else high))):
        accepted = "> 0" if high is None else f"in (0, {high:g})"
        raise ValueError(f"{name} must be finite numbers {accepted}; got {arr.tolist()}")
    return arr


def _check(measured_hz: Any, params: beam.BeamParams, fit: Sequence[str] | None, n_modes: int | None, hub: str, damping: Any) -> tuple[np.ndarray, tuple[str, ...], int, np.ndarray]:
    beam.check_beam_params(params)
    measured = _numbers("measured_hz", measured_hz)
    if measured.size == 0:
        raise ValueError("measured_hz must hold at least one frequency (Hz)")
    if np.any(np.diff(measured) <= 0):
        raise ValueError(f"measured_hz must be strictly ascending, mode 1 first (Hz); got {measured.tolist()}")
    beam.check_hub(hub)
    fit = default_fit(hub, measured.size) if fit is None else fit
    if not isinstance(fit, (list, tuple)) or not all(isinstance(name, str) for name in fit):
        raise ValueError(f"fit must be a list or tuple of field names of BeamParams; got {fit!r}")
    fit = tuple(fit)
    unknown = [name for name in fit if name not in FITTABLE]
    if unknown or not fit or len(set(fit)) != len(fit):
        raise ValueError(f"fit must name distinct fields among {', '.join(FITTABLE)}; got {list(fit)}")
    if len(fit) > measured.size:
        raise ValueError(f"fit names {len(fit)} fields but {_count(measured.size)} measured: fit at most {measured.size}")
    zero = [name for name in fit if float(getattr(params, name)) <= 0]
    if zero:
        raise ValueError(f"{', '.join(zero)} start(s) at 0: give a positive starting value in the arm ([beam]) to fit it")
    n_modes = max(2, measured.size) if n_modes is None else beam.check_n_modes(n_modes)
    if n_modes < measured.size:
        raise ValueError(f"n_modes must be >= the number of measured frequencies ({measured.size}); got {n_modes}")
    try:
        ratios = np.zeros(0) if damping is None else _numbers("damping", damping, 1.0)
    except ValueError as err:
        arr = np.asarray(damping, dtype=object).reshape(-1)
        if all(isinstance(v, numbers.Real) and not isinstance(v, bool) and 1 <= v < 100 for v in arr):  # 1.5 meant as 1.5 %
            raise ValueError(f"{err} (ratios, not percent: {arr[0]:g} % is {arr[0] / 100:g})") from None
        raise
    if ratios.size > measured.size:
        raise ValueError(f"damping holds {ratios.size} ratios but {_count(measured.size)} measured: give at most one ratio per measured mode, mode 1 first")
    return measured, fit, n_modes, ratios


def default_fit(hub: str, n_freqs: int) -> tuple[str, ...]:
    """The first ``n_freqs`` of ``DEFAULT_FIT`` that act on the frequencies with this hub."""
    return tuple(name for name in DEFAULT_FIT if hub != "clamped" or name != "hub_inertia_kg_m2")[: max(n_freqs, 1)]


def _count(n: int) -> str:
    return f"{n} frequenc{'y was' if n == 1 else 'ies were'}"


def _model(params: beam.BeamParams, fit: tuple[str, ...], n_modes: int, hub: str, n_f: int):
    """``log f_model(z)[:n_f]`` with field ``i`` of ``fit`` at ``start_i exp(z_i)``, and its Jacobian."""
    start = jnp.asarray([float(getattr(params, name)) for name in fit], jnp.float64)

    def log_freqs(z: jax.Array) -> jax.Array:
        arm = params._replace(**{name: value for name, value in zip(fit, start * jnp.exp(z))})
        return jnp.log(beam.natural_frequencies_hz(arm, n_modes, hub)[:n_f])

    return jax.jit(log_freqs), jax.jit(jax.jacfwd(log_freqs))


def calibrate(
    measured_hz: Any,
    params: beam.BeamParams | None = None,
    fit: Sequence[str] | None = None,
    n_modes: int | None = None,
    hub: str = "free",
    damping: Any = None,
) -> Calibration:
    """Fit ``fit``'s fields of ``params`` so that the n-mode model has the measured frequencies.

    Args:
      measured_hz: [n_f] measured natural frequencies (Hz) of flexible modes 1..n_f, ascending.
      params: the arm as known before the fit (geometry, material; default the paper's): the
        starting point, and the value of every field not fitted.
      fit: fields to fit, at most n_f, each starting from a positive value (``FITTABLE``);
        default :func:`default_fit`.
      n_modes: assumed modes of the model (default ``max(2, n_f)``; at least n_f). Simulate
        the calibrated arm with the same number.
      hub: the condition the frequencies were measured in: ``"free"`` (motor unpowered) or
        ``"clamped"`` (hub held still); see :func:`jaxflex.beam.natural_frequencies_hz`.
      damping: optional [n_d <= n_f] measured damping ratios of modes 1..n_d, each in (0, 1).

    Raises:
      ValueError: naming a bad input; a fitted field that does not act on the frequencies
        (the hub's inertia with the hub clamped, or on an arm in the wrong units: the starting
        arm's frequencies are named beside the measured ones); fields that the measured frequencies do not
        tell apart; a fit that ran to ``MAX_FACTOR`` times a starting value; or a fit that did
        not converge.
    """
    params = beam.BeamParams() if params is None else params
    measured, fit, n_modes, ratios = _check(measured_hz, params, fit, n_modes, hub, damping)
    start = tuple(float(getattr(params, name)) for name in fit)
    with jax.enable_x64(True):
        log_freqs, jacobian = _model(params, fit, n_modes, hub, measured.size)
        target = np.log(measured)
        z0 = np.zeros(len(fit))
        jac0 = np.asarray(jacobian(z0))
        scale = np.max(np.abs(jac0))
        inert = [name for name, column in zip(fit, jac0.T) if np.max(np.abs(column)) <= RANK_RTOL * scale]
        if inert:
            f0 = np.exp(np.asarray(log_freqs(z0)))
            far = np.any(np.abs(np.log(f0 / measured)) > np.log(10))
            units = "; a factor of 10 or more apart: check the starting arm's units (a length or a thickness in mm)" if far else ""
            hz = ", ".join
            raise ValueError(f"{', '.join(inert)} does not change the model's frequencies with the hub {hub}: leave it out of fit (the starting arm's model "
                             f"gives {hz(f'{f:.4g}' for f in f0)} Hz, against the {hz(f'{f:.4g}' for f in measured)} Hz measured{units})")
        sv = np.linalg.svd(jac0, compute_uv=False)
        if sv[-1] <= RANK_RTOL * sv[0]:
            raise ValueError(
                f"the measured frequencies do not tell {', '.join(fit)} apart (with the hub {hub}, the model's frequencies "
                f"change with them in fixed proportion): fit fewer fields, or fields that act differently"
            )
        bound = np.log(MAX_FACTOR)
        result = scipy.optimize.least_squares(
            lambda z: np.asarray(log_freqs(z)) - target,
            z0,
            jac=lambda z: np.asarray(jacobian(z)),
            bounds=(-bound, bound),
            x_scale="jac",
            ftol=1e-15,
            xtol=1e-15,
            gtol=1e-15,
            max_nfev=200,
        )
        at_bound = [name for name, z in zip(fit, result.x) if abs(z) >= bound * (1 - 1e-9)]
        if at_bound:
            raise ValueError(
                f"the fit took {', '.join(at_bound)} to {MAX_FACTOR:g} times (or 1/{MAX_FACTOR:g} of) its starting value: check the "
                f"units of the measured frequencies (Hz) and of the arm's constants, and whether the hub was {hub}"
            )
        if not result.success:
            raise ValueError(f"the fit did not converge ({result.message}); start from an arm closer to the measured one, or fit fewer fields")
        # d log(field) / d log(f_j) at the solution; a 1 % error in every frequency,
        # independent, moves each field by the root sum of squares of its row (in %)
        sensitivity = np.sqrt(np.sum(np.linalg.pinv(np.asarray(jacobian(result.x))) ** 2, axis=1))
        arm = params._replace(**{name: float(s * np.exp(z)) for name, s, z in zip(fit, start, result.x)})
        before, after = (np.exp(np.asarray(log_freqs(z), np.float64)) for z in (z0, result.x))
        arm, model_damping = _fit_damping(arm, after, ratios)
    return Calibration(arm, n_modes, hub, fit, start, measured, before, after, ratios, model_damping, sensitivity, int(result.nfev))


def _fit_damping(arm: beam.BeamParams, model_hz: np.ndarray, ratios: np.ndarray) -> tuple[beam.BeamParams, np.ndarray]:
    """The arm with the measured damping, and the damping ratio of its model in each measured mode."""
    omega = 2.0 * np.pi * model_hz
    if ratios.size == 1:
        # damping_ratio is that of the free hub's 2-mode model; the ratio of the mode measured
        # is proportional to it
        unit = arm._replace(damping_ratio=1.0, rayleigh_alpha=None, rayleigh_beta=None)
        alpha, beta = (float(c) for c in beam.rayleigh_coefficients(unit))
        arm = unit._replace(damping_ratio=float(ratios[0] / (alpha / (2.0 * omega[0]) + beta * omega[0] / 2.0)))
    elif ratios.size >= 2:
        basis = np.stack([0.5 / omega[: ratios.size], 0.5 * omega[: ratios.size]], axis=1)
        scale = np.linalg.norm(basis, axis=0)
        coef, _ = scipy.optimize.nnls(basis / scale, ratios)
        alpha, beta = coef / scale
        arm = arm._replace(rayleigh_alpha=float(alpha), rayleigh_beta=float(beta))
    alpha, beta = (float(c) for c in beam.rayleigh_coefficients(arm))
    return arm, alpha / (2.0 * omega) + beta * omega / 2.0


def to_toml(calibration: Calibration, dt: float | None = None, method: str | None = None) -> str:
    """A config holding the calibrated arm: ``n_modes`` and a ``[beam]`` table with every
    field, readable as ``--config`` by ``jaxflex tune``, ``montecarlo`` and ``stability``.

    ``dt`` and ``method``: the sample time (``[scenarios] dt``) and integrator of the config
    the arm came from, kept so that the file serves in its place (default: neither written,
    RK4 judged at ``ScenarioSpec``'s 1 ms). An RK4 step that grows the arm's fastest mode at
    that ``dt`` is replaced by the exact zero-order hold, and the file says so."""
    checks.instance("calibration", calibration, Calibration, "the result of calibrate(...)")
    if dt is not None:
        check_dt(dt)
    if method is not None:
        check_method(method)
    arm = calibration.beam
    # with the Rayleigh pair set, damping_ratio is ignored: say so where an edit would be lost
    unused = {"damping_ratio": "  # not used: rayleigh_alpha and rayleigh_beta set the damping (remove both to use it)"} if arm.rayleigh_alpha is not None else {}
    fields = "\n".join(f"{name} = {float(value)!r}{unused.get(name, '')}" for name, value in arm._asdict().items() if value is not None)
    measured = ", ".join(f"{f:g}" for f in calibration.measured_hz)
    # tune's and montecarlo's default integrator would refuse an arm whose fastest mode one RK4
    # step at the default dt grows (8 modes of the paper's arm at 1 ms): the exact ZOH serves
    step = ScenarioSpec().dt if dt is None else dt
    with jax.enable_x64(True):
        grown = None if method == "zoh" else rk4_amplified_omega(make_plant(arm, calibration.n_modes), step)
    if grown is not None:
        whose = "tune's and montecarlo's default" if method is None else "the config's method"
        method_line = (
            f"# RK4 ({whose}) at [scenarios] dt = {step:g} s grows this arm's {grown / (2 * np.pi):.1f} Hz mode;\n"
            '# the zero-order hold is exact for the arm at any dt.\nmethod = "zoh"\n'
        )
    else:
        method_line = "" if method is None else f'method = "{method}"\n'
    scenarios = "" if dt is None else f"\n[scenarios]\ndt = {float(dt)!r}\n"
    return (
        f"# jaxflex calibrate: the arm fitted to {measured} Hz (hub {calibration.hub}) with {calibration.n_modes} assumed modes.\n"
        "# Pass it as --config to jaxflex tune, montecarlo or stability, or copy its keys and tables into your config.\n"
        f"n_modes = {calibration.n_modes}\n{method_line}{scenarios}\n[beam]\n{fields}\n"
    )
