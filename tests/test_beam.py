"""Beam model: closed forms against quadrature, convergence to the exact frequency equation,
differentiability against finite differences, and input validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, optimize

from jaxflex import beam
from jaxflex.beam import BeamParams

RTOL_QUAD = 1e-9  # adaptive quadrature of smooth mode shapes in float64
RTOL_ROOT = 1e-9  # brentq to machine precision; frequencies are algebraic in the roots
RTOL_FD = 1e-6  # central difference with a relative step of 1e-4, float64


def _exact_no_payload_hz(params: BeamParams, count: int) -> np.ndarray:
    """Roots of the scalar hub-beam frequency equation, derived by hand for no payload:
    (sin l cosh l - cos l sinh l) + mu l^3 (1 + cos l cosh l) = 0, mu = I_H / (rho A L^3).
    Limits: mu -> inf gives the clamped-free equation, mu -> 0 the pinned-free one."""
    rho_a = params.density_kg_m3 * params.width_m * params.thickness_m
    e_i = params.youngs_modulus_pa * params.width_m * params.thickness_m**3 / 12
    mu = params.hub_inertia_kg_m2 / (rho_a * params.length_m**3)

    def f(lam):  # divided by cosh(lam) to stay O(1)
        return (math.sin(lam) - math.cos(lam) * math.tanh(lam)) + mu * lam**3 * (1 / math.cosh(lam) + math.cos(lam))

    grid = np.linspace(0.1, (count + 2) * math.pi, 20000)
    vals = np.array([f(x) for x in grid])
    roots = [optimize.brentq(f, a, b, xtol=1e-15) for a, b, fa, fb in zip(grid[:-1], grid[1:], vals[:-1], vals[1:]) if fa * fb < 0]
    lam = np.array(roots[:count])
    return lam**2 / params.length_m**2 * math.sqrt(e_i / rho_a) / (2 * math.pi)


def test_clamped_free_roots_solve_frequency_equation():
    lam = beam.clamped_free_roots(6)
    np.testing.assert_allclose(np.cos(lam) + 1 / np.cosh(lam), 0.0, atol=1e-14)  # well-scaled form of 1 + cos cosh = 0
    np.testing.assert_allclose(lam[:2], [1.8751040687, 4.6940911330], rtol=1e-10)  # textbook values


def test_mode_shapes_normalisation_and_closed_forms():
    n = 6
    lam = beam.clamped_free_roots(n)
    for i in range(n):
        phi = lambda xi: float(beam.mode_shapes(np.array([xi]), n)[0, i])
        norm = integrate.quad(lambda xi: phi(xi) ** 2, 0, 1, limit=200)[0]
        moment = integrate.quad(lambda xi: xi * phi(xi), 0, 1, limit=200)[0]
        np.testing.assert_allclose(norm, 1.0, rtol=RTOL_QUAD)  # int phi^2 dx = L
        np.testing.assert_allclose(moment, 2.0 / lam[i] ** 2, rtol=RTOL_QUAD)  # int x phi dx = 2 / beta^2 (L = 1)
        np.testing.assert_allclose(abs(phi(1.0)), 2.0, rtol=1e-12)
        np.testing.assert_allclose(phi(0.0), 0.0, atol=1e-12)


def test_mass_and_stiffness_against_quadrature_with_payload():
    params = BeamParams(payload_mass_kg=0.05, payload_inertia_kg_m2=2e-4)
    n = 3
    mats = beam.modal_matrices(params, n)
    L = params.length_m
    rho_a = params.density_kg_m3 * params.width_m * params.thickness_m
    e_i = params.youngs_modulus_pa * params.width_m * params.thickness_m**3 / 12
    xs = np.linspace(0, 1, 20001)
    phi = np.asarray(beam.mode_shapes(xs, n))  # [P, n]
    dphi = np.gradient(phi, xs * L, axis=0, edge_order=2)
    ddphi = np.gradient(dphi, xs * L, axis=0, edge_order=2)
    shapes = np.concatenate([xs[:, None] * L, phi], axis=1)  # y = x theta + sum phi q
    slopes = np.concatenate([np.ones((xs.size, 1)), dphi], axis=1)
    curv = np.concatenate([np.zeros((xs.size, 1)), ddphi], axis=1)
    m_ref = rho_a * integrate.trapezoid(shapes[:, :, None] * shapes[:, None, :], xs * L, axis=0)
    m_ref += params.hub_inertia_kg_m2 * np.outer(np.eye(n + 1)[0], np.eye(n + 1)[0])
    m_ref += params.payload_mass_kg * np.outer(shapes[-1], shapes[-1]) + params.payload_inertia_kg_m2 * np.outer(slopes[-1], slopes[-1])
    k_ref = e_i * integrate.trapezoid(curv[:, :, None] * curv[:, None, :], xs * L, axis=0)
    np.testing.assert_allclose(np.asarray(mats.M), m_ref, rtol=1e-5, atol=1e-7 * np.abs(m_ref).max())  # finite-difference slopes
    np.testing.assert_allclose(np.asarray(mats.K), k_ref, rtol=1e-3, atol=1e-4 * np.abs(k_ref).max())  # second differences


def test_library_exact_frequencies_match_hand_derived_equation():
    """To 30 modes, for the paper's hub, a heavy one (near clamped-free) and a light one (near
    pinned-free): the rows of the boundary conditions in cosh and sinh cancelled to round-off
    from about the twelfth mode, and the roots found there were spurious."""
    for hub in (BeamParams().hub_inertia_kg_m2, 1e3, 1e-9):
        params = BeamParams(hub_inertia_kg_m2=hub)
        np.testing.assert_allclose(beam.exact_natural_frequencies_hz(params, 30), _exact_no_payload_hz(params, 30), rtol=RTOL_ROOT, err_msg=str(hub))
    with pytest.raises(ValueError, match=r"n_freqs must be an integer in \[1, 100\]; got 0"):
        beam.exact_natural_frequencies_hz(params, 0)
    with pytest.raises(ValueError, match=r"n_freqs must be an integer in \[1, 100\]; got 101"):
        beam.exact_natural_frequencies_hz(params, 101)


def test_exact_payload_frequencies_bound_many_assumed_modes_from_below():
    """With a payload (no hand-derived equation), the first 16 exact frequencies bound the
    20- and 40-mode models' from below, which approach them (Rayleigh-Ritz), and they are
    spaced as a beam's high roots are: lambda = beta L gaps that grow towards pi."""
    loaded = BeamParams(payload_mass_kg=0.1, payload_inertia_kg_m2=1e-4)
    exact = beam.exact_natural_frequencies_hz(loaded, 16)
    coarse, fine = (np.asarray(beam.natural_frequencies_hz(loaded, n))[:16] for n in (20, 40))
    assert np.all(exact < fine) and np.all(fine < coarse)
    rho_a = loaded.density_kg_m3 * loaded.width_m * loaded.thickness_m
    e_i = loaded.youngs_modulus_pa * loaded.width_m * loaded.thickness_m**3 / 12
    gaps = np.diff(np.sqrt(2 * math.pi * exact / math.sqrt(e_i / rho_a)) * loaded.length_m)
    assert np.all(np.diff(gaps[4:]) > 0) and 0.995 * math.pi < gaps[-1] < math.pi


