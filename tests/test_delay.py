"""Delay line against collections.deque, fractional reads, and validation."""

from collections import deque

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex import delay


@pytest.mark.parametrize("capacity, d", [(1, 1), (5, 5), (8, 3), (8, 0)])
def test_ring_buffer_matches_deque_through_scan(capacity, d):
    rng = np.random.default_rng(0)
    ys = rng.normal(size=(40, 2))
    history = deque([ys[0]] * (capacity + 1), maxlen=capacity + 1)  # before t = 0: the first sample
    expected = []
    for y in ys:
        history.append(y)
        expected.append(history[-1 - d])

    def body(state, y):
        return delay.delay_step(state, y, d)

    _, got = jax.lax.scan(body, delay.delay_init(ys[0], capacity), jnp.asarray(ys))
    np.testing.assert_array_equal(np.asarray(got), np.array(expected))


def test_linear_read_is_exact_at_whole_samples_and_interpolates_between():
    ys = jnp.arange(20.0)[:, None] ** 2
    state = delay.delay_init(ys[0], 6)
    for y in ys:
        state = delay.delay_push(state, y)
    for d in range(7):
        np.testing.assert_allclose(delay.delay_read(state, d, "linear"), ys[-1 - d], rtol=1e-14)
        np.testing.assert_allclose(delay.delay_read(state, d, "nearest"), ys[-1 - d], rtol=1e-14)
    np.testing.assert_allclose(delay.delay_read(state, 2.25, "linear"), 0.75 * ys[-3] + 0.25 * ys[-4], rtol=1e-14)
    # float32's 0.005 / 1e-3 is 4.9999995: the nearest read rounds it to 5 samples, not down to 4
    d32 = np.float32(0.005) / np.float32(1e-3)
    assert d32 < 5
    np.testing.assert_array_equal(delay.delay_read(state, d32, "nearest"), ys[-6])
    np.testing.assert_array_equal(delay.delay_read(state, 4.4, "nearest"), ys[-5])
    # beyond the buffer the read is clamped to its oldest sample, and below 0 to the newest,
    # whatever the interpolation
    for interpolation in ("nearest", "linear", "cubic"):
        np.testing.assert_allclose(delay.delay_read(state, 6.7, interpolation), delay.delay_read(state, 6, interpolation), rtol=1e-14)
        for d in (-0.5, -1.0, -7.0):
            np.testing.assert_array_equal(delay.delay_read(state, d, interpolation), ys[-1])
    g = jax.grad(lambda d: delay.delay_read(state, d, "linear")[0])(2.25)
    np.testing.assert_allclose(g, ys[-4, 0] - ys[-3, 0], rtol=1e-14)


def test_whole_samples_is_relative_to_the_delay():
    """A float32 quotient tau / dt of a whole delay is off by round-off that grows with it
    (0.5 s / 1 ms is 499.99997 samples, 3e-5 from 500): still whole, traced or concrete; half
    a sample off is not."""
    for tau, whole in ((0.005, True), (0.03, True), (0.5, True), (0.0305, False), (0.5005, False)):
        d32 = jnp.float32(tau) / jnp.float32(1e-3)
        assert bool(jax.jit(delay.whole_samples)(d32)) is whole, (tau, d32)
        assert bool(delay.whole_samples(np.float32(tau) / np.float32(1e-3))) is whole, tau
        assert bool(delay.whole_samples(tau / 1e-3)) is whole, tau


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_gradient_at_the_ends_of_the_range_is_one_sided_and_whole(interpolation):
    """At d = capacity only the derivative from below exists, and at d = 0 the one from above:
    the read gives each in full (a min/max clamp halved them, splitting the gradient between
    its tied arguments)."""
    capacity = 6
    ys = jnp.arange(20.0)[:, None] ** 3  # y = k^3: the derivative in d differs on each side
    state = delay.delay_init(ys[0], capacity)
    for y in ys:
        state = delay.delay_push(state, y)
    read = lambda d: delay.delay_read(state, d, interpolation)[0]
    h = 1e-6
    below = (float(read(capacity)) - float(read(capacity - h))) / h
    above = (float(read(h)) - float(read(0.0))) / h
    np.testing.assert_allclose(float(jax.grad(read)(float(capacity))), below, rtol=1e-5)
    np.testing.assert_allclose(float(jax.grad(read)(0.0)), above, rtol=1e-5)


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"capacity must be an integer in \[1, 1000000\] \(samples\); got 0"):
        delay.delay_init(jnp.zeros(1), 0)
    with pytest.raises(ValueError, match=r"capacity must be an integer in \[1, 1000000\] \(samples\); got 1000000000000"):
        delay.delay_init(jnp.zeros(1), 10**12)  # terabytes: it failed in the allocator
    for bad in (jnp.zeros(()), jnp.zeros((2, 2, 2))):  # (n,) is one line, (n, B) a batch of them
        with pytest.raises(ValueError, match="y0 must have shape"):
            delay.delay_init(bad, 3)
    with pytest.raises(ValueError, match=r"y must have shape \(2,\)"):
        delay.delay_push(delay.delay_init(jnp.zeros(2), 3), jnp.zeros(()))
    with pytest.raises(ValueError, match="interpolation must be one of"):
        delay.delay_read(delay.delay_init(jnp.zeros(1), 3), 1, "sinc")


