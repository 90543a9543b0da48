"""Plant and discretisation: structure, literal RK4, order of convergence, scipy and python-control oracles."""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxflex import plant as plant_mod
from jaxflex.beam import BeamParams, natural_frequencies_hz
from jaxflex.plant import discretize, make_plant

RTOL_EXPM = 1e-10  # two expm implementations of the same matrix, float64
ATOL_EXPM = 1e-12  # expm is accurate relative to the matrix norm, not per element


def _literal_rk4(A, G, x, v, h):
    """Classical RK4 stage by stage for x' = A x + G v with v held over the step."""
    f = lambda s: A @ s + G @ v
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def test_state_space_structure():
    p = make_plant(BeamParams(), 3)
    n_q = 4
    A = np.asarray(p.A)
    np.testing.assert_array_equal(A[:n_q, :n_q], 0)
    np.testing.assert_array_equal(A[:n_q, n_q:], np.eye(n_q))
    assert p.B.shape == (8, 1) and p.E.shape == (8, 1) and p.C.shape == (2, 8) and p.Cz.shape == (3, 8)
    eig = np.linalg.eigvals(A)
    assert np.sum(np.abs(eig) < 1e-9) == 1  # the rigid-body position mode
    assert np.all(eig.real < 1e-9)
    # tip position = L * theta + tip deflection
    np.testing.assert_allclose(np.asarray(p.Cz[2]), 0.9 * np.asarray(p.Cz[0]) + np.asarray(p.Cz[1]))
    assert plant_mod.n_modes_of(p) == 3


def test_tip_force_generalised_input_matches_virtual_work():
    """A static tip force on a hub held by a torque: the tip force input equals M^-1 [L, phi_i(L)].
    The hub torque does work on theta alone: its input is M^-1 e_0 (before this check, an input
    without M^-1 failed only the stability analysis's tests)."""
    params = BeamParams()
    p = make_plant(params, 2)
    from jaxflex import beam

    mats = beam.modal_matrices(params, 2)
    np.testing.assert_array_equal(np.asarray(p.B[:3, 0]), 0.0)
    np.testing.assert_allclose(np.asarray(p.B[3:, 0]), np.linalg.solve(np.asarray(mats.M), [1.0, 0.0, 0.0]), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(p.E[3:, 0]), np.linalg.solve(np.asarray(mats.M), np.asarray(mats.tip_force_input)), rtol=1e-12)
    np.testing.assert_allclose(np.abs(np.asarray(mats.tip_force_input)), [0.9, 2.0, 2.0], rtol=1e-12)


def test_rk4_map_equals_literal_rk4():
    p = make_plant(BeamParams(), 2)
    dt = 1e-3
    d = discretize(p, dt, "rk4")
    rng = np.random.default_rng(0)
    x, v = rng.normal(size=6), rng.normal(size=2)
    G = np.concatenate([np.asarray(p.B), np.asarray(p.E)], axis=1)
    expected = _literal_rk4(np.asarray(p.A), G, x, v, dt)
    got = np.asarray(d.Ad) @ x + np.asarray(d.Bd) @ v[:1] + np.asarray(d.Ed) @ v[1:]
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-15)


def test_zoh_matches_scipy_expm_and_python_control_c2d():
    p = make_plant(BeamParams(), 2)
    dt = 1e-3
    d = discretize(p, dt, "zoh")
    A, B = np.asarray(p.A), np.asarray(p.B)
    block = np.zeros((7, 7))
    block[:6, :6], block[:6, 6:] = A, B
    phi = scipy.linalg.expm(block * dt)
    np.testing.assert_allclose(np.asarray(d.Ad), phi[:6, :6], rtol=RTOL_EXPM, atol=ATOL_EXPM * np.abs(phi).max())
    np.testing.assert_allclose(np.asarray(d.Bd), phi[:6, 6:], rtol=RTOL_EXPM, atol=ATOL_EXPM * np.abs(phi[:6, 6:]).max())
    sysd = control.c2d(control.ss(A, np.concatenate([B, np.asarray(p.E)], axis=1), np.asarray(p.C), 0), dt, method="zoh")
    np.testing.assert_allclose(np.asarray(d.Ad), sysd.A, rtol=RTOL_EXPM, atol=ATOL_EXPM * np.abs(sysd.A).max())
    np.testing.assert_allclose(np.asarray(d.Bd), sysd.B[:, :1], rtol=RTOL_EXPM, atol=ATOL_EXPM * np.abs(sysd.B[:, :1]).max())
    np.testing.assert_allclose(np.asarray(d.Ed), sysd.B[:, 1:], rtol=RTOL_EXPM, atol=ATOL_EXPM * np.abs(sysd.B[:, 1:]).max())