def test_payload_frequencies_converge_from_above():
    """With a tip payload the clamped-free trial functions (zero tip shear) converge slowly, but
    they still bound the exact roots from above and approach them monotonically."""
    loaded_params = BeamParams(payload_mass_kg=0.1, payload_inertia_kg_m2=1e-4)
    base = beam.exact_natural_frequencies_hz(BeamParams(), 3)
    loaded = beam.exact_natural_frequencies_hz(loaded_params, 3)
    assert np.all(loaded < base)  # a payload lowers every frequency
    errors = []
    for n in range(3, 9):
        model = np.asarray(beam.natural_frequencies_hz(loaded_params, n))[:3]
        assert np.all(model >= loaded * (1 - 1e-12))
        errors.append(model / loaded - 1)
    errors = np.array(errors)
    assert np.all(np.diff(errors, axis=0) < 0)
    assert errors[-1, 0] < 5e-4  # n = 8: first mode within 0.05 %


def test_a_tip_rotary_inertia_slows_convergence_to_about_one_over_n():
    """BeamParams' docstring: with J_p the error falls about as 1/n (every trial shape has zero
    tip moment), a tip mass alone fast; found by a walkthrough, where 3 modes of a 1 kg m^2
    payload were 16 % high."""
    heavy, massive = BeamParams(payload_inertia_kg_m2=1.0), BeamParams(payload_mass_kg=0.1)
    exact = beam.exact_natural_frequencies_hz(heavy, 1)[0]
    error = {n: float(beam.natural_frequencies_hz(heavy, n)[0]) / exact - 1 for n in (10, 100)}
    assert 0.7 < error[10] * 10 / (error[100] * 100) < 1.4 and 0 < error[100] < 5e-3  # n * error about constant (1/sqrt(n): 0.32)
    mass_error = float(beam.natural_frequencies_hz(massive, 20)[0]) / beam.exact_natural_frequencies_hz(massive, 1)[0] - 1
    assert 0 < mass_error < 1e-4


