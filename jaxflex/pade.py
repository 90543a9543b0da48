"""Pade approximants of a pure delay ``e^{-s tau}`` as a well-conditioned state space.

The ``[N/N]`` Pade approximant of ``e^{-x}`` (``x = s tau``) is ``D(-x) / D(x)`` with the
monic denominator

    D(x) = sum_k a_k x^k,   a_k = (2N - k)! / (k! (N - k)!)   (integers; a_N = 1),

a scaled reverse Bessel polynomial (``D(x) = 2^N theta_N(x / 2)``). Its roots ``-p_i`` lie in
the open left half plane, and ``D(-x) = (-1)^N prod_i (x - p_i)``, so the approximant is the
all-pass product

    H(s) = prod_i (p_i - s tau) / (p_i + s tau),   Re p_i > 0,

(``|H(j w)| = 1`` at every frequency, ``H(0) = 1``) with one real ``p_i`` when N is odd and
complex pairs otherwise.

Realisation. ``control.pade(tau, N)`` returns polynomial coefficients, which for
``tau = 5 ms`` and N = 8 span 27 decades, and ``control.tf2ss`` turns them into a companion
form whose ``A`` has entries up to 1e27 (condition number 1e27). Its transfer function is
still accurate in float64, but ``jax.scipy.linalg.expm`` (at most 16 squarings) returns NaN
for it from N = 3 on (see ``tests/test_pade.py``). scipy 1.17's ``expm`` samples it with
3e-5 relative error in the poles at N = 8, and the sampled N = 12 filter is unstable; scipy
1.18 is accurate at N = 8 (not checked at N = 12). Here the poles are computed once per order
(NumPy, cached) and each real pole or complex pair becomes a *balanced* all-pass section
(controllability and observability Gramians equal to the identity):

* real ``p``: ``A = -p, B = sqrt(2 p), C = sqrt(2 p), D = -1``;
* pair ``a +- j b``: ``A = [[-2 a, |p|], [-|p|, 0]], B = [2 sqrt(a), 0]^T,
  C = [-2 sqrt(a), 0], D = 1``.

The sections are chained in cascade (block lower-triangular ``A``); the chain stays balanced,
its entries are at most about ``5.4 N / tau`` and ``cond(A)`` is 59 at N = 8, 130 at N = 12,
3e3 at N = 60. With ``tau`` traced the state space is ``(A_1 / tau, B_1 / tau, C_1, D_1)``
with ``(A_1, B_1, C_1, D_1)`` the ``tau = 1`` matrices: differentiable in ``tau``, and a new
``tau`` never recompiles.

Poles. The roots of ``D`` are ill-conditioned functions of its coefficients: the eigenvalues
of its (scaled) companion matrix, as ``np.roots`` computes them, have relative errors of
1e-12 at N = 8, 2e-10 at N = 12, 1e-5 at N = 20, and are wrong at N = 30. They are started
here from the eigenvalues of the tridiagonal matrix of the Bessel three-term recurrence
(better, but still 5e-8 at N = 20) and refined by Aberth-Ehrlich iterations whose Newton
ratio ``D(z) / D'(z)`` is evaluated in exact integer arithmetic and rounded once. The poles
are then correct to float64 round-off (relative error about 1e-16, checked in the tests with
exact rational arithmetic) for every order tried up to N = 100, at a one-off cost of about
1 ms for N <= 12, 0.1 s at N = 30 and a few seconds at N = 100.

Cost and accuracy (``dt`` the loop's sample time):

* State: N states. Once per ``tau``: one ``expm`` of an ``(N + 1)``- or ``(N + 2)``-square
  matrix and one N-square solve (``sampled_delay``). Per step: ``N^2 + 2 N + 1``
  multiply-adds (a dense ``Ad @ xi``), whatever ``tau``; no buffer, no upper limit on tau.
* Continuous-time accuracy: magnitude exact (all-pass). The phase error is
  ``(N!)^2 / ((2N)! (2N + 1)!) (w tau)^(2N + 1)`` to leading order: at ``w tau = 1`` it is
  7.3e-2 rad (N = 1), 1.3e-3 (N = 2), 3.8e-8 (N = 4), 2e-19 (N = 8); the phase stays within
  0.01 rad of the delay up to ``w tau`` = 0.50 (N = 1), 1.5 (N = 2), 4.2 (N = 4), 10.6
  (N = 8), 17.5 (N = 12), 31.9 (N = 20).
* Sampled accuracy. The filter sees a continuous-time input built from the samples:
  ``"zoh"`` holds each sample (a staircase), ``"foh"`` joins consecutive samples by straight
  lines (causal: the response at ``k dt`` needs samples up to ``k`` only). The all-pass
  filter passes every jump of the staircase straight through its feedthrough
  ``D = (-1)^N``, so with ``"zoh"`` the output at the sample instants is off by about
  ``|u[k] - u[k-1]|`` whatever N (at 14 Hz and ``dt = 1 ms``: 3e-2 to 9e-2 relative to the
  exact ``z^-5``, for N = 1..40), and the DFS loop does not converge to the buffer (over
  3 s of the paper scenario it even diverges for tau = 5.3 ms, N >= 16). With ``"foh"`` it converges to the linear
  interpolation of the samples, i.e. to the ``"linear"`` ring-buffer read: at 14 Hz,
  6.7e-3 (N = 1), 2.9e-4 (N = 2), then a plateau of 3e-4 to 8e-4 for N = 4..12 from the
  interpolant's spectral images at ``w tau = 2 pi tau / dt`` (31 for tau = 5 ms), which only
  orders above about 16 follow (2.5e-4 at N = 20, 1.3e-4 at N = 40).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import checks
from jaxflex.controllers.base import is_concrete
from jaxflex.plant import check_dt

_ABERTH_MAX_ITERS = 200
_ABERTH_RTOL = 4 * np.finfo(np.float64).eps  # stop once no root moves by more than this (relative)


class PadeSS(NamedTuple):
    """Continuous-time Pade delay ``xi' = A xi + B u``, ``u_delayed = C xi + D u``.

    Attributes:
      A: [N, N] (1/s); B: [N, 1] (1/s); C: [1, N]; D: [1, 1] (``(-1)^N``).
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array
    D: jax.Array


