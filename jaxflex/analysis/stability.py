"""Stability of the delayed-feedback-signal (DFS) loop ``u = -k (theta(t) - theta(t - tau))``.

Three views of the same loop on the n-mode plant ``x' = A x + b u``, ``theta = c x``
(``b = B[:, 0]``, ``c = C[0]``, only the hub angle is fed back):

1. **Critical delays** (the paper's method, after Wang and Hu, 2000). The characteristic
   function is ``Delta(s, tau) = det(sI - A + k b c (1 - e^{-s tau}))``. As ``k b c`` has rank
   one, ``Delta`` is affine in ``z = e^{-s tau}`` (matrix determinant lemma):
   ``Delta = P(s) + Q(s) z`` with ``P(s) = det(sI - A + k b c) = a(s) + k N(s)`` (``z = 0``)
   and ``P + Q = det(sI - A) = a(s)`` (``z = 1``), so ``Q(s) = -k N(s)``, where
   ``G(s) = c (sI - A)^{-1} b = N(s) / a(s)`` is the torque-to-hub-angle transfer function.
   A root crosses the imaginary axis at ``s = j w`` only where ``|P(jw)| = |Q(jw)|``; dividing
   by ``|a(jw)|^2``, this is ``1 + 2 k Re G(jw) = 0``. ``F(w) = |P(jw)|^2 - |Q(jw)|^2`` is an
   even real polynomial, a polynomial in ``v = w^2``: its positive roots give every crossing
   frequency, each then polished on the well-conditioned ``1 + 2 k Re G(jw)`` (a dense
   frequency scan backs the polynomial up). With ``e^{-j beta} = -P/Q = 1 + 1 / (k G(jw))``,
   ``beta in [0, 2 pi)``, the critical delays are ``tau_m = (beta + 2 pi m) / w``. The
   direction follows from the implicit function theorem on ``Delta(s, tau) = 0``:
   ``ds/dtau = -Delta_tau / Delta_s``; ``Re ds/dtau > 0`` is *destabilising* (the pair enters
   the right half plane as tau grows), ``< 0`` *stabilising*. Its sign equals that of
   ``F'(w)`` at every ``tau_m`` (Cooke and van den Driessche); the tests check both.

2. **Rightmost characteristic root** of the delay equation ``x' = A0 x(t) + A1 x(t - tau)``,
   ``A0 = A - k b c``, ``A1 = k b c``, by Chebyshev collocation of its infinitesimal generator
   (Breda, Maset and Vermiglio, 2005): the history on ``[-tau, 0]`` is represented at ``M + 1``
   Chebyshev points; the eigenvalues of the resulting matrix converge spectrally
   (geometrically in M) to the characteristic roots of largest real part. Only theta is
   delayed, so the history of theta alone is kept: ``n_x + M`` instead of ``n_x (M + 1)``
   (see :func:`generator_matrix`).

3. **Sampled loop.** jaxflex's rollout holds ``u_k = -k (theta_k - theta_{k-d})``,
   ``d = tau / dt``, over each sample, with the history before t = 0 equal to theta(0). With
   the augmented state ``xi_k = [x_k, theta_{k-1}, ..., theta_{k-d}]`` the loop is exactly
   ``xi_{k+1} = L(k, d) xi_k``: ``x_{k+1} = (Ad - k Bd c) x_k + k Bd theta_{k-d}``,
   ``theta`` pushed into the history. Its spectral radius (structural eigenvalue excluded)
   is < 1 exactly when the sampled loop is asymptotically stable.

**The structural root.** DFS feeds back a difference of angles, so it has no position action:
any constant hub angle is an equilibrium. With the free hub, ``A v = 0`` for ``v = e_0``
(only theta nonzero), and then ``s = 0`` is a root of ``Delta(s, tau)`` for every ``k`` and
``tau`` (``Delta(0, tau) = det(-A) = 0``), the generator has the eigenvector ``[v, ..., v]``
with eigenvalue 0, and ``L(k, d)`` has ``[v, c v, ..., c v]`` with eigenvalue 1 (``Ad v = v``).
These are excluded from every stability statement by an exact orthogonal deflation: with
``[Q1 Q2]`` orthonormal and ``Q1`` spanning the known eigenvector(s), ``Q2^T L Q2`` has the
spectrum of ``L`` minus one copy of the structural eigenvalue per direction. Deflating by
the eigenvector, not by dropping eigenvalues within a tolerance of 1 (or 0), matters: the
rigid-body mode has a second root near 0 (``-alpha`` open loop, ``alpha`` the Rayleigh
mass coefficient, about ``1 - alpha dt`` sampled; DFS moves it to ``-(alpha + k tau / J)``
to first order in ``k tau``, J the arm's whole inertia about the hub: -1.47 /s at k = 10,
tau = 1 ms on the paper's arm, and -7.99 against the root's -9.34 at k = 55, tau = 5 ms), which a tolerance would wrongly drop for small ``k tau``; and
for ``k N(0) < 0`` (the wrong sign of k) that root passes *through* 0 at
``tau_0 = -a'(0) / (k N(0))``, where ``s = 0`` becomes double (a Jordan block at 1 in the
sampled loop). There the deflated matrix keeps the second copy, so the loop is correctly
reported marginal, and :func:`critical_delays` reports that real crossing (``zero_crossing``).
For k > 0 on the paper's arm ``tau_0 < 0`` and the root at 0 stays simple.

Everything here is NumPy float64 (the crossings) or ``jax.numpy`` taking its dtype from the
plant (the generator and the sampled loop: jittable and vmappable over k and tau; the
sampled radius is differentiable in k). Analyse in float64.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.optimize
from jax.typing import ArrayLike

from jaxflex import beam, checks, pade
from jaxflex.controllers.base import check_finite_scalar
from jaxflex.delay import whole_samples
from jaxflex.plant import DiscretePlant, LinearPlant, check_continuous, check_plant, check_sampled, discretize, make_plant, n_modes_of

_NULL_RTOL = 1e3  # x n_x eps x largest singular value: rank tolerance for the structural null space
_ROOT_IMAG_RTOL = 1e-6  # a root v of F is real when |Im v| <= this x |v| (before polishing on 1 + 2k Re G)
_SCAN_POINTS_PER_DECADE = 2000  # backup frequency scan: resolves resonances with damping ratio >~ 1e-3
_DEDUP_RTOL = 1e-7  # two polished crossing frequencies closer than this (relative) are the same one
_MAX_CRITICAL_DELAYS = 1_000_000  # per crossing frequency; beyond, |k| or tau_max is far outside the arm's range
DEFAULT_N_CHEB = 32  # Chebyshev intervals of the generator: on the 2-mode arm the rightmost root is converged to ~1e-11 rad/s for tau <= 40 ms, k <= 120
# rightmost_root_converged doubles the intervals until two successive roots agree to
# ROOT_RTOL x (1 + |root|): a delay of many periods of a stiff arm's modes needs more than 32
# (a 0.3 m arm at tau = 0.16 s: Re 8.79 /s at 32 intervals, 11.25 /s from 64 on)
ROOT_RTOL = 1e-8
MAX_N_CHEB = 1024


# ----------------------------------------------------------------------------------------------
# Validation


def check_gain(k: ArrayLike) -> float:
    """``k`` must be a finite scalar (N*m/rad); returns it as a float."""
    return check_finite_scalar("k", k)


def check_delay(tau_s: ArrayLike) -> float:
    """``tau_s`` must be a finite scalar > 0 (s)."""
    return check_finite_scalar("tau_s", tau_s, positive=True)


def delay_steps_of(tau_s: ArrayLike, dt: ArrayLike) -> int:
    """The delay as a whole number of samples ``d = tau_s / dt >= 1``.

    Raises:
      ValueError: when tau_s is not finite and > 0, dt is not finite and > 0, or tau_s is not
        a whole number of samples of dt (the sampled loop and the rollout's ``"nearest"``
        delay line need one).
    """
    tau = check_delay(tau_s)
    step = check_finite_scalar("dt", dt, positive=True)
    steps = tau / step
    if not whole_samples(steps) or round(steps) < 1:
        near = sorted({max(1, math.floor(steps)), max(1, math.ceil(steps))}) if math.isfinite(steps) else []
        nearest = f": the nearest {'are' if len(near) == 2 else 'is'} {' and '.join(f'{n * step:g} s' for n in near)}" if near else ""
        raise ValueError(f"tau_s must be a whole number >= 1 of samples of dt = {step:g} s; got {tau:g} s ({steps:g} samples){nearest}")
    return int(round(steps))


def _check_gain_and_delay(k: ArrayLike, tau_s: ArrayLike) -> None:
    """``check_gain`` and ``check_delay`` of whichever is concrete (traced ones: vmap, jit)."""
    if not isinstance(k, jax.core.Tracer):
        check_gain(k)
    if not isinstance(tau_s, jax.core.Tracer):
        check_delay(tau_s)


MAX_HISTORY = 2048
"""The longest delay history of the sampled loop (samples): its matrix has ``n_x + n_hist``
rows, and the eigenvalues of one took 4.2 s at 2,000 on the 2-core machine, growing as the
cube (10^6 aborted the process)."""


def _check_delay_steps(delay_steps: int, name: str = "delay_steps") -> int:
    return checks.integer(name, delay_steps, unit="samples", high=MAX_HISTORY)


def _one_plant(plant: Any, check: Callable[[Any], Any]) -> Any:
    """``check(plant)`` (``check_continuous``, ``check_sampled`` or ``check_plant``), and one
    plant, not a batch (whose matrices failed deep inside, or were read as one larger plant)."""
    plant = check(plant)
    matrix = plant.A if isinstance(plant, LinearPlant) else plant.Ad
    if jnp.ndim(matrix) != 2:
        raise ValueError(f"plant must be one plant (a state matrix of shape (n, n)); got a batch, of shape {jnp.shape(matrix)}: analyse its plants one at a time")
    return plant


def _whole_delay(delay_steps: ArrayLike) -> int:
    """A delay of whole samples >= 1 as an int: an integer, or a float within
    ``WHOLE_SAMPLE_RTOL`` of one, as ``tau_s / dt`` gives it (``0.003 / 0.001 =
    2.9999999999999996``); else ValueError naming ``delay_steps`` as given."""
    arr = np.asarray(delay_steps)
    if arr.ndim == 0 and arr.dtype.kind == "f" and np.isfinite(arr) and whole_samples(float(arr)) and round(float(arr)) >= 1:
        return _check_delay_steps(int(round(float(arr))))
    return _check_delay_steps(arr.item() if arr.ndim == 0 and arr.dtype.kind in "iu" else delay_steps)


def _grid_axes(**axes: ArrayLike) -> list[np.ndarray]:
    """The named grid axes as arrays of real numbers, each non-empty and 1-D (else ValueError
    naming them all)."""
    arrays = {name: checks.real_array(name, value) for name, value in axes.items()}
    if any(a.ndim != 1 or a.size < 1 for a in arrays.values()):
        raise ValueError(f"{' and '.join(arrays)} must be non-empty 1-D arrays (the grid's axes); got shapes {', '.join(str(a.shape) for a in arrays.values())}")
    return list(arrays.values())


def _check_n_cheb(n_cheb: int) -> int:
    return checks.integer("n_cheb", n_cheb, 2, unit="Chebyshev intervals")


def _plant_or_default(plant: LinearPlant | None, n_modes: int) -> LinearPlant:
    beam.check_n_modes(n_modes)
    return make_plant(n_modes=n_modes) if plant is None else _one_plant(plant, check_continuous)


# ----------------------------------------------------------------------------------------------
# The loop as seen by DFS: A, b, c and the structural null space


def loop_vectors(plant: LinearPlant | DiscretePlant) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NumPy float64 ``(A, b, c)``: state matrix (``Ad`` for a sampled plant), torque input
    column [n_x] and the measured-angle row ``c = C[0]`` [n_x]."""
    _one_plant(plant, check_plant)
    if isinstance(plant, DiscretePlant):
        A, B = plant.Ad, plant.Bd
    else:
        A, B = plant.A, plant.B
    return np.asarray(A, np.float64), np.asarray(B, np.float64)[:, 0], np.asarray(plant.C, np.float64)[0]


