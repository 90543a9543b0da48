"""Linear PD controller on the measured hub angle and velocity: ``u = -(kp theta + kd theta_dot)``."""

from __future__ import annotations

from typing import NamedTuple

import jax
from jax.typing import ArrayLike

from jaxflex.controllers.base import Controller, check_params_type, check_scalar_param


class PDParams(NamedTuple):
    """Attributes: kp: proportional gain (N*m/rad); kd: derivative gain (N*m*s/rad)."""

    kp: ArrayLike = 1.0
    kd: ArrayLike = 0.1


def pd() -> Controller:
    """The linear PD controller (stateless)."""

    def init(params: PDParams, y0: jax.Array) -> tuple[()]:
        del params, y0
        return ()

    def step(params: PDParams, state: tuple[()], y: jax.Array) -> tuple[tuple[()], jax.Array]:
        return state, -(params.kp * y[:1] + params.kd * y[1:2])

    def check(params: PDParams) -> None:
        check_params_type(params, PDParams)
        check_scalar_param("kp", params.kp)
        check_scalar_param("kd", params.kd)

    return Controller(init, step, check, batched=True)