# --- cubic (4-point Lagrange) reads -------------------------------------------------------

RTOL_ROUND = 1e-12  # a few float64 round-offs on O(1..1e3) sample values
RTOL_QUARTIC = 1e-9  # an O(1) error read off as the difference of two O(1e6) values


def _filled(ys, capacity):
    """The delay line after pushing every row of ``ys`` (more rows than slots: it wraps)."""
    state = delay.delay_init(ys[0], capacity)
    for y in ys:
        state = delay.delay_push(state, y)
    return state


def _lagrange_reference(history, d, capacity):
    """Independent reference: scipy's Lagrange polynomial through the documented stencil.

    ``history[j]`` is the sample ``j`` steps back. Nodes floor(d) - 1 .. floor(d) + 2, shifted
    into 0..capacity at the ends (four nodes whenever capacity >= 3).
    """
    from scipy.interpolate import BarycentricInterpolator

    n_pts = min(4, capacity + 1)
    start = int(np.clip(np.floor(d) - 1, 0, capacity + 1 - n_pts))
    nodes = np.arange(start, start + n_pts, dtype=float)
    return BarycentricInterpolator(nodes, history[start : start + n_pts])(d)


def test_cubic_read_is_exact_at_whole_samples_including_the_clamped_ends():
    rng = np.random.default_rng(1)
    ys = jnp.asarray(rng.normal(size=(23, 2)))
    capacity = 7
    state = _filled(ys, capacity)
    for d in range(capacity + 1):
        np.testing.assert_array_equal(np.asarray(delay.delay_read(state, float(d), "cubic")), np.asarray(ys[-1 - d]))


@pytest.mark.parametrize("d", [1.25, 2.5, 3.999, 5.75])
def test_cubic_read_reproduces_cubic_polynomials_between_samples(d):
    """y(n) = cubic in the sample index n: the 4-point Lagrange read is exact (the Lagrange
    property). Interior delays 1 <= d <= capacity - 1 (centred stencil)."""
    n = np.arange(30.0)
    ys = 0.3 * n**3 - 2.0 * n**2 + 5.0 * n - 7.0
    state = _filled(jnp.asarray(ys)[:, None], 7)
    n_read = n[-1] - d  # the sample index being read, between samples
    expected = 0.3 * n_read**3 - 2.0 * n_read**2 + 5.0 * n_read - 7.0
    np.testing.assert_allclose(float(delay.delay_read(state, d, "cubic")[0]), expected, rtol=RTOL_ROUND)


@pytest.mark.parametrize("d", [0.3, 0.9, 6.2, 6.9])
def test_cubic_read_at_the_ends_is_still_exact_for_cubics_and_off_centre(d):
    """In the outermost intervals the stencil is shifted into the buffer: still four nodes,
    so cubics stay exact; for the quartic n^4 (fourth derivative / 4! = 1) the error
    ``f - p`` is exactly the node polynomial ``prod (d - node)`` of the shifted stencil,
    which pins the stencil."""
    capacity = 7
    n = np.arange(30.0)
    state3 = _filled(jnp.asarray(n**3)[:, None], capacity)
    n_read = n[-1] - d
    np.testing.assert_allclose(float(delay.delay_read(state3, d, "cubic")[0]), n_read**3, rtol=RTOL_ROUND)
    state4 = _filled(jnp.asarray(n**4)[:, None], capacity)
    start = 0 if d < 1 else capacity - 3
    node_poly = np.prod([d - (start + i) for i in range(4)])  # in units of delay samples
    np.testing.assert_allclose(n_read**4 - float(delay.delay_read(state4, d, "cubic")[0]), node_poly, rtol=RTOL_QUARTIC)


