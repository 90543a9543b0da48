"""Assumed-mode model of a single-link flexible arm: a rotating Euler-Bernoulli beam on a hub.

Kinematics (small deflections, horizontal plane, no gravity): a point at distance x along
the beam moves transversally by ``y(x, t) = x theta(t) + v(x, t)`` with the elastic
deflection ``v(x, t) = sum_i phi_i(x) q_i(t)`` expanded in ``n`` clamped-free cantilever
mode shapes. The kinetic energy ``T = 1/2 (I_H + I_b) theta_dot^2 + 1/2 int_0^L rho A
(v_dot^2 + 2 v_dot x theta_dot) dx`` with ``I_b = rho A L^3 / 3``, and the strain energy
``U = 1/2 int_0^L E I (v'')^2 dx`` (plus an optional tip payload of mass ``m_p`` and rotary
inertia ``J_p``), give by Lagrange's equations ``M Q'' + D Q' + K Q = F`` with
``Q = [theta, q_1..q_n]`` and ``F = [tau, 0, .., 0]``.

Mode shapes are normalised so that ``int_0^L phi_i^2 dx = L``; then ``|phi_i(L)| = 2``. This
only sets the scale of the modal coordinates ``q_i`` (metres at the tip / 2).

All matrix entries are closed forms in the physical parameters, so every quantity here is
differentiable with respect to them:

* ``M[0, 0] = I_H + rho A L^3 / 3 + m_p L^2 + J_p``
* ``M[0, i] = rho A int x phi_i dx + m_p L phi_i(L) + J_p phi_i'(L)``, with
  ``int_0^L x phi_i dx = 2 / beta_i^2`` (integrate ``phi'''' = beta^4 phi`` by parts)
* ``M[i, j] = rho A L delta_ij + m_p phi_i(L) phi_j(L) + J_p phi_i'(L) phi_j'(L)``
* ``K[i, j] = E I beta_i^4 L delta_ij`` (``K[0, :] = 0``: the hub is free)
* ``D = alpha M + beta K`` (Rayleigh).

The dimensionless roots ``lambda_i = beta_i L`` of ``1 + cos(lambda) cosh(lambda) = 0`` are
computed once in NumPy: they depend only on the (static) number of modes.
"""

from __future__ import annotations

import math
from functools import lru_cache, partial
from typing import Any, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import checks, fileio


class BeamParams(NamedTuple):
    """Physical constants of the arm, SI units; defaults are the paper's aluminium link.

    Every field is a leaf, so jax.grad works with respect to any of them.

    Attributes:
      length_m: beam length L (m).
      width_m: cross-section width b (m).
      thickness_m: cross-section thickness h (m); second moment of area is b h^3 / 12.
      youngs_modulus_pa: E (N/m^2).
      density_kg_m3: rho (kg/m^3).
      hub_inertia_kg_m2: hub inertia I_H (kg m^2).
      payload_mass_kg: tip payload mass m_p (kg); 0 in the paper.
      payload_inertia_kg_m2: tip payload rotary inertia J_p about the tip (kg m^2); 0 in the paper.
        With J_p > 0 the assumed-mode frequencies converge slowly, about as 1/n: every
        clamped-free shape has zero bending moment at the tip, which J_p's does not. The
        first three of ``exact_natural_frequencies_hz`` are 0.07, 0.6 and 5.8 % high with 3
        modes at 1e-4 kg m^2, 0.005, 0.08 and 0.5 % high with 30; at 1 kg m^2 16-20 % with 3 and 0.3-0.4 %
        with 100. A tip mass alone converges fast (1e-5 with 20 modes).
      damping_ratio: modal damping ratio given to the two flexible modes of the 2-mode model
        of these parameters, from which the Rayleigh coefficients are derived (jaxflex
        convention; the paper gives no values). Ignored when both Rayleigh fields are set.
      rayleigh_alpha: mass-proportional Rayleigh coefficient (1/s). Give both Rayleigh
        coefficients, or neither (None) to derive them from ``damping_ratio``.
      rayleigh_beta: stiffness-proportional Rayleigh coefficient (s), with ``rayleigh_alpha``.
    """

    length_m: ArrayLike = 0.9
    width_m: ArrayLike = 19.008e-3
    thickness_m: ArrayLike = 3.2004e-3
    youngs_modulus_pa: ArrayLike = 71e9
    density_kg_m3: ArrayLike = 2710.0
    hub_inertia_kg_m2: ArrayLike = 5.8598e-4
    payload_mass_kg: ArrayLike = 0.0
    payload_inertia_kg_m2: ArrayLike = 0.0
    damping_ratio: ArrayLike = 0.01
    rayleigh_alpha: ArrayLike | None = None
    rayleigh_beta: ArrayLike | None = None