def test_assumed_mode_frequencies_converge_from_above():
    params = BeamParams()
    exact = _exact_no_payload_hz(params, 6)
    previous = None
    errors = []
    for n in range(1, 7):
        f = np.asarray(beam.natural_frequencies_hz(params, n))
        assert f.shape == (n,)
        assert np.all(np.diff(f) > 0)
        assert np.all(f >= exact[:n] * (1 - 1e-12)), (n, f, exact[:n])  # Rayleigh-Ritz upper bounds
        if previous is not None:
            assert np.all(f[: n - 1] <= previous * (1 + 1e-12))  # nested trial spaces: monotone
        previous = f
        errors.append(f[0] / exact[0] - 1)
    assert errors[-1] < 1e-6 and errors[0] > 1e-2
    assert all(b < a for a, b in zip(errors, errors[1:]))


def test_paper_frequencies_are_not_reproduced_and_pinned_free_bound_holds():
    """The paper's 16 Hz first mode exceeds the pinned-free bound of this beam (tan x = tanh x)."""
    params = BeamParams()
    f1 = beam.exact_natural_frequencies_hz(params, 1)[0]
    huge_hub = beam.exact_natural_frequencies_hz(params._replace(hub_inertia_kg_m2=1e9), 1)[0]
    tiny_hub = beam.exact_natural_frequencies_hz(params._replace(hub_inertia_kg_m2=1e-12), 1)[0]
    assert huge_hub < f1 < tiny_hub  # the hub interpolates between clamped-free and pinned-free
    lam_pf = optimize.brentq(lambda x: math.tan(x) - math.tanh(x), 3.5, 4.5)
    rho_a = params.density_kg_m3 * params.width_m * params.thickness_m
    e_i = params.youngs_modulus_pa * params.width_m * params.thickness_m**3 / 12
    pinned_free = lam_pf**2 / params.length_m**2 * math.sqrt(e_i / rho_a) / (2 * math.pi)
    np.testing.assert_allclose(tiny_hub, pinned_free, rtol=1e-6)
    assert pinned_free < 16.0