STIFF_ARM = BeamParams(length_m=0.5, width_m=0.025, thickness_m=0.02, youngs_modulus_pa=200e9, density_kg_m3=7850.0, hub_inertia_kg_m2=2e-3)


UNDAMPED_ARM = BeamParams(rayleigh_alpha=0.0, rayleigh_beta=0.0)


@pytest.mark.parametrize(
    "arm, n_modes, rtol",
    [
        (BeamParams(), 2, 1e-6),  # unbalanced: 9.5e-5
        (BeamParams(), 6, 1e-6),  # unbalanced: 6 %
        (STIFF_ARM, 3, 5e-5),  # modes 0.27-1.3 kHz; unbalanced: NaN (17 squarings), or unstable with more
        (UNDAMPED_ARM, 8, 1e-5),  # balancing every index at once (a 2-cycle) left 0.17 here
    ],
)
def test_float32_zoh_is_balanced(arm, n_modes, rtol):
    """A float32 ZOH against scipy's expm of the same (float32) plant in float64. The modal
    matrices are badly scaled; the balanced expm stays accurate, finite and as stable as the
    arm (error relative to each column's largest entry), and the balancing does balance."""
    p = make_plant(BeamParams(*(None if v is None else jnp.float32(v) for v in arm)), n_modes)
    d = discretize(p, 1e-3, "zoh")
    assert d.Ad.dtype == jnp.float32
    n = p.A.shape[0]
    block = np.zeros((n + 2, n + 2))
    block[:n, :n] = np.asarray(p.A, float)
    block[:n, n:] = np.concatenate([np.asarray(p.B, float), np.asarray(p.E, float)], axis=1)
    phi = scipy.linalg.expm(block * 1e-3)
    got = np.concatenate([np.asarray(m, float) for m in (d.Ad, d.Bd, d.Ed)], axis=1)
    error = np.max(np.abs(got - phi[:n]) / np.abs(phi[:n]).max(axis=0))
    assert error < rtol, error
    assert np.max(np.abs(np.linalg.eigvals(np.asarray(d.Ad, float)))) <= 1 + 1e-6
    scale = np.asarray(plant_mod._balancing_scales(jnp.asarray(block * 1e-3, jnp.float32)), float)
    balanced = np.abs(block * 1e-3) * scale[None, :] / scale[:, None]
    np.fill_diagonal(balanced, 0.0)
    rows, cols = balanced.sum(axis=1), balanced.sum(axis=0)
    live = (rows > 0) & (cols > 0)
    assert np.all(np.log2(scale) == np.round(np.log2(scale)))  # powers of 2: an exact similarity
    assert np.max(np.maximum(rows[live] / cols[live], cols[live] / rows[live])) <= 2.0


def test_rk4_converges_to_zoh_at_fourth_order():
    """Same held-input signal over 0.2 s: the sup-over-time RK4 error (per state, relative to that
    state's peak) falls by 2^4 per halving of dt, from the paper's 1 kHz down."""
    p = make_plant(BeamParams(), 2)
    x0 = np.array([0.0, 1e-3, 0.0, 0.0, 1e-5, 0.0])
    errors = []
    for dt in (1e-3, 5e-4, 2.5e-4, 1.25e-4):
        steps = int(round(0.2 / dt))
        u = 0.05 * np.sin(2 * np.pi * 3 * np.arange(steps) * dt)  # held input, sampled at each dt
        runs = {}
        for method in ("rk4", "zoh"):
            d = discretize(p, dt, method)
            Ad, Bd = np.asarray(d.Ad), np.asarray(d.Bd)
            x, states = x0.copy(), []
            for k in range(steps):
                x = Ad @ x + Bd[:, 0] * u[k]
                states.append(x)
            runs[method] = np.array(states)
        errors.append(np.max(np.abs(runs["rk4"] - runs["zoh"]) / np.max(np.abs(runs["zoh"]), axis=0)))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(orders, 4.0, atol=0.1)
    assert errors[0] < 1e-3  # 1 kHz, the paper's setting: 0.05 % of each state's peak