def structural_directions(plant: LinearPlant | DiscretePlant) -> np.ndarray:
    """[n_x, n0] orthonormal basis of the plant's equilibria under DFS.

    For a continuous plant the null space of ``A``; for a sampled plant that of ``Ad - I``
    (the same space: ``Ad = expm(A dt)`` or the RK4 polynomial fixes exactly ``null(A)``).
    On the free-hub arm ``n0 = 1`` and the direction is ``e_0`` (a constant hub angle).
    Rank tolerance: ``_NULL_RTOL * n_x * eps * sigma_max``.
    """
    A, _, _ = loop_vectors(plant)
    if isinstance(plant, DiscretePlant):
        A = A - np.eye(A.shape[0])
    _, sv, vh = np.linalg.svd(A)
    tol = _NULL_RTOL * A.shape[0] * np.finfo(np.float64).eps * max(sv[0], 1.0)
    v = vh[sv <= tol].T.copy()
    for i in range(v.shape[1]):  # sign: largest entry positive (on the arm, v = e_0)
        v[:, i] *= np.sign(v[np.argmax(np.abs(v[:, i])), i])
    return v


def _deflation_basis(r: jax.Array) -> jax.Array:
    """[n, n - n0] orthonormal complement Q2 of the columns of r [n, n0] (complete QR)."""
    q, _ = jnp.linalg.qr(r, mode="complete")
    return q[:, r.shape[1] :]


# ----------------------------------------------------------------------------------------------
# 1. Characteristic quasi-polynomial and critical delays (NumPy float64)


class CharacteristicPolynomials(NamedTuple):
    """``Delta(s, tau) = P(s) + Q(s) e^{-s tau}``; coefficient arrays, highest power first
    (``np.polyval`` order), in s (rad/s).

    Attributes:
      P: [n_x + 1] ``det(sI - A + k b c) = a + k N``.
      Q: [n_x + 1] ``-k N`` (so ``P + Q = a``).
      a: [n_x + 1] open-loop characteristic polynomial ``det(sI - A)`` (monic).
      N: [n_x + 1] numerator of ``G(s) = c (sI - A)^{-1} b = N / a`` (zero-padded).
      k: the gain.
    """

    P: np.ndarray
    Q: np.ndarray
    a: np.ndarray
    N: np.ndarray
    k: float