def test_rayleigh_damping_gives_requested_ratio():
    params = BeamParams(damping_ratio=0.02)
    mats = beam.modal_matrices(params, 2)
    m, k, d = (np.asarray(a) for a in (mats.M, mats.K, mats.D))
    n_q = 3
    a = np.block([[np.zeros((n_q, n_q)), np.eye(n_q)], [-np.linalg.solve(m, k), -np.linalg.solve(m, d)]])
    eig = np.linalg.eigvals(a)
    osc = eig[eig.imag > 1e-6]
    zeta = -osc.real / np.abs(osc)
    np.testing.assert_allclose(zeta, 0.02, rtol=1e-9)
    explicit = beam.modal_matrices(params._replace(rayleigh_alpha=0.5, rayleigh_beta=1e-4), 2)
    np.testing.assert_allclose(np.asarray(explicit.D), 0.5 * m + 1e-4 * k, rtol=1e-12)


@pytest.mark.parametrize(
    "field",
    ["youngs_modulus_pa", "density_kg_m3", "hub_inertia_kg_m2", "length_m", "payload_mass_kg", "payload_inertia_kg_m2"],
)
def test_frequency_gradients_match_central_differences(field):
    base = BeamParams(payload_mass_kg=0.02, payload_inertia_kg_m2=1e-5)
    value = float(getattr(base, field))

    def f(v):
        return beam.natural_frequencies_hz(base._replace(**{field: v}), 3)

    jac = np.asarray(jax.jacfwd(f)(jnp.asarray(value)))
    grad_rev = np.asarray(jax.grad(lambda v: f(v)[1])(jnp.asarray(value)))
    h = 1e-4 * value  # truncation O(h^2) ~ 1e-8 relative, far below RTOL_FD; smaller steps meet eigenvalue round-off
    fd = (np.asarray(f(value + h)) - np.asarray(f(value - h))) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=RTOL_FD)
    np.testing.assert_allclose(grad_rev, fd[1], rtol=RTOL_FD)
    assert np.all(np.isfinite(jac))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(length_m=-1.0), "length_m must be > 0"),
        (dict(youngs_modulus_pa=0.0), "youngs_modulus_pa must be > 0"),
        (dict(density_kg_m3=float("nan")), "density_kg_m3 must be finite"),
        (dict(hub_inertia_kg_m2=float("inf")), "hub_inertia_kg_m2 must be finite"),
        (dict(payload_mass_kg=-0.1), "payload_mass_kg must be >= 0"),
        (dict(rayleigh_alpha=0.1), "given together"),
        (dict(length_m="0.9"), r"length_m must be a real number; got '0\.9'"),
        (dict(damping_ratio=True), r"damping_ratio must be a real number"),
        (dict(width_m=[0.01, [0.02]]), r"width_m must be a real number"),
        (dict(length_m=None), r"length_m must be a real number"),  # only the Rayleigh fields may be None
    ],
)
def test_bad_parameters_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        beam.modal_matrices(BeamParams(**kwargs), 2)


def test_a_dict_of_fields_is_refused_by_name():
    with pytest.raises(ValueError, match=r"params must be a BeamParams .*got dict"):
        beam.natural_frequencies_hz({"length_m": 1.2}, 2)
    # a configuration's arm too: a None field was dropped there, leaving the paper's value
    with pytest.raises(ValueError, match=r"beam thickness_m must be a finite number > 0; got None"):
        beam.plain_params(BeamParams(thickness_m=None))


@pytest.mark.parametrize("n", [0, -1, 2.0, True, 101, 227])
def test_bad_mode_count_is_rejected(n):
    with pytest.raises(ValueError, match="n_modes must be an integer in \\[1, 100\\]"):
        beam.natural_frequencies_hz(BeamParams(), n)