def test_discretize_differentiable_against_fd():
    def f(E):
        p = make_plant(BeamParams(youngs_modulus_pa=E), 2)
        return discretize(p, 1e-3, "zoh").Ad[1, 4] + discretize(p, 1e-3, "rk4").Bd[4, 0]

    E = 71e9
    g = float(jax.grad(f)(E))
    h = 1e-4 * E
    fd = (float(f(E + h)) - float(f(E - h))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


@pytest.mark.parametrize("dt, match", [(0.0, "dt must be"), (-1e-3, "dt must be"), (float("nan"), "dt must be"), (np.ones(2), "dt must be"), ("1e-3", "dt must be a real number")])
def test_bad_dt_is_rejected(dt, match):
    with pytest.raises(ValueError, match=match):
        discretize(make_plant(), dt)


def test_unknown_method_is_rejected():
    with pytest.raises(ValueError, match="method must be one of"):
        discretize(make_plant(), 1e-3, "euler")


def test_float32_is_preserved():
    params = BeamParams(*(jnp.float32(v) if v is not None else None for v in BeamParams()))
    d = discretize(make_plant(params, 2), 1e-3, "zoh")
    assert d.Ad.dtype == jnp.float32 and d.Bd.dtype == jnp.float32


def _rk4_ad(plant, dt):
    """The RK4 map at ``dt`` as it is: ``discretize`` refuses an amplifying step unless asked
    not to, and a traced ``dt`` (jit, vmap over steps) gives the same map unchecked."""
    ad = np.asarray(discretize(plant, dt, "rk4", check_rk4=False).Ad)
    np.testing.assert_array_equal(ad, np.asarray(jax.jit(lambda d: discretize(plant, d, "rk4").Ad)(dt)))
    return ad


def test_rk4_step_that_amplifies_a_mode_is_refused_by_the_configs():
    """A stiff arm (modes at 216 and 695 Hz) at 1 ms: one RK4 step multiplies the 695 Hz mode
    by |R(i omega dt)| > 1 (omega dt = 4.37 > 2.83), so tune and montecarlo ran NaN and blamed
    the learning rate. The configs now refuse it by name, and so does discretize itself (it
    returned the growing map); ZOH, or a short enough dt, is fine."""
    from jaxflex.beam import natural_frequencies_hz
    from jaxflex.montecarlo import MCConfig
    from jaxflex.plant import check_rk4_step
    from jaxflex.scenarios import ScenarioSpec
    from tuning.tuner import TuneConfig

    stiff = BeamParams(length_m=0.25, thickness_m=8e-3)
    plant = make_plant(stiff, 2)
    omega = 2 * np.pi * np.asarray(natural_frequencies_hz(stiff, 2)).max()
    assert np.abs(np.linalg.eigvals(_rk4_ad(plant, 1e-3))).max() > 1  # what the check stands for
    message = r"method = 'rk4' with dt = 0.001 s is unstable for this arm: its mode at 69\d.\d Hz has omega dt = 4.3\d"
    with pytest.raises(ValueError, match=message):
        discretize(plant, 1e-3)
    # a thickness typed in mm (5 m) failed here, before tune printed its model, and the advice
    # (method = 'zoh') would have tuned a 5 m thick link: the message says to check units first
    with pytest.raises(ValueError, match=r"Use method = 'zoh' \(exact for any dt\) or dt <= \S+ s, once the arm, dt and the 2 modes are what you meant: a unit slip \(a thickness in mm, dt in ms\) gives this too, and so do more modes than the sample time holds \(each adds a faster one\)$"):
        discretize(make_plant(BeamParams(thickness_m=5.0), 2), 1e-3)
    # 50 modes of the paper's arm (n_modes = 50 was blamed on a unit slip alone): the mode count is named
    with pytest.raises(ValueError, match=r"the 50 modes are what you meant: .*and so do more modes than the sample time holds \(each adds a faster one\)$"):
        discretize(make_plant(BeamParams(), 50), 1e-3)
    discretize(plant, 1e-3, "zoh")
    with pytest.raises(ValueError, match="check_rk4 must be True or False; got 0"):
        discretize(plant, 1e-3, check_rk4=0)
    for make in (MCConfig, TuneConfig):
        with pytest.raises(ValueError, match=message):
            make(beam=stiff)
        make(beam=stiff, method="zoh")
        make(beam=stiff, scenarios=ScenarioSpec(dt=2.7 / omega))
    check_rk4_step(make_plant(BeamParams(), 4), 1e-3)  # the paper's arm, even with 4 modes
    for dt in (-1e-3, 0.0, float("nan")):
        with pytest.raises(ValueError, match="dt must be a finite scalar > 0"):
            check_rk4_step(plant, dt)
    assert np.abs(np.linalg.eigvals(np.asarray(discretize(plant, 2.7 / omega, "rk4").Ad))).max() <= 1


def test_rk4_step_check_refuses_exactly_where_the_rk4_map_grows():
    """On either side of the largest stable step, found on the RK4 map itself (its spectral
    radius, the rigid-body eigenvalue 1 included), the check passes and then refuses: one step
    past it the map grows by about 0.7 % per step."""
    from jaxflex.plant import check_rk4_step

    plant = make_plant(BeamParams(length_m=0.25, thickness_m=8e-3), 2)

    def grows(dt):
        return np.abs(np.linalg.eigvals(_rk4_ad(plant, dt))).max() > 1 + 1e-9

    lo, hi = 3e-4, 1e-3  # stable, unstable
    assert not grows(lo) and grows(hi)
    for _ in range(50):
        lo, hi = (lo, (lo + hi) / 2) if grows((lo + hi) / 2) else ((lo + hi) / 2, hi)
    check_rk4_step(plant, lo * (1 - 1e-3))
    assert np.abs(np.linalg.eigvals(_rk4_ad(plant, hi * (1 + 1e-3)))).max() < 1.01
    with pytest.raises(ValueError, match="method = 'rk4' with dt"):
        check_rk4_step(plant, hi * (1 + 1e-3))


def test_rk4_amplified_omega_is_the_fastest_amplified_mode_and_skips_growing_ones():
    """At a step that amplifies both flexible modes of the stiff arm the report is the faster
    one (|lambda| = omega_n for Rayleigh damping); a mode that the continuous plant grows
    itself (Re lambda > 0) is not blamed on RK4."""
    from jaxflex.beam import natural_frequencies_hz
    from jaxflex.plant import rk4_amplified_omega

    stiff = BeamParams(length_m=0.25, thickness_m=8e-3)
    plant = make_plant(stiff, 2)
    omega = 2 * np.pi * np.asarray(natural_frequencies_hz(stiff, 2))
    dt = 4e-3
    assert np.all(omega * dt > 2.83)  # both modes amplified by one step
    np.testing.assert_allclose(rk4_amplified_omega(plant, dt), omega[1], rtol=1e-9)
    assert rk4_amplified_omega(plant, 1e-4) is None
    # A growing mode (lambda = +10/s, |R(10 dt)| > 1) next to a decaying oscillation
    # lambda = -1 +- 4000i (|R| > 1 at dt = 1 ms): only the oscillation is reported.
    a = np.zeros((3, 3))
    a[0, 0] = 10.0
    a[1:, 1:] = [[-1.0, 4000.0], [-4000.0, -1.0]]
    growing = plant._replace(A=jnp.asarray(a))
    np.testing.assert_allclose(rk4_amplified_omega(growing, 1e-3), np.hypot(1.0, 4000.0), rtol=1e-12)
    assert rk4_amplified_omega(plant._replace(A=jnp.asarray([[10.0]])), 1e-3) is None


def test_rk4_amplification_of_an_undamped_arm_is_found():
    """An undamped mode's eigenvalues have real parts of round-off size, of either sign: the
    one at +3e-15 was taken for a growing mode, and an RK4 step of 20 ms on the undamped arm,
    which multiplies mode 2 by 14 each step, was accepted."""
    from jaxflex.beam import natural_frequencies_hz
    from jaxflex.plant import rk4_amplified_omega

    undamped = BeamParams(damping_ratio=0.0)
    omega = 2 * np.pi * np.asarray(natural_frequencies_hz(undamped, 2))
    dt = 0.02
    gain = np.abs(np.polyval([1 / 24, 1 / 6, 1 / 2, 1, 1], 1j * omega * dt))  # |R(i omega dt)|
    assert gain[0] < 1 < gain[1]  # mode 1 (84 rad/s) held, mode 2 (229 rad/s) amplified
    plant = make_plant(undamped, 2)
    np.testing.assert_allclose(rk4_amplified_omega(plant, dt), omega[1], rtol=1e-9)
    with pytest.raises(ValueError, match=r"method = 'rk4' with dt = 0.02 s is unstable for this arm: its mode at 36.47 Hz has omega dt = 4.58"):
        discretize(plant, dt, "rk4")


def test_measurement_and_performance_maps_read_the_documented_states():
    """x = [theta, q_1..q_n, theta_dot, q_dot...]: y = [theta, theta_dot]; z = [theta,
    sum_i phi_i(L) q_i, L theta + w(L)] with |phi_i(L)| = 2 (the normalisation)."""
    for n in (1, 3):
        p = make_plant(BeamParams(length_m=1.3), n)
        n_q = n + 1
        expected_c = np.zeros((2, 2 * n_q))
        expected_c[0, 0] = expected_c[1, n_q] = 1.0
        np.testing.assert_array_equal(np.asarray(p.C), expected_c)
        cz = np.asarray(p.Cz)
        np.testing.assert_array_equal(cz[0], expected_c[0])
        np.testing.assert_array_equal(cz[1, [0, *range(n_q, 2 * n_q)]], 0.0)
        np.testing.assert_allclose(np.abs(cz[1, 1:n_q]), 2.0, rtol=1e-12)
        np.testing.assert_allclose(cz[2], 1.3 * expected_c[0] + cz[1], rtol=1e-15)


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("youngs_modulus_pa", 1e39, r"BeamParams.youngs_modulus_pa must be in \[1.175e-38, 3.403e\+38\] to be simulated in float32 .*; got 1e\+39"),
        ("hub_inertia_kg_m2", 1e39, r"BeamParams.hub_inertia_kg_m2 must be in \[1.175e-38, 3.403e\+38\] to be simulated in float32"),
        ("density_kg_m3", 1e-40, r"BeamParams.density_kg_m3 must be in \[1.175e-38, 3.403e\+38\] to be simulated in float32 .*; got 1e-40"),
        ("damping_ratio", 1e39, r"BeamParams.damping_ratio must be in \[0, 3.403e\+38\] to be simulated in float32"),
        ("length_m", 1e20, r"the plant's A must be finite in float32; got inf or NaN for BeamParams\(length_m=1e\+20"),
    ],
)
def test_arm_that_overflows_float32_is_refused_by_name(field, value, match):
    """A value finite in float64 (what configs are checked in) but not in the float32 of the
    run, or one whose plant matrices overflow float32, was built into an inf/NaN plant; and
    natural_frequencies_hz returned NaN frequencies for them."""
    arm = BeamParams(**{field: value})
    frequencies = match.replace(r"the plant's A must be finite", r"the natural frequencies of the 2-mode model must be finite")
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match=match):
            make_plant(arm)
        with pytest.raises(ValueError, match=frequencies):
            natural_frequencies_hz(arm)
    assert all(np.all(np.isfinite(m)) for m in make_plant(arm))  # float64 holds it
    assert np.all(np.isfinite(natural_frequencies_hz(arm)))