class PadeDiscrete(NamedTuple):
    """The Pade delay sampled at ``dt`` (``discretize_pade``).

    ``xi[k+1] = Ad xi[k] + Bd u[k]``, ``u_delayed[k] = C xi[k] + D u[k]``.

    Attributes:
      Ad: [N, N]; Bd: [N, 1]; C: [1, N]; D: [1, 1].
    """

    Ad: jax.Array
    Bd: jax.Array
    C: jax.Array
    D: jax.Array


HOLDS = ("foh", "zoh")


MAX_ORDER = 100
"""The highest order whose poles are checked (and found in a few seconds); higher ones take
minutes (21 s at 150) and gain nothing a sampled loop can use."""


def check_order(order: int, name: str = "order") -> int:
    """The order sets array shapes, so it must be an integer in [1, ``MAX_ORDER``] (returned
    as an int; ``name`` is the caller's argument)."""
    return checks.integer(name, order, high=MAX_ORDER)


def _monic_denominator(order: int) -> list[int]:
    """Exact coefficients ``a_k`` (of ``x^k``, k = 0..N) of the monic denominator."""
    n = order
    return [math.factorial(2 * n - k) // (math.factorial(k) * math.factorial(n - k)) for k in range(n + 1)]


def pade_coefficients(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of the ``[N/N]`` Pade approximant of ``e^{-s}`` (tau = 1).

    Highest power first and the denominator monic, as ``control.pade(1.0, order)``; here
    every coefficient is the float64 rounding of an exact integer.

    Returns:
      num: [N + 1] numerator ``D(-s)``; den: [N + 1] denominator ``D(s)``.
    """
    a = _monic_denominator(check_order(order))
    den = np.array([float(c) for c in a[::-1]])
    num = np.array([float(c) * (-1.0) ** k for k, c in enumerate(a)][::-1])
    return num, den


def _newton_ratio(a: list[int], z: complex) -> complex:
    """``p(z) / p'(z)`` for the integer polynomial ``sum_k a[k] x^k``, exact, rounded once.

    ``z`` is a pair of binary floats, so ``z = (zr + j zi) / 2^e`` with integers zr, zi and
    Horner's scheme runs in (big) integers; Python's int / int division rounds correctly.
    """
    n = len(a) - 1
    nr, dr = z.real.as_integer_ratio()
    ni, di = z.imag.as_integer_ratio()
    e = max(dr.bit_length(), di.bit_length()) - 1  # both denominators are powers of two
    zr, zi = (nr << e) // dr, (ni << e) // di
    pr, pi_ = a[n], 0  # p(z) 2^(e n)
    qr, qi = n * a[n], 0  # p'(z) 2^(e (n - 1))
    for k in range(n - 1, -1, -1):
        pr, pi_ = pr * zr - pi_ * zi + (a[k] << (e * (n - k))), pr * zi + pi_ * zr
        if k >= 1:
            qr, qi = qr * zr - qi * zi + ((k * a[k]) << (e * (n - k))), qr * zi + qi * zr
    den = (qr * qr + qi * qi) << e
    if den == 0:  # z is a multiple root: cannot happen for these polynomials
        return 0j
    return complex((pr * qr + pi_ * qi) / den, (pi_ * qr - pr * qi) / den)


@functools.lru_cache(maxsize=None)
def _poles(order: int) -> np.ndarray:
    """The N poles ``p_i`` (Re > 0) of the tau = 1 approximant: ``D(-p_i) = 0``."""
    n = order
    # Start: Bessel polynomials y_m(z) = (2m - 1) z y_{m-1}(z) + y_{m-2}(z), y_{-1} = y_0 = 1,
    # so the zeros of y_N are the eigenvalues of a tridiagonal matrix, and D(2 / z) = 0.
    rec = np.diag(np.ones(n - 1), 1) - np.diag(np.ones(n - 1), -1)
    rec[0, 0] = -1.0
    zeta = np.linalg.eigvals(rec / np.arange(1, 2 * n, 2, dtype=float)[:, None])
    roots = 2.0 / zeta.astype(complex)
    a = _monic_denominator(n)
    for _ in range(_ABERTH_MAX_ITERS):
        ratio = np.array([_newton_ratio(a, complex(z)) for z in roots])
        diff = roots[:, None] - roots[None, :]
        np.fill_diagonal(diff, np.inf)
        step = ratio / (1.0 - ratio * np.sum(1.0 / diff, axis=1))
        roots = roots - step
        if np.all(np.abs(step) <= _ABERTH_RTOL * np.abs(roots)):
            break
    else:  # pragma: no cover - never seen for N <= 100
        raise RuntimeError(f"Pade poles of order {n} did not converge")
    poles = -roots
    # D has real coefficients: exactly N mod 2 real roots (reverse Bessel polynomials),
    # the rest in conjugate pairs. Snap them so the sections below are exactly real.
    poles = poles[np.argsort(np.abs(poles.imag))]
    n_real = n % 2
    poles[:n_real] = poles[:n_real].real
    return poles


@functools.lru_cache(maxsize=None)
def _unit_realisation(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Balanced all-pass sections in cascade for tau = 1 (see the module docstring)."""
    poles = _poles(order)
    n_real = order % 2
    sections = []
    for p in poles[:n_real].real:
        r = np.sqrt(2.0 * p)
        sections.append((np.array([[-p]]), np.array([[r]]), np.array([[r]]), np.array([[-1.0]])))
    pairs = poles[n_real:]
    pairs = pairs[pairs.imag > 0]
    if pairs.shape[0] != order // 2:  # pragma: no cover - conjugate pairs are well separated
        raise RuntimeError(f"Pade poles of order {order}: expected {order // 2} conjugate pairs")
    for p in pairs[np.argsort(np.abs(pairs))]:
        a, m = p.real, abs(p)
        g = 2.0 * np.sqrt(a)
        sections.append((np.array([[-2.0 * a, m], [-m, 0.0]]), np.array([[g], [0.0]]), np.array([[-g, 0.0]]), np.array([[1.0]])))
    A, B, C, D = sections[0]
    for A2, B2, C2, D2 in sections[1:]:
        # u -> (A, B, C, D) -> (A2, B2, C2, D2) -> y
        A = np.block([[A, np.zeros((A.shape[0], A2.shape[0]))], [B2 @ C, A2]])
        B = np.concatenate([B, B2 @ D])
        C = np.concatenate([D2 @ C, C2], axis=1)
        D = D2 @ D
    return A, B, C, D


def pade_state_space(tau_s: ArrayLike, order: int) -> PadeSS:
    """The ``[N/N]`` Pade approximant of ``e^{-s tau}`` as a balanced cascade state space.

    Args:
      tau_s: shape () delay (s), > 0; may be traced (the result is differentiable in it).
      order: N, a Python int >= 1 (static: it sets the state size).

    Returns:
      PadeSS with ``A = A_1 / tau``, ``B = B_1 / tau``, ``C = C_1``, ``D = D_1`` in the dtype
      of ``tau_s`` (float64 for a Python float under ``jax_enable_x64``).
    """
    A1, B1, C1, D1 = _unit_realisation(check_order(order))
    if is_concrete(tau_s):
        checks.real_array("tau_s", tau_s, scalar=True)
    tau = jnp.asarray(tau_s)
    if tau.ndim != 0:
        raise ValueError(f"tau_s must be a scalar; got shape {tau.shape}")
    if not jnp.issubdtype(tau.dtype, jnp.floating):
        tau = tau.astype(jnp.result_type(float))
    if is_concrete(tau) and not (math.isfinite(float(tau)) and float(tau) > 0):
        raise ValueError(f"tau_s must be a finite delay > 0 (s); got {float(tau)!r}")
    dtype = tau.dtype
    return PadeSS(jnp.asarray(A1, dtype) / tau, jnp.asarray(B1, dtype) / tau, jnp.asarray(C1, dtype), jnp.asarray(D1, dtype))


def _hold_integrals(ss: PadeSS, dt: ArrayLike, hold: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``Phi = e^{A dt}``, ``G1 = int_0^dt e^{A s} ds B`` and, for ``"foh"``,
    ``G2 = int_0^dt e^{A (dt - s)} B s / dt ds`` (zeros for ``"zoh"``), from one ``expm``."""
    check_dt(dt)
    if hold not in HOLDS:
        raise ValueError(f"hold must be one of {HOLDS}; got {hold!r}")
    n = ss.A.shape[0]
    dtype = ss.A.dtype
    dt = jnp.asarray(dt, dtype)
    # ||A dt|| grows as N dt / tau: a delay far below dt needs more than expm's default 16
    # squarings (NaN from tau ~ 1e-7 s at N = 8, dt = 1 ms). 64 covers any positive float tau.
    expm = functools.partial(jax.scipy.linalg.expm, max_squarings=64)
    if hold == "zoh":
        block = jnp.zeros((n + 1, n + 1), dtype).at[:n, :n].set(ss.A * dt).at[:n, n:].set(ss.B * dt)
        phi = expm(block)
        return phi[:n, :n], phi[:n, n:], jnp.zeros((n, 1), dtype)
    # u(s) = u0 + (u1 - u0) s / dt: augment with u and its (scaled) slope.
    block = jnp.zeros((n + 2, n + 2), dtype).at[:n, :n].set(ss.A * dt).at[:n, n : n + 1].set(ss.B * dt).at[n, n + 1].set(1.0)
    phi = expm(block)
    return phi[:n, :n], phi[:n, n : n + 1], phi[:n, n + 1 :]


def _sample(ss: PadeSS, dt: ArrayLike, hold: str) -> tuple[PadeDiscrete, jax.Array]:
    phi, g1, g2 = _hold_integrals(ss, dt, hold)
    if hold == "zoh":
        return PadeDiscrete(phi, g1, ss.C, ss.D), g2
    return PadeDiscrete(phi, g1 - g2 + phi @ g2, ss.C, ss.D + ss.C @ g2), g2


def discretize_pade(ss: PadeSS, dt: ArrayLike, hold: str = "foh") -> PadeDiscrete:
    """Sample the Pade delay exactly for an input held or interpolated between samples.

    ``"zoh"``: the input is held over each sample; ``(Ad, Bd)`` are blocks of
    ``expm([[A, B], [0, 0]] dt)`` (as :mod:`jaxflex.plant`) and ``C, D`` are unchanged.

    ``"foh"``: the input is the straight line through consecutive samples (triangle hold,
    python-control's and scipy's ``"foh"``); the response at ``k dt`` needs the samples up
    to ``u[k]`` only, so it is causal. With ``Phi, G1, G2`` from
    ``expm([[A dt, B dt, 0], [0, 0, 1], [0, 0, 0]])`` the state
    ``xi[k] = x(k dt) - G2 u[k]`` gives ``Ad = Phi``, ``Bd = G1 - G2 + Phi G2``, ``C``,
    ``D + C G2``.

    Args:
      ss: continuous Pade delay (``pade_state_space``); may be traced.
      dt: sample time (s), finite and > 0.
      hold: ``"foh"`` (default, as :func:`sampled_delay` and ``dfs``: it converges to the
        delay as the order grows) or ``"zoh"``.
    """
    checks.instance("ss", ss, PadeSS, "build one with pade_state_space(tau_s, order)")
    return _sample(ss, dt, hold)[0]


def steady_state(ss: PadeSS, u0: jax.Array) -> jax.Array:
    """[N] continuous filter state for an input held at ``u0`` [1] forever: ``A x = -B u0``.

    Its output is then ``u0`` (unit DC gain): a history equal to ``u0`` before t = 0.
    """
    return jnp.linalg.solve(ss.A, -(ss.B @ u0))


def sampled_delay(tau_s: ArrayLike, order: int, dt: ArrayLike, u0: jax.Array, hold: str = "foh") -> tuple[PadeDiscrete, jax.Array]:
    """The sampled Pade delay and its state for an input equal to ``u0`` [1] before t = 0.

    The initial state is the continuous steady state (``A x = -B u0``), moved to the
    sampled coordinates (``xi = x - G2 u0`` for ``"foh"``), so the outputs are exactly
    ``u0`` while the input stays at ``u0``. Cost, once per ``tau``: one ``expm`` of an
    ``(N + 1)``-square (zoh) or ``(N + 2)``-square (foh) matrix and one ``N``-square solve.

    Args:
      tau_s: shape () delay (s), > 0; may be traced.
      order: N (Python int >= 1).
      dt: sample time (s).
      u0: [1] input before t = 0 ([1, B] for a batch of B lines, as a batched rollout's).
      hold: ``"foh"`` or ``"zoh"`` (see ``discretize_pade``).

    Returns:
      (PadeDiscrete, xi0 [N]).
    """
    ss = pade_state_space(tau_s, order)
    if jnp.ndim(u0) not in (1, 2) or jnp.shape(u0)[0] != 1:
        raise ValueError(f"u0 must have shape (1,), or (1, B) for a batch (the input before t = 0); got shape {jnp.shape(u0)}")
    filt, g2 = _sample(ss, dt, hold)
    u0 = jnp.asarray(u0, ss.A.dtype)
    return filt, steady_state(ss, u0) - g2 @ u0