def _open_loop_polynomials(plant: LinearPlant) -> tuple[np.ndarray, np.ndarray]:
    """``a(s) = det(sI - A)`` from the eigenvalues of A (structural roots set exactly to 0) and
    ``N(s) = g prod(s - z_i)`` from the transmission zeros (finite eigenvalues of the
    Rosenbrock pencil, as python-control's ``zeros``) and the high-frequency gain
    ``g = c A^{r-1} b`` at relative degree r."""
    A, b, c = loop_vectors(plant)
    n = A.shape[0]
    eig = np.linalg.eigvals(A)
    n0 = structural_directions(plant).shape[1]
    if n0:
        eig[np.argsort(np.abs(eig))[:n0]] = 0.0
    a = np.real(np.poly(eig))
    scale = max(np.linalg.norm(A, 2), 1.0)
    markov, v = [], b.copy()
    for _ in range(n):
        markov.append(c @ v)
        v = A @ v
    markov = np.asarray(markov)
    big = np.abs(markov) * scale ** -np.arange(n, dtype=np.float64)  # c A^i b scaled to O(|b| |c|)
    if not np.any(big > 1e-12 * np.linalg.norm(b) * np.linalg.norm(c)):
        return a, np.zeros(n + 1)
    r = int(np.argmax(big > 1e-12 * np.linalg.norm(b) * np.linalg.norm(c))) + 1  # relative degree
    gain = markov[r - 1]
    pencil_a = np.block([[A, b[:, None]], [c[None, :], np.zeros((1, 1))]])
    pencil_e = np.zeros((n + 1, n + 1))
    pencil_e[:n, :n] = np.eye(n)
    alpha, beta = scipy.linalg.eigvals(pencil_a, pencil_e, homogeneous_eigvals=True)
    ratio = np.abs(beta) / np.maximum(np.abs(alpha), np.finfo(np.float64).tiny)
    finite = np.argsort(-ratio)[: n - r]  # the n - r most finite generalised eigenvalues
    zeros = alpha[finite] / beta[finite]
    N = np.zeros(n + 1)
    N[r:] = gain * np.real(np.poly(zeros))
    return a, N


def characteristic_polynomials(plant: LinearPlant, k: ArrayLike) -> CharacteristicPolynomials:
    """P(s) and Q(s) of ``Delta(s, tau) = P(s) + Q(s) e^{-s tau}`` for the DFS gain k."""
    _one_plant(plant, check_continuous)
    k = check_gain(k)
    a, N = _open_loop_polynomials(plant)
    return CharacteristicPolynomials(a + k * N, -k * N, a, N, k)


def delta(plant: LinearPlant, k: ArrayLike, tau_s: ArrayLike, s: ArrayLike) -> np.ndarray:
    """``Delta(s, tau) = det(sI - A + k b c (1 - e^{-s tau}))`` evaluated directly (complex s, any shape)."""
    _one_plant(plant, check_continuous)
    A, b, c = loop_vectors(plant)
    k, tau = check_gain(k), check_delay(tau_s)
    if isinstance(s, jax.core.Tracer) or np.asarray(s).dtype.kind not in "iufc":  # a bool, a string, an object
        raise ValueError(f"s must be a complex number or an array of them (concrete: delta is NumPy); got {s!r}")
    s = np.asarray(s, np.complex128)
    z = np.exp(-s * tau)
    mats = s[..., None, None] * np.eye(A.shape[0]) - A + (k * (1 - z))[..., None, None] * np.outer(b, c)
    return np.linalg.det(mats)