@pytest.mark.parametrize("payload_kg", [0.0, 0.1])
@pytest.mark.parametrize("hub", ["free", "clamped"])
def test_many_mode_frequencies_against_scipy_in_both_precisions(hub, payload_kg):
    """At 20 and 100 modes, against scipy's generalized symmetric eigensolver on the same
    matrices in float64. Stiffness grows as lambda^4 (1e10 between the first and the 100th
    mode), and the first frequencies came out 13 % off in float32 when each eigenvalue was
    resolved to the precision of the largest. Float32 now holds the first three to 2e-5 and
    every one to 2e-3, the bound eps32 f_n / f_1 of the method."""
    from scipy import linalg

    params = BeamParams(payload_mass_kg=payload_kg)
    params32 = BeamParams(*(jnp.float32(v) if v is not None else None for v in params))
    for n in (20, 100):
        M, K, *_ = (np.asarray(a, np.float64) for a in beam._structural(params, n)[:2])
        first = 1 if hub == "free" else 0  # the free hub's rigid-body zero
        if hub == "clamped":
            M, K = M[1:, 1:], K[1:, 1:]
        reference = np.sqrt(linalg.eigh(K, M, eigvals_only=True)[first:]) / (2 * np.pi)
        f64 = np.asarray(beam.natural_frequencies_hz(params, n, hub=hub))
        f32 = np.asarray(beam.natural_frequencies_hz(params32, n, hub=hub))
        assert f32.dtype == np.float32
        np.testing.assert_allclose(f64, reference, rtol=1e-6, err_msg=f"float64, {n} modes")
        np.testing.assert_allclose(f32[:3], reference[:3], rtol=2e-5, err_msg=f"float32, {n} modes")
        np.testing.assert_allclose(f32, reference, rtol=2e-3, err_msg=f"float32, {n} modes")


def test_float32_is_preserved():
    params = BeamParams(*(jnp.float32(v) if v is not None else None for v in BeamParams()))
    assert beam.modal_matrices(params, 2).M.dtype == jnp.float32


def test_mode_shapes_refuse_positions_off_the_beam():
    with pytest.raises(ValueError, match="x_over_l must be a 1-D array"):
        beam.mode_shapes(0.5, 2)
    with pytest.raises(ValueError, match=r"x_over_l must lie in \[0, 1\]"):
        beam.mode_shapes(np.array([0.5, 2.0]), 2)


def test_rayleigh_alpha_damps_the_rigid_hub_rotation():
    """D = alpha M + beta K gives the rigid mode (K phi = 0) the eigenvalues 0 and -alpha: the
    hub's free rotation decays at rate alpha (README, Conventions); alpha = 0 leaves it free."""
    from jaxflex.plant import make_plant

    alpha, _ = beam.rayleigh_coefficients(BeamParams())
    for a, expected in ((float(alpha), float(alpha)), (0.0, 0.0)):
        plant = make_plant(BeamParams(rayleigh_alpha=a, rayleigh_beta=6.4e-5))
        eig = np.linalg.eigvals(np.asarray(plant.A, dtype=float))
        real = eig[np.abs(eig.imag) < 1e-9].real
        np.testing.assert_allclose(np.sort(real)[-2:], [-expected, 0.0], atol=1e-9 + 1e-6 * expected)


def test_params_from_mapping_reads_a_config_table():
    """A config's [beam] table: missing fields keep the paper's values, NumPy numbers become
    floats, and a typo, a non-number or an out-of-range value is refused by name."""
    arm = beam.params_from_mapping({"length_m": 0.6, "payload_mass_kg": np.float64(0.05)})
    assert arm == BeamParams(length_m=0.6, payload_mass_kg=0.05) and type(arm.payload_mass_kg) is float
    assert beam.plain_params(BeamParams(density_kg_m3=np.float32(2700.0))).density_kg_m3 == 2700.0
    for table, match in (
        ({"lenght_m": 1.0}, r"unknown beam key\(s\) \['lenght_m'\]"),
        ({"length_m": "1"}, "beam length_m must be a finite number > 0"),
        ({"payload_mass_kg": float("nan")}, "beam payload_mass_kg must be a finite number >= 0"),
        ({"length_m": -1.0}, "beam length_m must be a finite number > 0"),  # it said >= 0, then refused 0
        ({"length_m": 0.0}, "beam length_m must be a finite number > 0"),
        ({"payload_mass_kg": 0.0, "length_m": 0.6}, None),
        ({"rayleigh_alpha": 1.0}, "must be given together"),
        (5, "beam must be a table of keys"),
    ):
        if match is None:
            beam.params_from_mapping(table)  # a zero payload is an arm without one
            continue
        with pytest.raises(ValueError, match=match):
            beam.params_from_mapping(table)
    with pytest.raises(ValueError, match="beam must be a BeamParams"):
        beam.plain_params({"length_m": 1.0})