def test_sampled_plant_that_overflows_is_refused():
    """A stiff arm's RK4 polynomial in float32 overflows (the exact ZOH does not). The step
    is refused first for what makes it overflow: it amplifies the arm's modes; traced, the
    map itself is checked."""
    with jax.enable_x64(False):
        stiff = make_plant(BeamParams(youngs_modulus_pa=1e38))
        with pytest.raises(ValueError, match=r"method = 'rk4' with dt = 0.001 s is unstable for this arm"):
            discretize(stiff, 1e-3, "rk4")
        assert not np.all(np.isfinite(np.asarray(jax.jit(lambda d: discretize(stiff, d, "rk4").Ad)(1e-3))))
        assert np.all(np.isfinite(discretize(stiff, 1e-3, "zoh").Ad))


def test_an_already_sampled_plant_is_refused_by_name():
    """discretize and the RK4 check read plant.A: a DiscretePlant failed with an AttributeError."""
    sampled = discretize(make_plant(BeamParams(), 2), 1e-3, "rk4")
    match = r"plant must be a LinearPlant \(build one with make_plant\(...\); a DiscretePlant is already sampled\); got DiscretePlant"
    with pytest.raises(ValueError, match=match):
        discretize(sampled, 1e-3, "zoh")
    with pytest.raises(ValueError, match=match):
        plant_mod.check_rk4_step(sampled, 1e-3)