def _transfer(A: np.ndarray, b: np.ndarray, c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G(s) = c (sI - A)^{-1} b and G'(s) = -c (sI - A)^{-2} b for an array of complex s."""
    s = np.atleast_1d(np.asarray(s, np.complex128))
    mats = s[:, None, None] * np.eye(A.shape[0]) - A
    x = np.linalg.solve(mats, np.broadcast_to(b.astype(np.complex128), s.shape + b.shape)[..., None])
    x2 = np.linalg.solve(mats, x)
    return x[..., 0] @ c, -(x2[..., 0] @ c)


class Crossing(NamedTuple):
    """One imaginary-axis crossing frequency and its critical delays.

    Attributes:
      omega: crossing frequency w (rad/s); ``freq_hz = w / (2 pi)``.
      freq_hz: the same in Hz.
      beta: phase in [0, 2 pi) with ``e^{-j beta} = -P(jw) / Q(jw)``.
      tau_s: [n] critical delays ``(beta + 2 pi m) / w <= tau_max_s`` (s), ascending.
      re_dsdtau: [n] ``Re ds/dtau`` at each critical delay (1/s^2).
      direction: ``"destabilising"`` (``Re ds/dtau > 0``), ``"stabilising"`` or ``"tangent"``.
      dF_dw: derivative of ``|P(jw)|^2 - |Q(jw)|^2`` (the Cooke-van den Driessche sign).
    """

    omega: float
    freq_hz: float
    beta: float
    tau_s: np.ndarray
    re_dsdtau: np.ndarray
    direction: str
    dF_dw: float


class ZeroCrossing(NamedTuple):
    """The non-structural real root passing through s = 0 at ``tau_s`` (only when ``k N(0) < 0``).

    Attributes:
      tau_s: ``-a'(0) / (k N(0))`` (s).
      dsdtau: ds/dtau of that real root at s = 0 (1/s^2).
      direction: ``"destabilising"`` or ``"stabilising"``.
    """

    tau_s: float
    dsdtau: float
    direction: str


class CriticalDelays(NamedTuple):
    """Result of :func:`critical_delays`.

    Attributes:
      k: the gain.
      crossings: imaginary-axis crossings (w > 0), by ascending frequency.
      zero_crossing: the real crossing through s = 0, or None.
      structural: description of the excluded structural root.
      tau_max_s: the largest delay listed.
      n_unstable_open_loop: non-structural roots of ``a(s) = det(sI - A)`` in the right half
        plane: the count as tau -> 0+ (the loop is retarded, deg Q < deg P, so the roots that
        appear for tau > 0 come from Re s = -inf).
    """

    k: float
    crossings: tuple[Crossing, ...]
    zero_crossing: ZeroCrossing | None
    structural: dict
    tau_max_s: float
    n_unstable_open_loop: int


def _f_poly_in_v(polys: CharacteristicPolynomials, scale: float) -> np.ndarray:
    """Ascending coefficients, in ``nu = (w / scale)^2``, of the even real polynomial
    ``F(w) = |P(jw)|^2 - |Q(jw)|^2`` (as ``p(jw) p(-jw)`` products), divided by ``nu`` when
    ``a(0) = 0`` (the structural root: then ``F(0) = a(0)^2 + 2 k a(0) N(0) = 0`` exactly)."""
    pp = np.polynomial.polynomial
    n = polys.a.shape[0]
    j_pow = (1j) ** np.arange(n)
    sc = scale ** np.arange(n)

    def in_w(p):  # ascending coefficients of p(j w) in the scaled variable w / scale
        return p[::-1] * j_pow * sc

    def conj_in_w(p):
        return p[::-1] * np.conj(j_pow) * sc

    f = pp.polysub(pp.polymul(in_w(polys.P), conj_in_w(polys.P)), pp.polymul(in_w(polys.Q), conj_in_w(polys.Q)))
    f = np.real(f)
    even = f[0::2].copy()
    if polys.a[-1] == 0.0:  # structural root: a(0) = 0 exactly, so F(0) = |a(0)|^2 + 2k a(0) N(0) = 0
        even = even[1:]
    return even


def _h(A, b, c, k, w):
    """``1 + 2 k Re G(jw) = (|P|^2 - |Q|^2) / |a|^2`` (well conditioned)."""
    g, _ = _transfer(A, b, c, 1j * np.asarray(w, np.float64))
    return 1.0 + 2.0 * k * np.real(g)


def crossing_frequencies(plant: LinearPlant, k: ArrayLike) -> np.ndarray:
    """All w > 0 (rad/s, ascending) with ``|P(jw)| = |Q(jw)|``: positive real roots of the
    polynomial in ``v = w^2``, polished by ``brentq`` on ``1 + 2 k Re G(jw) = 0``, united with the
    sign changes of a dense logarithmic scan of the same function."""
    _one_plant(plant, check_continuous)
    k = check_gain(k)
    if k == 0.0:
        return np.zeros((0,))
    A, b, c = loop_vectors(plant)
    polys = characteristic_polynomials(plant, k)
    scale = max(np.max(np.abs(np.linalg.eigvals(A))), 1.0)
    coef = _f_poly_in_v(polys, scale)
    if not np.all(np.isfinite(coef)):
        raise ValueError(
            f"n_modes = {n_modes_of(plant)}: the coefficients of this plant's characteristic polynomial "
            "overflow float64, so its crossings cannot be found; use fewer modes (the paper's arm holds up to 17)"
        )
    coef = np.trim_zeros(coef / np.max(np.abs(coef)), "b")
    nu = np.polynomial.polynomial.polyroots(coef) if coef.shape[0] > 1 else np.zeros((0,))
    real = nu[(np.abs(nu.imag) <= _ROOT_IMAG_RTOL * np.abs(nu)) & (nu.real > 0)].real
    candidates = list(scale * np.sqrt(real))

    hi = 10.0 * max([scale] + candidates)
    grid = np.geomspace(1e-3 * scale, hi, int(_SCAN_POINTS_PER_DECADE * math.log10(hi / (1e-3 * scale))) + 2)
    hv = _h(A, b, c, k, grid)
    brackets = [(grid[i], grid[i + 1]) for i in np.nonzero(np.sign(hv[:-1]) * np.sign(hv[1:]) < 0)[0]]

    def f(w):
        return float(_h(A, b, c, k, w)[0])

    def polish(w0):  # smallest bracket first, so a neighbouring root is not picked up
        for rel in (1e-9, 1e-7, 1e-5, 1e-3, 1e-2):
            lo, hi_ = w0 * (1 - rel), w0 * (1 + rel)
            if f(lo) * f(hi_) < 0:
                return scipy.optimize.brentq(f, lo, hi_, xtol=1e-15 * w0, rtol=4 * np.finfo(np.float64).eps, maxiter=200)
        return w0  # tangency (double root of F): kept as found

    found = [polish(w) for w in candidates]
    found += [scipy.optimize.brentq(f, lo, hi_, xtol=1e-15 * lo, rtol=4 * np.finfo(np.float64).eps, maxiter=200) for lo, hi_ in brackets]
    found = np.sort(np.asarray(found, np.float64))
    unique = []
    for w in found:
        if not unique or w - unique[-1] > _DEDUP_RTOL * w:
            unique.append(w)
    return np.asarray(unique, np.float64)


def _dsdtau(A, b, c, k, tau, s):
    """ds/dtau on ``phi(s, tau) = 1 + k G(s) (1 - e^{-s tau}) = Delta / a`` (same roots where a != 0)."""
    g, dg = _transfer(A, b, c, s)
    z = np.exp(-s * tau)
    phi_s = k * dg * (1 - z) + k * g * tau * z
    phi_tau = k * g * s * z
    return -phi_tau / phi_s


def critical_delays(plant: LinearPlant, k: ArrayLike, tau_max_s: ArrayLike = 0.05) -> CriticalDelays:
    """Imaginary-axis crossings of the DFS loop's characteristic roots for delays up to ``tau_max_s``.

    Args:
      plant: continuous-time plant (``make_plant``).
      k: DFS gain (N*m/rad), finite.
      tau_max_s: list critical delays up to this (s), > 0.
    """
    _one_plant(plant, check_continuous)
    k = check_gain(k)
    tau_max = check_finite_scalar("tau_max_s", tau_max_s, positive=True)
    A, b, c = loop_vectors(plant)
    polys = characteristic_polynomials(plant, k)
    crossings = []
    for w in crossing_frequencies(plant, k):
        g, _ = _transfer(A, b, c, 1j * w)
        beta = float(np.mod(-np.angle(1.0 + 1.0 / (k * g[0])), 2 * np.pi))
        count = int(np.floor((tau_max * w - beta) / (2 * np.pi))) + 1
        if count > _MAX_CRITICAL_DELAYS:
            raise ValueError(
                f"k = {k:g}: the loop crosses the imaginary axis at {w / (2 * np.pi):.4g} Hz, every {2 * np.pi / w:.3g} s of delay, "
                f"which is {count:.3g} critical delays up to {tau_max:g} s (at most {_MAX_CRITICAL_DELAYS:g} are listed): use a smaller |k| or tau_max_s"
            )
        taus = beta / w + 2 * np.pi / w * np.arange(count)
        taus = taus[(taus > 0) & (taus <= tau_max)]
        re = np.real(_dsdtau(A, b, c, k, taus, 1j * w)).reshape(-1)
        dw = 1e-6 * w
        fw = lambda x: np.abs(np.polyval(polys.P, 1j * x)) ** 2 - np.abs(np.polyval(polys.Q, 1j * x)) ** 2  # noqa: E731
        df = (fw(w + dw) - fw(w - dw)) / (2 * dw)
        ref = np.real(_dsdtau(A, b, c, k, beta / w if beta > 0 else 2 * np.pi / w, 1j * w)[0])
        big = abs(ref) > 1e-12 * w**2
        direction = ("destabilising" if ref > 0 else "stabilising") if big else "tangent"
        crossings.append(Crossing(float(w), float(w / (2 * np.pi)), beta, taus, re, direction, float(df)))

    n0 = structural_directions(plant).shape[1]
    zero = None
    structural = {"root": "s = 0 (z = 1 sampled)", "multiplicity": n0, "reason": "DFS has no position action: a constant hub angle (null space of A) is an equilibrium for every k and tau"}
    if n0 == 1 and k != 0.0:
        a_asc, n_asc = polys.a[::-1], polys.N[::-1]
        if n_asc[0] != 0.0:
            tau0 = -a_asc[1] / (k * n_asc[0])
            if tau0 > 0:
                g_s = a_asc[2] + k * n_asc[1] * tau0 - k * n_asc[0] * tau0**2 / 2
                ds = -k * n_asc[0] / g_s
                zero = ZeroCrossing(float(tau0), float(ds), "destabilising" if ds > 0 else "stabilising")
    elif n0 > 1:
        structural["note"] = "more than one structural direction: real crossings through s = 0 are not analysed"
    roots = np.roots(polys.a)
    roots = roots[np.argsort(np.abs(roots))][n0:]
    n_open = int(np.sum(roots.real > 1e-9 * max(1.0, np.max(np.abs(roots), initial=0.0))))
    return CriticalDelays(k, tuple(crossings), zero, structural, tau_max, n_open)


def unstable_root_count(result: CriticalDelays, tau_s: ArrayLike) -> np.ndarray:
    """Number of non-structural characteristic roots in the right half plane at each delay,
    counted from the crossings (stability switches): the open-loop count, plus 2 at each
    destabilising and minus 2 at each stabilising critical delay below tau (1 for the real
    crossing through 0). Exact between critical delays up to ``result.tau_max_s``.

    Args:
      result: :func:`critical_delays` output.
      tau_s: delays (s), any shape, each <= ``result.tau_max_s``.
    """
    checks.instance("result", result, CriticalDelays, "the result of critical_delays(...)")
    tau = checks.real_array("tau_s", tau_s).astype(np.float64)
    if tau.size == 0:
        raise ValueError("tau_s must hold at least one delay (s); got an empty array")
    if not np.all(np.isfinite(tau)) or np.any(tau > result.tau_max_s * (1 + 1e-12)) or np.any(tau <= 0):
        raise ValueError(f"tau_s must be in (0, tau_max_s = {result.tau_max_s:g}] s; got range [{tau.min():g}, {tau.max():g}]")
    count = np.full(tau.shape, result.n_unstable_open_loop, np.int64)
    for cr in result.crossings:
        for t, re in zip(cr.tau_s, cr.re_dsdtau):
            count += np.where(tau > t, 2 * int(np.sign(re)), 0)
    if result.zero_crossing is not None:
        count += np.where(tau > result.zero_crossing.tau_s, int(np.sign(result.zero_crossing.dsdtau)), 0)
    return count


def first_destabilising_delay(k: ArrayLike, n_modes: int = 2, *, plant: LinearPlant | None = None, tau_max_s: ArrayLike = 1.0) -> float:
    """The smallest delay (s) at which a characteristic root of the continuous DFS loop enters
    the right half plane (an imaginary-axis crossing or the real crossing through 0, whichever
    comes first), or ``inf`` when none does up to ``tau_max_s``.

    Args:
      k: DFS gain (N*m/rad), finite.
      n_modes: number of assumed modes (>= 1) of the default plant; ignored when ``plant`` is given.
      plant: a continuous-time plant to analyse instead of ``make_plant(n_modes=n_modes)``.
      tau_max_s: search up to this delay (s).
    """
    plant = _plant_or_default(plant, n_modes)
    result = critical_delays(plant, k, tau_max_s)
    taus = [float(t) for cr in result.crossings for t, re in zip(cr.tau_s, cr.re_dsdtau) if re > 0]
    if result.zero_crossing is not None and result.zero_crossing.direction == "destabilising":
        taus.append(result.zero_crossing.tau_s)
    return min(taus) if taus else math.inf


# ----------------------------------------------------------------------------------------------
# 2. Rightmost root of the delay equation: Chebyshev collocation of the generator (jax.numpy)


def chebyshev_differentiation(n_cheb: int) -> tuple[np.ndarray, np.ndarray]:
    """Trefethen's ``cheb``: points ``t_j = cos(j pi / M)`` (j = 0..M, t_0 = 1) and the
    [M + 1, M + 1] differentiation matrix (diagonal by the negative-sum trick, so rows sum to 0
    and constants are differentiated exactly)."""
    m = _check_n_cheb(n_cheb)
    t = np.cos(np.pi * np.arange(m + 1) / m)
    weights = np.ones(m + 1)
    weights[0] = weights[-1] = 2.0
    weights *= (-1.0) ** np.arange(m + 1)
    dt = t[:, None] - t[None, :] + np.eye(m + 1)
    D = np.outer(weights, 1.0 / weights) / dt
    D -= np.diag(np.sum(D, axis=1))
    return t, D


def generator_matrix(plant: LinearPlant, k: ArrayLike, tau_s: ArrayLike, n_cheb: int = DEFAULT_N_CHEB) -> jax.Array:
    """[n_x + M, n_x + M] Chebyshev collocation of the generator of ``x' = A0 x(t) + A1 x(t - tau)``.

    Only ``theta = c x`` is delayed (``A1 = k b c`` has rank one), so the state is ``x(0)`` and
    the history of theta at the collocation points ``theta_j = tau (t_j - 1) / 2``, j = 1..M
    (``theta_0 = c x(0)``, ``theta_M = theta(-tau)``): the first n_x rows are
    ``A0 x + k b theta_M``, the others differentiate the Chebyshev interpolant of the history.
    This is the quotient of the full-state collocation ``n_x (M + 1)`` (Breda-Maset-Vermiglio)
    by the histories with ``x(0) = 0`` and ``c u(theta_j) = 0``, whose only eigenvalues are
    those of the differentiation matrix with a zero condition at 0 (spurious, far left); the
    characteristic-root approximations are the same. Traced k and tau are fine (vmap over
    both); concrete ones are checked; ``n_cheb`` (M) is static.
    """
    _check_gain_and_delay(k, tau_s)
    return _generator(_one_plant(plant, check_continuous), k, tau_s, _check_n_cheb(n_cheb))


def _generator(plant: LinearPlant, k: ArrayLike, tau_s: ArrayLike, m: int) -> jax.Array:
    A, B, C = plant.A, plant.B, plant.C
    dtype = A.dtype
    _, D = chebyshev_differentiation(m)
    c = C[:1]  # [1, n]
    k = jnp.asarray(k, dtype)
    tau = jnp.asarray(tau_s, dtype)
    tap = jnp.zeros((1, m), dtype).at[0, m - 1].set(1.0)  # reads theta(-tau)
    top = jnp.concatenate([A - k * B @ c, k * B @ tap], axis=1)
    D = jnp.asarray(D, dtype)
    rest = (2.0 / tau) * jnp.concatenate([D[1:, :1] * c, D[1:, 1:]], axis=1)
    return jnp.concatenate([top, rest], axis=0)


@partial(jax.jit, static_argnums=4)
def _generator_roots(plant: LinearPlant, k: jax.Array, tau: jax.Array, v: jax.Array, m: int) -> jax.Array:
    """Deflated generator eigenvalues, by decreasing real part. v: [n_x, n0] structural directions."""
    r = jnp.concatenate([v, jnp.ones((m, 1), v.dtype) * (plant.C[:1] @ v)])  # constant history
    q2 = _deflation_basis(r)
    roots = jnp.linalg.eigvals(q2.T @ _generator(plant, k, tau, m) @ q2)
    return roots[jnp.argsort(-jnp.real(roots))]


def characteristic_roots(plant: LinearPlant, k: ArrayLike, tau_s: ArrayLike, n_cheb: int = DEFAULT_N_CHEB) -> jax.Array:
    """Approximate characteristic roots (rad/s, complex), structural root(s) deflated, sorted by
    decreasing real part. Only the rightmost few are accurate. Concrete k, tau are checked;
    traced ones are fine (vmap/jit over them with the plant closed over)."""
    _one_plant(plant, check_continuous)
    _check_gain_and_delay(k, tau_s)
    m = _check_n_cheb(n_cheb)
    dtype = plant.A.dtype
    v = jnp.asarray(structural_directions(plant), dtype)
    return _generator_roots(plant, jnp.asarray(k, dtype), jnp.asarray(tau_s, dtype), v, m)


def rightmost_root(plant: LinearPlant, k: ArrayLike, tau_s: ArrayLike, n_cheb: int = DEFAULT_N_CHEB) -> jax.Array:
    """The non-structural characteristic root of largest real part (rad/s, complex; of a complex
    pair, the one with Im >= 0). The continuous loop is stable when its real part is < 0."""
    roots = characteristic_roots(plant, k, tau_s, n_cheb)
    top = jnp.real(roots) >= jnp.real(roots[0]) - 1e-9 * (1.0 + jnp.abs(roots[0]))
    return roots[jnp.argmax(jnp.where(top, jnp.imag(roots), -jnp.inf))]


class ConvergedRoot(NamedTuple):
    """The rightmost root at ``n_cheb`` intervals; ``change`` is its distance (rad/s) from the
    root at half as many, and ``converged`` whether that is within ``ROOT_RTOL x (1 + |root|)``."""

    root: complex
    n_cheb: int
    change: float
    converged: bool


def rightmost_root_converged(plant: LinearPlant, k: ArrayLike, tau_s: ArrayLike, n_cheb: int = DEFAULT_N_CHEB, max_n_cheb: int | None = None) -> ConvergedRoot:
    """:func:`rightmost_root` at ``n_cheb``, ``2 n_cheb``, ``4 n_cheb``, ... intervals until two
    successive roots agree to ``ROOT_RTOL`` relative, or the next doubling would pass
    ``max_n_cheb`` (default the larger of ``MAX_N_CHEB`` and ``2 n_cheb``): then ``converged``
    is False. Concrete k and tau only (a loop on their values)."""
    m = _check_n_cheb(n_cheb)
    top = max(MAX_N_CHEB, 2 * m) if max_n_cheb is None else checks.integer("max_n_cheb", max_n_cheb, 2 * m, unit="Chebyshev intervals, twice n_cheb at least")
    root = complex(rightmost_root(plant, k, tau_s, m))
    while True:
        m *= 2
        finer = complex(rightmost_root(plant, k, tau_s, m))
        change = abs(finer - root)
        converged = change <= ROOT_RTOL * (1.0 + abs(finer))
        if converged or 2 * m > top:
            return ConvergedRoot(finer, m, change, converged)
        root = finer


# ----------------------------------------------------------------------------------------------
# 3. The sampled loop (jax.numpy)


def _check_sampled_args(k: ArrayLike, delay_steps: ArrayLike, n_hist: int | None) -> tuple[int, ArrayLike]:
    """The history length and the delay: ``n_hist`` and ``delay_steps``, or with ``n_hist``
    None a whole ``delay_steps`` as both (a float whole to ``WHOLE_SAMPLE_RTOL``, as
    ``tau_s / dt`` gives it, ``0.003 / 0.001 = 2.9999999999999996``, as that int). With
    ``n_hist`` given a concrete delay may be fractional, as a traced one."""
    if not isinstance(k, jax.core.Tracer):
        check_gain(k)
    if isinstance(delay_steps, jax.core.Tracer):
        if n_hist is None:
            raise ValueError("a traced delay_steps needs a static n_hist (history length >= every delay)")
        return _check_delay_steps(n_hist, "n_hist"), delay_steps
    arr = checks.real_array("delay_steps", delay_steps, scalar=True)
    if n_hist is None:
        try:
            whole = _whole_delay(delay_steps)
        except ValueError as err:
            if arr.ndim == 0 and arr.dtype.kind == "f" and float(arr) >= 1 and not whole_samples(float(arr)):  # 5.5 samples: say where a fractional delay goes
                raise ValueError(f"{err}; a fractional delay needs n_hist, the history length (an integer >= the delay)") from None
            raise
        return whole, whole
    n_hist = _check_delay_steps(n_hist, "n_hist")
    if arr.ndim != 0 or not 1 <= float(arr) <= n_hist:
        raise ValueError(f"delay_steps must be a number of samples in [1, n_hist = {n_hist}] (fractional: read between samples by interpolation); got {delay_steps!r}")
    return n_hist, delay_steps


def sampled_loop_matrix(plant: DiscretePlant, k: ArrayLike, delay_steps: ArrayLike, n_hist: int | None = None, interpolation: str = "linear") -> jax.Array:
    """The exact one-sample map of jaxflex's sampled DFS loop.

    ``xi_k = [x_k, theta_{k-1}, ..., theta_{k-n_hist}]``; ``u_k = -k (theta_k - theta_{k-d})``;
    ``x_{k+1} = Ad x_k + Bd u_k``; ``theta_k`` is pushed into the history. The rollout's
    initial history (all equal to theta(0)) is ``xi_0 = [x_0, theta_0, ..., theta_0]``.

    Args:
      plant: sampled plant (any ``discretize`` method: the map is exact for its Ad, Bd).
      k: gain (N*m/rad); may be traced.
      delay_steps: d >= 1 samples. A whole number when ``n_hist`` is None (then ``n_hist = d``;
        a float within ``WHOLE_SAMPLE_RTOL`` of one, as ``tau_s / dt`` gives it, is read as it);
        with ``n_hist`` given it may be fractional (linear interpolation, as
        ``dfs(interpolation="linear")``) and traced (vmap over delays): history slots beyond
        floor(d) + 1 are neither shifted nor read, so they add only semisimple zero
        eigenvalues (no defective block whose computed eigenvalues would scatter by
        eps^(1/size)).
      n_hist: static history length >= d, at most ``MAX_HISTORY``.
      interpolation: how a fractional d is read, ``"linear"`` or ``"cubic"`` (4-point
        Lagrange, as ``dfs(interpolation="cubic")``; slots up to the last one it reads are live).

    Returns:
      [n_x + n_hist, n_x + n_hist] matrix.
    """
    n_hist, delay_steps = _check_sampled_args(k, delay_steps, n_hist)
    return _loop_matrix(_one_plant(plant, check_sampled), k, delay_steps, n_hist, interpolation)


def _read(delay_steps: ArrayLike, n_hist: int, interpolation: str, dtype) -> tuple[jax.Array, jax.Array]:
    """The delay read as weights on ``theta_{k-j}``, j = 0..n_hist, and the last lag it reads.

    ``"linear"``: ``(1 - f) theta_{k-w} + f theta_{k-w-1}`` with ``w = floor(d)``, ``f = d - w``,
    as ``dfs(interpolation="linear")`` (and "nearest" at whole d); at a whole d lag d + 1 is
    read with weight 0, so it is kept live: the derivative in d (from above) reads it.
    ``"cubic"``: 4-point Lagrange on the lags ``s .. s + 3``, ``s = floor(d) - 1`` clamped into
    the buffer of ``n_hist + 1`` samples (on all of them when it holds fewer than 4), as
    ``jaxflex.delay.delay_read``.
    """
    d = jnp.asarray(delay_steps, dtype)
    lags = jnp.arange(n_hist + 1, dtype=dtype)
    if interpolation == "linear":
        whole = jnp.floor(d)
        frac = d - whole
        return (1 - frac) * (lags == whole) + frac * (lags == whole + 1), whole + 1
    if interpolation != "cubic":
        raise ValueError(f"interpolation must be 'linear' or 'cubic'; got {interpolation!r}")
    n_pts = min(4, n_hist + 1)  # a buffer of 2 or 3 samples: Lagrange on all of them, as delay_read
    start = jnp.clip(jnp.floor(d) - 1, 0, n_hist + 1 - n_pts)
    t = d - start
    weights = jnp.zeros(n_hist + 1, dtype)
    for i in range(n_pts):  # the Lagrange basis as delay_read forms it
        w = jnp.ones_like(t)
        for j in range(n_pts):
            if j != i:
                w = w * (t - j) / (i - j)
        weights = weights + w * (lags == start + i)
    return weights, start + n_pts - 1


def _loop_matrix(plant: DiscretePlant, k: ArrayLike, delay_steps: ArrayLike, n_hist: int, interpolation: str = "linear") -> jax.Array:
    """The loop map for a whole or fractional delay d, read as ``_read`` says. History slots
    beyond the last lag read are neither shifted nor read."""
    Ad, Bd = plant.Ad, plant.Bd
    dtype = Ad.dtype
    c = plant.C[:1]  # [1, n]
    k = jnp.asarray(k, dtype)
    weights, live = _read(delay_steps, n_hist, interpolation, dtype)  # weights on theta_{k-j}, j = 0..n_hist
    slots = jnp.arange(1, n_hist + 1, dtype=dtype)
    shift = (slots[:, None] == slots[None, :] + 1) & (slots[:, None] <= live)  # h_i <- h_{i-1}, i <= floor(d) + 1
    top = jnp.concatenate([Ad - k * (1 - weights[0]) * Bd @ c, k * Bd @ weights[None, 1:]], axis=1)
    first = (slots == 1).astype(dtype)[:, None] * c  # h_1 <- theta_k
    hist = jnp.concatenate([first, shift.astype(dtype)], axis=1)
    return jnp.concatenate([top, hist], axis=0)


def deflated_loop_matrix(plant: DiscretePlant, k: ArrayLike, delay_steps: ArrayLike, n_hist: int, interpolation: str = "linear") -> jax.Array:
    """The sampled loop map restricted to the complement of its structural eigenvectors.

    Its eigenvalues are those of :func:`sampled_loop_matrix` with one eigenvalue 1 removed per
    structural direction. ``delay_steps`` may be fractional and traced, in [1, n_hist], read
    by ``interpolation``, ``"linear"`` or ``"cubic"`` as ``dfs`` reads it (see ``_read``); the
    plant must be concrete.
    """
    n_hist, delay_steps = _check_sampled_args(k, delay_steps, n_hist)
    return _deflated(plant, k, delay_steps, jnp.asarray(structural_directions(_one_plant(plant, check_sampled)), plant.Ad.dtype), n_hist, interpolation)


def pade_loop_matrix(plant: DiscretePlant, k: ArrayLike, tau_s: ArrayLike, order: int, hold: str = "foh") -> jax.Array:
    """The exact one-sample map of the sampled loop of ``dfs(approximation="pade")``.

    State ``[x_k, xi_k]`` with the Pade filter's ``xi``, sampled at the plant's dt as ``dfs``
    samples it (``pade.sampled_delay``): ``theta_k = c x_k``, ``u_k = -k (theta_k - C xi_k -
    D theta_k)``, ``x_{k+1} = Ad x_k + Bd u_k``, ``xi_{k+1} = Ad_f xi_k + Bd_f theta_k``. The
    rollout starts the filter at its steady state for ``theta_0``. k and tau_s (> 0) may be
    traced; the plant must be concrete.
    """
    filt, _ = _sampled_pade(plant, k, tau_s, order, hold, jnp.zeros((1, 1), _one_plant(plant, check_sampled).Ad.dtype))
    return _pade_loop(plant, k, filt)


def deflated_pade_loop_matrix(plant: DiscretePlant, k: ArrayLike, tau_s: ArrayLike, order: int, hold: str = "foh") -> jax.Array:
    """``pade_loop_matrix`` restricted to the complement of its structural eigenvectors, as
    ``deflated_loop_matrix`` is for the buffer: a constant hub angle, with the filter at its
    steady state (whose output is that angle). Its eigenvalues differ from the buffer loop's:
    at k = 150, tau = 5 ms the order-1 loop decays (0.989) where the exact delay's grows (1.063).
    """
    v = jnp.asarray(structural_directions(_one_plant(plant, check_sampled)), plant.Ad.dtype)
    filt, xi_eq = _sampled_pade(plant, k, tau_s, order, hold, plant.C[:1] @ v)  # xi_eq: [N, n0]
    q2 = _deflation_basis(jnp.concatenate([v, xi_eq], axis=0))
    return q2.T @ _pade_loop(plant, k, filt) @ q2


def _sampled_pade(plant: DiscretePlant, k: ArrayLike, tau_s: ArrayLike, order: int, hold: str, theta: jax.Array) -> tuple[pade.PadeDiscrete, jax.Array]:
    """The checked inputs' Pade filter sampled at the (sampled) plant's dt, and its steady
    states for the angles ``theta`` [1, n] (one ``expm``)."""
    if not isinstance(k, jax.core.Tracer):
        check_gain(k)
    if not isinstance(tau_s, jax.core.Tracer):
        checks.real_array("tau_s", tau_s, scalar=True)  # a string failed in NumPy's float(); pade names the range
    return pade.sampled_delay(jnp.asarray(tau_s, plant.Ad.dtype), pade.check_order(order), float(plant.dt), theta, hold)


def _pade_loop(plant: DiscretePlant, k: ArrayLike, filt: pade.PadeDiscrete) -> jax.Array:
    """``pade_loop_matrix`` from the sampled filter."""
    c = plant.C[:1]
    k = jnp.asarray(k, plant.Ad.dtype)
    return jnp.block([[plant.Ad - k * (1 - filt.D[0, 0]) * plant.Bd @ c, k * plant.Bd @ filt.C], [filt.Bd @ c, filt.Ad]])


def _deflated(plant: DiscretePlant, k: ArrayLike, delay_steps: ArrayLike, v: jax.Array, n_hist: int, interpolation: str = "linear") -> jax.Array:
    """``Q2^T M Q2`` with Q2 the orthonormal complement of the structural eigenvectors; v: [n_x, n0]."""
    dtype = v.dtype
    last = _read(delay_steps, n_hist, interpolation, dtype)[1]
    live = (jnp.arange(1, n_hist + 1, dtype=dtype) <= last).astype(dtype)[:, None]
    r = jnp.concatenate([v, live * (plant.C[:1] @ v)], axis=0)  # [v, c v, ..., c v, 0, ...]
    q2 = _deflation_basis(r)
    return q2.T @ _loop_matrix(plant, k, delay_steps, n_hist, interpolation) @ q2


@partial(jax.jit, static_argnums=4)
def _sampled_eigs(plant: DiscretePlant, k: jax.Array, delay_steps: jax.Array, v: jax.Array, n_hist: int) -> jax.Array:
    """Deflated eigenvalues of the sampled loop by decreasing modulus; v: [n_x, n0]."""
    eig = jnp.linalg.eigvals(_deflated(plant, k, delay_steps, v, n_hist))
    return eig[jnp.argsort(-jnp.abs(eig))]


def sampled_eigenvalues(plant: DiscretePlant, k: ArrayLike, delay_steps: ArrayLike, n_hist: int | None = None) -> jax.Array:
    """Eigenvalues of the sampled loop with the structural eigenvalue 1 deflated (one copy per
    structural direction, by its known eigenvector ``[v, c v, ..., c v]``), by decreasing modulus.
    The plant must be concrete (closed over under jit/vmap); k and the delay may be traced, and
    with ``n_hist`` given the delay may be fractional (see ``sampled_loop_matrix``)."""
    _one_plant(plant, check_sampled)
    n_hist, delay_steps = _check_sampled_args(k, delay_steps, n_hist)
    dtype = plant.Ad.dtype
    v = jnp.asarray(structural_directions(plant), dtype)
    return _sampled_eigs(plant, jnp.asarray(k, dtype), jnp.asarray(delay_steps, dtype), v, n_hist)


def spectral_radius(plant: DiscretePlant, k: ArrayLike, delay_steps: ArrayLike, n_hist: int | None = None) -> jax.Array:
    """Spectral radius of the sampled DFS loop without the structural eigenvalue; < 1 is
    asymptotically stable. Jittable, vmappable over k and (with a static ``n_hist``) over
    ``delay_steps``, which may then be fractional; differentiable in k, and in a fractional
    delay between whole samples, where the largest modulus is simple or a conjugate pair."""
    return jnp.abs(sampled_eigenvalues(plant, k, delay_steps, n_hist)[0])


# ----------------------------------------------------------------------------------------------
# 4. The (k, tau) chart


class StabilityChart(NamedTuple):
    """Stability over a grid of gains and delays (NumPy).

    Attributes:
      k: [n_k] gains (N*m/rad).
      tau_s: [n_tau] delays (s), whole samples of dt.
      delay_steps: [n_tau] the same in samples.
      spectral_radius: [n_tau, n_k] sampled loop (structural eigenvalue excluded); < 1 stable.
      rightmost_real: [n_tau, n_k] real part of the rightmost non-structural root of the
        continuous loop (1/s), or NaN when not computed; < 0 stable.
      first_destabilising_delay_s: [n_k] from the crossings (inf when none).
      dt: sample time (s).
    """

    k: np.ndarray
    tau_s: np.ndarray
    delay_steps: np.ndarray
    spectral_radius: np.ndarray
    rightmost_real: np.ndarray
    first_destabilising_delay_s: np.ndarray
    dt: float


def sampled_radius_grid(plant: DiscretePlant, k_values: ArrayLike, delay_steps: ArrayLike) -> jax.Array:
    """[n_tau, n_k] sampled spectral radii: one jitted ``vmap(vmap(...))`` over delays and gains
    (every delay padded to the longest history, so there is one compilation)."""
    _one_plant(plant, check_sampled)
    k_values, delay_steps = _grid_axes(k_values=k_values, delay_steps=delay_steps)
    delay_steps = np.asarray([_whole_delay(d) for d in delay_steps.tolist()])
    for kv in k_values.tolist():
        check_gain(kv)
    dtype = plant.Ad.dtype
    v = jnp.asarray(structural_directions(plant), dtype)
    return _radius_grid(plant, jnp.asarray(k_values, dtype), jnp.asarray(delay_steps, jnp.int32), v, int(delay_steps.max()))


@partial(jax.jit, static_argnums=4)
def _radius_grid(plant, k_values, delay_steps, v, n_hist):
    def one(k, d):
        return jnp.abs(_sampled_eigs(plant, k, d, v, n_hist)[0])

    return jax.vmap(jax.vmap(one, in_axes=(0, None)), in_axes=(None, 0))(k_values, delay_steps)


def rightmost_real_grid(plant: LinearPlant, k_values: ArrayLike, tau_s: ArrayLike, n_cheb: int = DEFAULT_N_CHEB) -> jax.Array:
    """[n_tau, n_k] real part of the rightmost non-structural root, batched with ``vmap``, for
    non-empty 1-D ``k_values`` and ``tau_s`` (s)."""
    _one_plant(plant, check_continuous)
    m = _check_n_cheb(n_cheb)
    _grid_axes(k_values=k_values, tau_s=tau_s)
    for kv in np.asarray(k_values).tolist():
        check_gain(kv)
    for t in np.asarray(tau_s).tolist():
        check_delay(t)
    dtype = plant.A.dtype
    v = jnp.asarray(structural_directions(plant), dtype)
    return _rightmost_grid(plant, jnp.asarray(k_values, dtype), jnp.asarray(tau_s, dtype), v, m)


@partial(jax.jit, static_argnums=4)
def _rightmost_grid(plant, k_values, tau_s, v, m):
    def one(k, tau):
        return jnp.real(_generator_roots(plant, k, tau, v, m)[0])

    return jax.vmap(jax.vmap(one, in_axes=(0, None)), in_axes=(None, 0))(k_values, tau_s)


def stability_chart(
    plant: LinearPlant,
    k_values: ArrayLike,
    delay_steps: ArrayLike,
    dt: float = 1e-3,
    method: str = "zoh",
    n_cheb: int = DEFAULT_N_CHEB,
    continuous: bool = True,
) -> StabilityChart:
    """Sampled and continuous stability over a (k, tau) grid.

    Args:
      plant: continuous-time plant.
      k_values: [n_k] gains (N*m/rad), finite.
      delay_steps: [n_tau] delays in samples of dt (whole numbers >= 1, as for
        ``spectral_radius``); tau = d dt.
      dt: sample time (s).
      method: discretisation of the sampled loop (``"zoh"`` or ``"rk4"``, as ``discretize``).
      n_cheb: Chebyshev intervals of the generator.
      continuous: also compute the continuous loop's rightmost root.
    """
    dplant = discretize(plant, dt, method)
    k_values, delay_steps = _grid_axes(k_values=k_values, delay_steps=delay_steps)
    k_values, delay_steps = k_values.astype(np.float64), np.asarray([_whole_delay(d) for d in delay_steps.tolist()])
    tau = delay_steps * float(dt)
    radius = np.asarray(sampled_radius_grid(dplant, k_values, delay_steps))
    if continuous:
        real = np.asarray(rightmost_real_grid(plant, k_values, tau, n_cheb))
    else:
        real = np.full(radius.shape, np.nan)
    first = np.asarray([first_destabilising_delay(kv, plant=plant, tau_max_s=max(1.0, 2 * tau.max())) if kv != 0 else math.inf for kv in k_values])
    return StabilityChart(k_values, tau, delay_steps.astype(np.int64), radius, real, first, float(dt))