def test_exact_frequencies_of_a_heavy_hub_approach_the_cantilever():
    """A very heavy hub clamps the beam: the exact frequencies tend to the clamped-free roots of
    cos(l) cosh(l) = -1 (found here by brentq), and the assumed-mode ones stay above them. The
    hub row of the frequency determinant once swamped the tip rows there (review: mode 4 off
    by 1.35e-3 at I_H = 1e6 kg m^2 and below the assumed-mode model)."""
    params = BeamParams(hub_inertia_kg_m2=1e9)  # the hub-to-beam inertia ratio (~1e-11) sets how far from clamped
    rho_a = params.density_kg_m3 * params.width_m * params.thickness_m
    e_i = params.youngs_modulus_pa * params.width_m * params.thickness_m**3 / 12
    roots = [optimize.brentq(lambda x: math.cos(x) * math.cosh(x) + 1, (k - 1) * math.pi, k * math.pi, xtol=1e-15) for k in range(1, 5)]
    cantilever = np.array(roots) ** 2 / (2 * math.pi) * math.sqrt(e_i / (rho_a * params.length_m**4))
    exact = beam.exact_natural_frequencies_hz(params, 4)
    np.testing.assert_allclose(exact, cantilever, rtol=1e-9)
    assumed = np.asarray(beam.natural_frequencies_hz(params, 8))[:4]
    assert np.all(assumed >= exact * (1 - 1e-12))


def test_derived_rayleigh_coefficients_damp_both_flexible_modes():
    """The derived (alpha, beta) are 2 z w1 w2 / (w1 + w2) and 2 z / (w1 + w2) of the 2-mode
    model's flexible frequencies (scipy's generalised eigenvalues), and both flexible modes
    stay oscillatory with ratio z (an empty set of oscillatory modes must not pass)."""
    from scipy import linalg

    z = 0.02
    params = BeamParams(damping_ratio=z)
    mats = beam.modal_matrices(params, 2)
    m, k, d = (np.asarray(a) for a in (mats.M, mats.K, mats.D))
    w1, w2 = np.sqrt(linalg.eigh(k, m, eigvals_only=True)[1:])
    alpha, beta = beam.rayleigh_coefficients(params)
    np.testing.assert_allclose([float(alpha), float(beta)], [2 * z * w1 * w2 / (w1 + w2), 2 * z / (w1 + w2)], rtol=1e-9)
    np.testing.assert_allclose(d, 2 * z * w1 * w2 / (w1 + w2) * m + 2 * z / (w1 + w2) * k, rtol=1e-9, atol=1e-15)
    n_q = 3
    a = np.block([[np.zeros((n_q, n_q)), np.eye(n_q)], [-np.linalg.solve(m, k), -np.linalg.solve(m, d)]])
    osc = np.linalg.eigvals(a)
    osc = osc[osc.imag > 1e-6]
    assert osc.shape == (2,)
    np.testing.assert_allclose(np.sort(np.abs(osc)), [w1, w2], rtol=1e-9)
    np.testing.assert_allclose(-osc.real / np.abs(osc), z, rtol=1e-9)


@pytest.mark.parametrize("positions", [[0.5, 1.0 + 1e-6], [-1e-6, 0.5], [1.2]])
def test_mode_shapes_refuse_positions_just_off_the_beam(positions):
    with pytest.raises(ValueError, match=r"x_over_l must lie in \[0, 1\]"):
        beam.mode_shapes(np.array(positions), 2)
    beam.mode_shapes(np.array([0.0, 1.0]), 2)  # both ends are on the beam


