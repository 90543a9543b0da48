"""jaxflex: a differentiable JAX simulator and tuner for vibration control of flexible arms.

Conventions: SI units; time is the first axis of every signal (``[T, n]``, batches
``[B, T, n]``), unlike python-control's ``(n, T)``; state
``x = [theta, q_1..q_n, theta_dot, q_1_dot..q_n_dot]``; float32 unless the caller enables
float64 (jaxflex never changes the JAX configuration itself).
"""

from jaxflex.beam import BeamParams, exact_natural_frequencies_hz, modal_matrices, natural_frequencies_hz
from jaxflex.plant import DiscretePlant, LinearPlant, discretize, make_plant
from jaxflex.rollout import Trajectory, rollout
from jaxflex.scenarios import Scenario, paper_scenario

__version__ = "0.1.0"

__all__ = [
    "BeamParams",
    "DiscretePlant",
    "LinearPlant",
    "Scenario",
    "Trajectory",
    "discretize",
    "exact_natural_frequencies_hz",
    "make_plant",
    "modal_matrices",
    "natural_frequencies_hz",
    "paper_scenario",
    "rollout",
]