class ModalMatrices(NamedTuple):
    """Second-order model ``M Q'' + D Q' + K Q = F`` with ``Q = [theta, q_1..q_n]``.

    Attributes:
      M: [n+1, n+1] mass matrix (kg m^2 / kg m / kg blocks).
      K: [n+1, n+1] stiffness matrix.
      D: [n+1, n+1] Rayleigh damping matrix.
      torque_input: [n+1] generalised force of a unit hub torque (= e_0).
      tip_force_input: [n+1] generalised force of a unit transverse tip force: [L, phi_i(L)].
      tip_deflection: [n+1] map from Q to the elastic tip deflection w(L) (m): [0, phi_i(L)].
    """

    M: jax.Array
    K: jax.Array
    D: jax.Array
    torque_input: jax.Array
    tip_force_input: jax.Array
    tip_deflection: jax.Array


_POSITIVE_FIELDS = (
    "length_m",
    "width_m",
    "thickness_m",
    "youngs_modulus_pa",
    "density_kg_m3",
    "hub_inertia_kg_m2",
)
_NONNEGATIVE_FIELDS = ("payload_mass_kg", "payload_inertia_kg_m2", "damping_ratio")


def check_beam_params(params: BeamParams, *, representable: bool = False) -> None:
    """Value checks on concrete parameters (skipped for traced leaves).

    Args:
      params: the parameters.
      representable: also require each field to be representable in the dtype the arm's
        matrices are built in (``structural_dtype``): finite (1e39 N/m^2 is finite in float64
        but inf in float32), and a positive field at least its smallest normal number (else 0).

    Raises:
      ValueError: naming the field and its accepted range (a concrete field must be a real
        scalar), or ``params`` when it is not a ``BeamParams`` (a dict of the fields, say).
    """
    if not isinstance(params, BeamParams):
        raise ValueError(f"params must be a BeamParams (jaxflex.beam.BeamParams(length_m=..., ...)); got {type(params).__name__} {params!r}")
    fields = _POSITIVE_FIELDS + _NONNEGATIVE_FIELDS + ("rayleigh_alpha", "rayleigh_beta")
    for name in fields:
        value = getattr(params, name)
        if (value is None and name.startswith("rayleigh")) or isinstance(value, jax.core.Tracer):
            continue
        arr = checks.real_array(f"BeamParams.{name}", value, scalar=True)
        if arr.ndim != 0:  # the matrices are built for one arm: an array failed deep in JAX with a reshape error
            raise ValueError(f"BeamParams.{name} must be a scalar (one arm; jax.vmap over arms for a batch); got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"BeamParams.{name} must be finite; got {value}")
        if name in _POSITIVE_FIELDS and not np.all(arr > 0):
            raise ValueError(f"BeamParams.{name} must be > 0; got {value}")
        if name not in _POSITIVE_FIELDS and not np.all(arr >= 0):
            raise ValueError(f"BeamParams.{name} must be >= 0; got {value}")
    if (params.rayleigh_alpha is None) != (params.rayleigh_beta is None):
        raise ValueError("BeamParams.rayleigh_alpha and rayleigh_beta must be given together (or both None)")
    if not representable:
        return
    dtype = structural_dtype(params)  # read once the fields are known to be real scalars
    info = jnp.finfo(dtype)
    for name in fields:
        value = getattr(params, name)
        if value is None or isinstance(value, jax.core.Tracer):
            continue
        low = float(info.tiny) if name in _POSITIVE_FIELDS else 0.0
        if not low <= float(np.asarray(value)) <= float(info.max):  # as Python floats: 1e39 is no float32
            raise ValueError(
                f"BeamParams.{name} must be in [{low:.4g}, {info.max:.4g}] to be simulated in {jnp.dtype(dtype).name} "
                f"(float64 with jax_enable_x64, --x64 on the command line); got {value}"
            )


def params_from_mapping(values: Mapping[str, Any]) -> BeamParams:
    """``BeamParams`` from plain numbers by field name (a config's ``[beam]`` table, SI units);
    missing fields keep the paper's values.

    Raises:
      ValueError: naming an unknown key (listing the accepted ones), a value that is not a
        finite number, or one out of its range (``check_beam_params``).
    """
    fileio.check_keys(values, BeamParams._fields, "beam")
    params = BeamParams(**{key: checks.number(f"beam {key}", value, strict=key in _POSITIVE_FIELDS) for key, value in values.items()})
    check_beam_params(params)
    return params


def plain_params(params: Any) -> BeamParams:
    """A configuration's arm: ``params`` checked and with plain float fields (for JSON and
    fingerprints).

    Raises:
      ValueError: naming ``beam`` when ``params`` is not a ``BeamParams``, else as
        ``params_from_mapping``.
    """
    if not isinstance(params, BeamParams):
        raise ValueError(f"beam must be a BeamParams; got {params!r}")
    return params_from_mapping({key: value for key, value in params._asdict().items() if value is not None or not key.startswith("rayleigh")})


MAX_MODES = 100
"""The most assumed modes: the mode shapes' constants overflow float64 from mode 227 on, and
mode 100 of the paper's arm is already at 91 kHz."""


def check_n_modes(n_modes: int) -> int:
    """The number of assumed modes must be a Python int in [1, ``MAX_MODES``] (it sets array
    shapes)."""
    return checks.integer("n_modes", n_modes, high=MAX_MODES)


@lru_cache(maxsize=None)
def _clamped_free_constants(n_modes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dimensionless constants of the first n clamped-free modes (NumPy float64).

    Returns:
      lam: [n] roots lambda_i = beta_i L of 1 + cos(lambda) cosh(lambda) = 0.
      tip_value: [n] phi_i(L) (= +-2 for the normalisation int phi^2 = L).
      tip_slope: [n] L phi_i'(L) / lambda_i, i.e. phi_i'(L) = tip_slope * lambda_i / L.
    """
    lam = np.empty(n_modes)
    for i in range(n_modes):
        z = (2 * i + 1) * math.pi / 2  # asymptotic root; cos(z) + 1/cosh(z) = 0 is well scaled
        for _ in range(60):
            f = math.cos(z) + 1.0 / math.cosh(z)
            df = -math.sin(z) - math.tanh(z) / math.cosh(z)
            step = f / df
            z -= step
            if abs(step) < 1e-15 * z:
                break
        lam[i] = z
    sh, ch, s, c = np.sinh(lam), np.cosh(lam), np.sin(lam), np.cos(lam)
    # phi(L) = cosh - cos - sigma (sinh - sin), sigma = (cosh + cos) / (sinh + sin), simplified.
    tip_value = 2.0 * (ch * s - c * sh) / (sh + s)
    tip_slope = 2.0 * sh * s / (sh + s)
    return lam, tip_value, tip_slope


def clamped_free_roots(n_modes: int) -> np.ndarray:
    """[n] roots lambda_i = beta_i L of the clamped-free frequency equation (dimensionless)."""
    return _clamped_free_constants(check_n_modes(n_modes))[0].copy()


def mode_shapes(x_over_l: ArrayLike, n_modes: int) -> jax.Array:
    """Clamped-free mode shapes phi_i at positions x / L (dimensionless, int phi^2 dx = L).

    Evaluated in a cancellation-free form, so high modes stay accurate in float32.

    Args:
      x_over_l: [P] positions along the beam as a fraction of L, in [0, 1].
      n_modes: number of modes (static).

    Returns:
      [P, n_modes] mode-shape values.

    Raises:
      ValueError: for positions that are not a 1-D array, or (where concrete) outside [0, 1].
    """
    lam = jnp.asarray(_clamped_free_constants(check_n_modes(n_modes))[0])
    xi = jnp.asarray(x_over_l)
    if xi.ndim != 1:
        raise ValueError(f"x_over_l must be a 1-D array of positions [P]; got shape {xi.shape}")
    if not isinstance(xi, jax.core.Tracer) and not np.all((np.asarray(xi) >= 0) & (np.asarray(xi) <= 1)):  # NumPy: no tracer under jit
        raise ValueError(f"x_over_l must lie in [0, 1] (fractions of the length L); got {np.asarray(xi)}")
    lam = lam.astype(jnp.result_type(xi, float))
    z = xi[:, None] * lam[None, :]
    s_l, c_l = jnp.sin(lam), jnp.cos(lam)
    e_l = jnp.exp(-lam)
    # cosh z - sigma sinh z = ((1 - sigma) e^z + (1 + sigma) e^-z) / 2, with
    # (1 - sigma) e^z = 2 (sin L - cos L - e^-L) e^(z - L) / (1 - e^-2L + 2 sin L e^-L).
    denom = 1.0 - e_l**2 + 2.0 * s_l * e_l
    one_minus_sigma_ez = 2.0 * (s_l - c_l - e_l)[None, :] * jnp.exp(z - lam[None, :]) / denom[None, :]
    sigma = 1.0 - 2.0 * (s_l - c_l - e_l) * e_l / denom
    hyper = 0.5 * (one_minus_sigma_ez + (1.0 + sigma)[None, :] * jnp.exp(-z))
    return hyper - jnp.cos(z) + sigma[None, :] * jnp.sin(z)


def structural_dtype(params: BeamParams) -> jnp.dtype:
    """The floating dtype the arm's matrices are built in: that of its length, Young's modulus
    and density, at least JAX's default float (float32 unless ``jax_enable_x64``)."""
    return jnp.result_type(jnp.asarray(params.length_m), params.youngs_modulus_pa, params.density_kg_m3, float)


@partial(jax.jit, static_argnums=1)
def _structural(params: BeamParams, n_modes: int):
    """Mass and stiffness matrices and input maps (no damping); jitted so eager calls are cheap."""
    lam_np, tip_np, slope_np = _clamped_free_constants(n_modes)
    dtype = structural_dtype(params)
    length = jnp.asarray(params.length_m).astype(dtype)
    lam = jnp.asarray(lam_np, dtype)
    tip = jnp.asarray(tip_np, dtype)
    beta = lam / length
    tip_slope = jnp.asarray(slope_np, dtype) * beta
    area = params.width_m * params.thickness_m
    rho_a = params.density_kg_m3 * area
    e_i = params.youngs_modulus_pa * params.width_m * params.thickness_m**3 / 12.0
    m_p, j_p = params.payload_mass_kg, params.payload_inertia_kg_m2

    m00 = params.hub_inertia_kg_m2 + rho_a * length**3 / 3.0 + m_p * length**2 + j_p
    m0i = rho_a * 2.0 / beta**2 + m_p * length * tip + j_p * tip_slope
    mij = rho_a * length * jnp.eye(n_modes, dtype=dtype) + m_p * jnp.outer(tip, tip) + j_p * jnp.outer(tip_slope, tip_slope)
    M = jnp.block([[jnp.reshape(m00, (1, 1)), m0i[None, :]], [m0i[:, None], mij]]).astype(dtype)
    k_diag = jnp.concatenate([jnp.zeros((1,), dtype), e_i * beta**4 * length])
    K = jnp.diag(k_diag).astype(dtype)
    zero = jnp.zeros((1,), dtype)
    torque_input = jnp.concatenate([jnp.ones((1,), dtype), jnp.zeros((n_modes,), dtype)])
    tip_force_input = jnp.concatenate([jnp.reshape(length, (1,)), tip])
    tip_deflection = jnp.concatenate([zero, tip])
    return M, K, torque_input, tip_force_input, tip_deflection


@jax.jit
def _undamped_eigenvalues(M: jax.Array, K: jax.Array) -> jax.Array:
    """Ascending eigenvalues omega^2 of K v = omega^2 M v (M symmetric positive definite)."""
    chol = jnp.linalg.cholesky(M)
    left = jax.scipy.linalg.solve_triangular(chol, K, lower=True)
    sym = jax.scipy.linalg.solve_triangular(chol, left.T, lower=True)
    return jnp.linalg.eigvalsh(0.5 * (sym + sym.T))


def _natural_omegas_sq(M: jax.Array, K: jax.Array) -> jax.Array:
    """Ascending eigenvalues omega^2 of K v = omega^2 M v (M, K symmetric positive definite),
    each to about the working precision of its own size.

    ``_undamped_eigenvalues(M, K)`` resolves each eigenvalue to the precision of the largest:
    with many modes (stiffness growing as lambda^4, 1e10 between the first of 100 and the
    last) the first modes' frequencies came out 13 % off in float32. The inverse problem,
    ``M v = (1 / omega^2) K v``, resolves the low modes instead. Each mode takes the problem
    that resolves it: the inverse one below the geometric mean of the extreme eigenvalues,
    where its relative error is at most eps times the ratio of the extreme frequencies.
    """
    direct = _undamped_eigenvalues(M, K)
    inverse = 1.0 / _undamped_eigenvalues(K, M)[::-1]
    return jnp.where(inverse < jnp.sqrt(inverse[0] * direct[-1]), inverse, direct)


def _flexible_omegas(M: jax.Array, K: jax.Array) -> jax.Array:
    """[n] flexible natural frequencies (rad/s) of the free hub. The hub angle carries no
    stiffness (``K[0]`` is zero), so for omega > 0 its equation gives it from the modal
    coordinates, and condensing it out leaves ``K_ff q = omega^2 (M_ff - M_f0 M_0f / M_00) q``,
    without the rigid-body zero."""
    reduced_mass = M[1:, 1:] - jnp.outer(M[1:, 0], M[0, 1:]) / M[0, 0]
    return jnp.sqrt(_natural_omegas_sq(reduced_mass, K[1:, 1:]))


def rayleigh_coefficients(params: BeamParams) -> tuple[jax.Array, jax.Array]:
    """Rayleigh (alpha, beta) of these parameters.

    When ``params.rayleigh_alpha`` and ``rayleigh_beta`` are set they are returned.
    Otherwise both flexible modes of the 2-mode model get ``damping_ratio`` z:
    ``alpha = 2 z w1 w2 / (w1 + w2)``, ``beta = 2 z / (w1 + w2)``. The same numbers are used
    whatever number of modes the simulated model has.
    """
    if params.rayleigh_alpha is not None:
        return jnp.asarray(params.rayleigh_alpha), jnp.asarray(params.rayleigh_beta)
    M, K, *_ = _structural(params, 2)
    w1, w2 = _flexible_omegas(M, K)
    z = params.damping_ratio
    return 2.0 * z * w1 * w2 / (w1 + w2), 2.0 * z / (w1 + w2)


def modal_damping_ratios(params: BeamParams, freqs_hz: ArrayLike) -> jax.Array:
    """Each flexible mode's damping ratio under ``alpha M + beta K``
    (:func:`rayleigh_coefficients`): ``alpha / (2 w) + beta w / 2`` at ``w = 2 pi f``, for the
    model's ``freqs_hz`` (:func:`natural_frequencies_hz`). ``damping_ratio`` is that of the
    2-mode model, so with other n_modes the modes run with other ratios.

    Raises:
      ValueError: naming ``params`` fields out of range (``check_beam_params``), or concrete
        ``freqs_hz`` that are not finite numbers > 0 (Hz).
    """
    check_beam_params(params)
    if not isinstance(freqs_hz, jax.core.Tracer):
        f = checks.real_array("freqs_hz", freqs_hz)
        if not np.all(np.isfinite(f) & (f > 0)):
            raise ValueError(f"freqs_hz must be finite frequencies > 0 (Hz), the model's natural_frequencies_hz; got {f.tolist()}")
    alpha, beta = rayleigh_coefficients(params)
    omega = 2 * jnp.pi * jnp.asarray(freqs_hz)
    return alpha / (2 * omega) + beta * omega / 2


def modal_matrices(params: BeamParams, n_modes: int = 2) -> ModalMatrices:
    """Mass, stiffness and Rayleigh damping matrices of the n-mode model (closed form).

    Args:
      params: physical constants.
      n_modes: number of clamped-free assumed modes (static Python int >= 1).

    Returns:
      ModalMatrices with [n+1, n+1] matrices and [n+1] input/output maps.

    Raises:
      ValueError: naming a field not representable in the matrices' dtype
        (``check_beam_params(representable=True)``), or the arm when, concrete, its matrices
        are not finite there (a 1e-30 m thick arm gave inf and 0 entries).
    """
    n_modes = check_n_modes(n_modes)
    check_beam_params(params, representable=True)
    M, K, torque_input, tip_force_input, tip_deflection = _structural(params, n_modes)
    alpha, beta = rayleigh_coefficients(params)
    D = alpha * M + beta * K
    matrices = ModalMatrices(M, K, D, torque_input, tip_force_input, tip_deflection)
    if not any(isinstance(m, jax.core.Tracer) for m in matrices) and not (
        all(np.all(np.isfinite(np.asarray(m))) for m in matrices) and np.all(np.diag(np.asarray(K))[1:] > 0)
    ):
        raise ValueError(f"the {n_modes}-mode model's matrices must be finite, with each flexible mode's stiffness > 0, in {M.dtype}; "
                         f"got inf, NaN or 0 for {params} (check the units, or compute in float64 with jax_enable_x64, --x64)")
    return matrices


HUBS = ("free", "clamped")


def check_hub(hub: str) -> str:
    """``hub`` must name one of ``HUBS``."""
    if hub not in HUBS:
        raise ValueError(f"hub must be one of {HUBS}; got {hub!r}")
    return hub


def natural_frequencies_hz(params: BeamParams, n_modes: int = 2, hub: str = "free") -> jax.Array:
    """[n] undamped flexible natural frequencies (Hz) of the n-mode model, ascending.

    Args:
      params: physical constants.
      n_modes: number of clamped-free assumed modes (static Python int >= 1).
      hub: ``"free"`` (no torque on the hub, the arm as simulated open loop; the rigid-body
        mode at 0 Hz is excluded) or ``"clamped"`` (the hub held still, as by a stiff
        position servo: the cantilever's frequencies, from the flexible block of ``M`` and
        ``K``; without a payload they are exact, since the assumed modes are the
        cantilever's own).
    """
    n_modes = check_n_modes(n_modes)
    check_hub(hub)
    check_beam_params(params, representable=True)  # 1e39 N/m^2 is inf in float32: NaN frequencies
    M, K, *_ = _structural(params, n_modes)
    omegas = jnp.sqrt(_natural_omegas_sq(M[1:, 1:], K[1:, 1:])) if hub == "clamped" else _flexible_omegas(M, K)
    if not isinstance(omegas, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(omegas))):
        raise ValueError(f"the natural frequencies of the {n_modes}-mode model must be finite in {omegas.dtype}; got inf or NaN for {params} "
                         "(check the units, or compute in float64 with jax_enable_x64, --x64)")
    return omegas / (2.0 * jnp.pi)


def _exact_determinant(lam: float, mu: float, j: float, r: float) -> float:
    """Determinant of the boundary conditions of the hub-beam-payload frequency equation.

    ``Y = c1 cos(l s) + c2 sin(l s) + c3 e^(-l s) + c4 e^(-l (1 - s))`` along the beam
    (s = x / L, l = lambda), with Y(0) = 0, EI Y''(0) = -I_H w^2 Y'(0),
    EI Y''(L) = J_p w^2 Y'(L), EI Y'''(L) = -m_p w^2 Y(L); mu = I_H / (rho A L^3),
    j = J_p / (rho A L^3), r = m_p / (rho A L). Each derivative in s is divided by l. Every
    basis function and derivative is then O(1) on [0, 1], and so are the rows at any lambda
    (with cosh and sinh, scaled by e^-lambda, the rows cancelled to round-off from about the
    twelfth mode on, and the roots found there were spurious). The hub row
    ``D2 + mu l^3 D1`` is not O(1) at a heavy hub (mu l^3 up to 1e13, where elimination
    through it wiped out the tip rows): the determinant is affine in that row, so it is the
    weighted sum of the determinants with ``D2`` and ``D1``, each O(1), divided by
    ``1 + mu l^3 > 0`` (same zeros and signs).
    """
    s, c, e = math.sin(lam), math.cos(lam), math.exp(-lam)
    l3 = lam**3
    at_zero = [1.0, 0.0, 1.0, e]  # Y(0) = 0
    tip_inertia = [-c + j * l3 * s, -s - j * l3 * c, e * (1.0 + j * l3), 1.0 - j * l3]  # D2 - j l^3 D1 at 1
    tip_mass = [s + r * lam * c, -c + r * lam * s, e * (r * lam - 1.0), 1.0 + r * lam]  # D3 + r l D0 at 1
    free, clamped = (float(np.linalg.det(np.array([at_zero, hub, tip_inertia, tip_mass]))) for hub in ([-1.0, 0.0, 1.0, e], [0.0, 1.0, -1.0, e]))
    weight = mu * l3
    return (free + weight * clamped) / (1.0 + weight)


def exact_natural_frequencies_hz(params: BeamParams, n_freqs: int = 2) -> np.ndarray:
    """The first flexible frequencies (Hz) of the continuous hub-beam(-payload) system.

    Roots of the exact frequency equation of the Euler-Bernoulli beam clamped to a free
    hub (see ``_exact_determinant``), found by a sign-change scan in lambda = beta L and
    bisection, in NumPy float64. Not differentiable: it is the reference that the
    assumed-mode frequencies converge to from above as n grows (slowly with a tip rotary
    inertia: see ``BeamParams.payload_inertia_kg_m2``).

    Raises:
      ValueError: naming ``n_freqs`` out of [1, ``MAX_MODES``], a field out of its range
        (``check_beam_params``), or ``params`` when the arm's scales or frequencies are not
        finite and > 0 in float64 (an extreme arm, 1e-200 or 1e200 m long), or its roots are
        beyond the scan.
    """
    n_freqs = checks.integer("n_freqs", n_freqs, high=MAX_MODES)
    check_beam_params(params)
    # NumPy scalars: an extreme arm overflows its own scales in float64, which with Python
    # floats raised a ZeroDivisionError (1e-200 m long) or an OverflowError (1e200 m)
    p = {name: np.float64(np.asarray(getattr(params, name))) for name in _POSITIVE_FIELDS + _NONNEGATIVE_FIELDS}
    length = p["length_m"]
    with np.errstate(all="ignore"):
        rho_a = p["density_kg_m3"] * p["width_m"] * p["thickness_m"]
        e_i = p["youngs_modulus_pa"] * p["width_m"] * p["thickness_m"] ** 3 / 12.0
        rho_a_l3 = rho_a * length**3
        mu, j, r = p["hub_inertia_kg_m2"] / rho_a_l3, p["payload_inertia_kg_m2"] / rho_a_l3, p["payload_mass_kg"] / (rho_a * length)
        scale = e_i / rho_a
    if not (np.all(np.isfinite([mu, j, r, rho_a_l3, scale])) and rho_a_l3 > 0 and scale > 0):
        raise ValueError(f"params: the arm's frequency equation must be finite in float64, its scales > 0; got hub and payload ratios {mu:g}, {j:g}, {r:g}, "
                         f"rho A L^3 = {rho_a_l3:g} kg m^2 and EI / (rho A) = {scale:g} m^4/s^2 for {params} (check the units)")
    mu, j, r = float(mu), float(j), float(r)

    def f(lam: float) -> float:
        return _exact_determinant(lam, mu, j, r)

    roots: list[float] = []
    grid = np.arange(0.05, (n_freqs + 2) * math.pi + 1.0, 0.01)
    values = [f(x) for x in grid]
    for a, b, fa, fb in zip(grid[:-1], grid[1:], values[:-1], values[1:]):
        if fa == 0.0 or fa * fb < 0:
            lo, hi, flo = a, b, fa
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                fm = f(mid)
                if flo * fm <= 0:
                    hi = mid
                else:
                    lo, flo = mid, fm
                if hi - lo < 1e-14 * hi:
                    break
            roots.append(0.5 * (lo + hi))
            if len(roots) == n_freqs:
                break
    if len(roots) < n_freqs:
        raise ValueError(f"params: the scan found {len(roots)} of the {n_freqs} frequencies asked for (n_freqs) in lambda = beta L up to {grid[-1]:.4g} "
                         f"for {params}: the hub and payload ratios {mu:g}, {j:g}, {r:g} are beyond what it resolves")
    lam = np.array(roots)
    with np.errstate(under="ignore"):
        freqs = lam**2 / length**2 * math.sqrt(scale) / (2 * math.pi)
    if not np.all(freqs > 0):  # underflowed: 1e100 m long and 1e-300 N/m^2
        raise ValueError(f"params: the arm's frequencies must be > 0 in float64; got {freqs} Hz for {params} (check the units)")
    return freqs