def test_the_most_modes_accepted_are_computed():
    freqs = np.asarray(beam.natural_frequencies_hz(BeamParams(), beam.MAX_MODES))
    assert np.all(np.isfinite(freqs)) and np.all(np.diff(freqs) > 0)


@pytest.mark.parametrize(
    "params, match",
    [
        ({"length_m": 1.2}, r"params must be a BeamParams .*got dict"),
        (BeamParams(length_m="0.9"), r"BeamParams\.length_m must be a real number; got '0\.9'"),
        (BeamParams(width_m=[0.01, 0.02]), r"BeamParams\.width_m must be a scalar \(one arm; jax\.vmap over arms for a batch\); got shape \(2,\)"),
        (BeamParams(width_m=np.array([0.01, 0.02])), r"BeamParams\.width_m must be a scalar .*got shape \(2,\)"),
    ],
)
def test_every_public_arm_function_refuses_a_bad_arm_by_name(params, match):
    """make_plant read the fields (structural_dtype) before checking them: a dict failed with
    an AttributeError and a string with JAX's TypeError. A field holding an array (a batch of
    arms) passed the checks and failed deep in JAX with a reshape error, in make_plant,
    modal_matrices and natural_frequencies_hz alike."""
    from jaxflex.plant import make_plant

    for f in (make_plant, beam.modal_matrices, beam.natural_frequencies_hz, beam.exact_natural_frequencies_hz):
        with pytest.raises(ValueError, match=match):
            f(params, 2)
    # a batch of arms is jax.vmap's: one arm per call
    widths = jnp.array([0.015, 0.019008])
    batch = jax.vmap(lambda w: beam.natural_frequencies_hz(BeamParams(width_m=w), 2))(widths)
    np.testing.assert_allclose(batch[1], beam.natural_frequencies_hz(BeamParams(), 2), rtol=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"length_m": 1e-200}, r"params: the arm's frequency equation must be finite in float64, its scales > 0; got hub and payload ratios inf, nan, 0"),  # a ZeroDivisionError
        ({"length_m": 1e200}, r"params: the arm's frequency equation .*rho A L\^3 = inf kg m\^2"),  # an OverflowError
        ({"thickness_m": 1e-300}, r"params: the arm's frequency equation .*EI / \(rho A\) = 0 m\^4/s\^2"),
        ({"length_m": 1e100, "youngs_modulus_pa": 1e-300}, r"params: the arm's frequencies must be > 0 in float64; got \[0\. 0\.\] Hz"),  # returned
    ],
)
def test_exact_frequencies_refuse_an_arm_beyond_float64(kwargs, match):
    with pytest.raises(ValueError, match=match):
        beam.exact_natural_frequencies_hz(BeamParams(**kwargs))


def test_modal_damping_ratios_are_the_poles_ratios_and_refuse_nonsense():
    """Each flexible pole's -Re s / |s| of a 4-mode plant (float64) is the ratio given for
    its frequency; non-positive or NaN frequencies and a negative length are refused by name."""
    from jaxflex.plant import make_plant

    with jax.enable_x64(True):
        arm = beam.BeamParams()
        freqs = np.asarray(beam.natural_frequencies_hz(arm, 4))
        lam = np.linalg.eigvals(np.asarray(make_plant(arm, 4).A))
        poles = sorted(lam[lam.imag > 1.0], key=abs)
        np.testing.assert_allclose(np.asarray(beam.modal_damping_ratios(arm, freqs)), [-s.real / abs(s) for s in poles], rtol=1e-9)
    for bad in ([13.3, 0.0], [float("nan")], [-1.0]):
        with pytest.raises(ValueError, match=r"freqs_hz must be finite frequencies > 0 \(Hz\)"):
            beam.modal_damping_ratios(beam.BeamParams(), bad)
    with pytest.raises(ValueError, match="length_m"):
        beam.modal_damping_ratios(beam.BeamParams(length_m=-1.0), [13.3])