def test_make_plant_jacobian_in_every_parameter_against_fd():
    """The continuous matrices A, B, E in each BeamParams field (the frequencies' gradients,
    test_beam.py, do not see damping, and the rollout's only E): one forward-mode Jacobian, with
    the Rayleigh coefficients derived from damping_ratio (the default branch; given ones enter
    D linearly), against central differences. A payload is set so that its fields act. h = 1e-5 relative: truncation ~1e-10,
    round-off ~1e-11 relative to each matrix's largest entry."""
    base = BeamParams(payload_mass_kg=0.02, payload_inertia_kg_m2=1e-5)
    names = [f for f in BeamParams._fields if getattr(base, f) is not None]
    x = np.array([float(getattr(base, f)) for f in names])

    def maps(v):
        p = make_plant(base._replace(**dict(zip(names, v * x))), 2)  # relative parameters
        return jnp.concatenate([p.A.ravel(), p.B.ravel(), p.E.ravel()])

    value_and_jac = jax.jit(lambda v: (maps(v), jax.jacfwd(maps)(v)))  # one compilation
    jac = np.asarray(value_and_jac(jnp.ones(len(names)))[1])
    f = lambda v: value_and_jac(v)[0]  # noqa: E731
    h = 1e-5
    for i, name in enumerate(names):
        e = np.zeros(len(names))
        e[i] = h
        fd = (np.asarray(f(1 + e)) - np.asarray(f(1 - e))) / (2 * h)
        assert np.max(np.abs(fd)) > 0, name
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-6, atol=1e-7 * np.max(np.abs(fd)), err_msg=name)


def test_discretize_takes_a_traced_dt():
    """jit, vmap and grad over the sample time: discretize formatted ``float(dt)`` into its
    finiteness message before looking at whether the maps were traced, so a traced dt failed
    with a ConcretizationTypeError. Oracles: the eager plant at each dt, and for ZOH
    d Ad / d dt = A Ad (Ad = expm(A dt))."""
    cont = make_plant(BeamParams(), 2)
    dts = jnp.array([5e-4, 1e-3, 2e-3])
    for method in ("zoh", "rk4"):
        batch = jax.vmap(lambda dt: discretize(cont, dt, method).Ad)(dts)
        for i, dt in enumerate([5e-4, 1e-3, 2e-3]):
            np.testing.assert_allclose(batch[i], discretize(cont, dt, method).Ad, rtol=1e-12, atol=1e-14)
    d_ad = jax.jacfwd(lambda dt: discretize(cont, dt, "zoh").Ad)(1e-3)
    expected = np.asarray(cont.A) @ np.asarray(discretize(cont, 1e-3, "zoh").Ad)
    np.testing.assert_allclose(d_ad, expected, rtol=1e-9, atol=1e-9 * np.max(np.abs(expected)))
