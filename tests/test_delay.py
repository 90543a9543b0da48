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
    g = jax.grad(lambda d: delay.delay_read(state, d, "linear")[0])(2.25)
    np.testing.assert_allclose(g, ys[-4, 0] - ys[-3, 0], rtol=1e-14)


def test_bad_arguments():
    with pytest.raises(ValueError, match="capacity must be an integer >= 1"):
        delay.delay_init(jnp.zeros(1), 0)
    with pytest.raises(ValueError, match="y0 must have shape"):
        delay.delay_init(jnp.zeros((2, 2)), 3)
    with pytest.raises(NotImplementedError, match="interpolation must be one of"):
        delay.delay_read(delay.delay_init(jnp.zeros(1), 3), 1, "sinc")