def test_cubic_read_through_scan_matches_independent_lagrange():
    """Random data through the ring buffer (it wraps several times) against scipy's
    barycentric Lagrange interpolation on the documented stencil, delays all over [0, cap]."""
    rng = np.random.default_rng(2)
    capacity = 6
    ys = rng.normal(size=(40, 3))
    delays = rng.uniform(0, capacity, size=40)
    delays[:4] = [0.0, capacity, 0.5, capacity - 0.5]

    def body(state, inputs):
        y, d = inputs
        return delay.delay_step(state, y, d, "cubic")

    _, got = jax.lax.scan(body, delay.delay_init(ys[0], capacity), (jnp.asarray(ys), jnp.asarray(delays)))
    padded = np.concatenate([np.repeat(ys[:1], capacity, axis=0), ys])  # history before t = 0 = ys[0]
    for i in range(len(ys)):
        history = padded[i + capacity :: -1][: capacity + 1]  # history[j]: j steps back
        expected = _lagrange_reference(history, delays[i], capacity)
        np.testing.assert_allclose(np.asarray(got[i]), expected, rtol=RTOL_ROUND, atol=RTOL_ROUND)


@pytest.mark.parametrize("capacity", [1, 2])
def test_cubic_read_in_tiny_buffers_uses_every_sample(capacity):
    """Capacity 1 (2 samples) reads linearly, capacity 2 (3 samples) quadratically."""
    n = np.arange(10.0)
    ys = n**capacity  # degree = number of samples - 1: reproduced exactly
    state = _filled(jnp.asarray(ys)[:, None], capacity)
    for d in np.linspace(0, capacity, 7):
        np.testing.assert_allclose(float(delay.delay_read(state, d, "cubic")[0]), (n[-1] - d) ** capacity, rtol=RTOL_ROUND)


def test_cubic_read_gradient_in_the_delay():
    """Between samples: the derivative of the Lagrange polynomial. At a whole sample: the
    derivative from above (JAX's floor picks the stencil of [d, d + 1)), which differs from
    the one from below (the read is only C0 there)."""
    rng = np.random.default_rng(3)
    ys = jnp.asarray(rng.normal(size=(20, 1)))
    capacity = 8
    state = _filled(ys, capacity)
    history = np.asarray(ys[::-1, 0])[: capacity + 1]

    def read(d):
        return delay.delay_read(state, d, "cubic")[0]

    def lagrange_slope(d, start):
        nodes = np.arange(start, start + 4, dtype=float)
        poly = np.polyfit(nodes, history[start : start + 4], 3)  # exact fit: 4 points, degree 3
        return np.polyval(np.polyder(poly), d)

    np.testing.assert_allclose(float(jax.grad(read)(3.4)), lagrange_slope(3.4, 2), rtol=1e-10)
    g_whole = float(jax.grad(read)(4.0))
    np.testing.assert_allclose(g_whole, lagrange_slope(4.0, 3), rtol=1e-10)  # from above: nodes 3..6
    assert abs(lagrange_slope(4.0, 2) - g_whole) > 1e-3 * abs(g_whole)  # from below: nodes 2..5, a kink


def test_changing_the_delay_does_not_retrace_a_cubic_read():
    traces = [0]
    state = _filled(jnp.asarray(np.arange(12.0))[:, None], 6)

    @jax.jit
    def read(d):
        traces[0] += 1  # runs only while tracing
        return delay.delay_read(state, d, "cubic")

    for d in (0.2, 2.5, 5.9, 6.0):
        read(jnp.asarray(d))
    assert traces[0] == 1


def test_numpy_integers_are_accepted_as_sizes():
    """check_n_modes took np.int64 while capacity and the Pade order refused it."""
    from jaxflex import pade

    assert delay.check_capacity(np.int64(8)) == 8 and type(delay.check_capacity(np.int64(8))) is int
    assert pade.check_order(np.int32(4)) == 4
    with pytest.raises(ValueError, match=r"capacity must be an integer in \[1, 1000000\]"):
        delay.check_capacity(np.float64(8.0))
