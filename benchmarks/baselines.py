"""Baselines for ``bench_rollout.py``: the same closed loop written with NumPy, python-control
and scikit-fuzzy.

Every baseline simulates the plant, controllers and scenarios of ``jaxflex.bench``
(``bench_plant``, ``controller_and_params``, ``bench_inputs``) and is checked against the
jaxflex trajectory before it is timed (``bench_rollout.py --section baselines``,
``tests/test_bench.py``).

* ``numpy_closed_loop``: what a skilled NumPy user writes: the time loop in Python, the
  batch in arrays laid out state-major (``X`` [n_x, B], so ``Ad @ X`` is one matmul), the
  delay line a ``[capacity + 1, B]`` ring buffer, and the fuzzy controller as a vectorised
  version of the same exact closed-form centroid jaxflex uses (memberships ``[n_sets, B]``,
  rule strengths by fancy indexing, group maxima, per-interval areas and moments). Float32
  or float64 follows the inputs.
* ``python_control_closed_loop``: one scenario through ``control.input_output_response``:
  the DFS+fuzzy controller as a discrete ``control.nlsys`` (dt = 1 ms) whose states are the
  delay register, interconnected with the discrete plant ``control.ss(Ad, [Bd Ed], C, 0, dt)``.
* ``skfuzzy_closed_loop``: one scenario, one ``ControlSystemSimulation.compute`` per sample
  (scikit-fuzzy's Mamdani inference on a sampled universe; needs ``networkx``), inside a
  Python loop with the NumPy plant and delay line.
"""

from __future__ import annotations

import warnings
from typing import Any, NamedTuple

import numpy as np

from jaxflex.controllers.fuzzy import PAPER_RULES, SET_NAMES


class LoopSpec(NamedTuple):
    """A controller in plain numbers (what every baseline needs).

    Attributes:
      kind: "open_loop", "dfs", "fuzzy" or "dfs+fuzzy".
      k: DFS gain (N*m/rad); delay_steps: DFS delay in samples; capacity: ring-buffer size.
      k1, k2, k3: fuzzy scalings; centres: (angle, velocity, torque) centres, each [n_sets].
      defuzz: "centroid" or "singleton".
    """

    kind: str
    k: float = 55.0
    delay_steps: int = 5
    capacity: int = 64
    k1: float = 1.02
    k2: float = 0.30
    k3: float = 1.0
    centres: tuple = ((-1.0, -0.5, 0.0, 0.5, 1.0),) * 3
    defuzz: str = "centroid"

    @property
    def has_dfs(self) -> bool:
        return "dfs" in self.kind

    @property
    def has_fuzzy(self) -> bool:
        return "fuzzy" in self.kind


def rule_indices(rules=PAPER_RULES, set_names=SET_NAMES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(angle, velocity, torque) set indices of each rule, each [n_rules]."""
    pos = {n: i for i, n in enumerate(set_names)}
    idx = np.array([[pos[a], pos[v], pos[t]] for a, v, t in rules])
    return idx[:, 0], idx[:, 1], idx[:, 2]


def _feet(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left and right feet of each triangle (outer feet mirrored), each [n_sets]."""
    left = np.concatenate([[2 * c[0] - c[1]], c[:-1]])
    right = np.concatenate([c[1:], [2 * c[-1] - c[-2]]])
    return left, right


def fuzzy_surface_np(e: np.ndarray, e_dot: np.ndarray, spec: LoopSpec) -> np.ndarray:
    """Vectorised exact Mamdani surface F(e, e_dot) [B] (jaxflex's closed form, in NumPy)."""
    dtype = e.dtype
    ca, cv, ct = (np.asarray(c, dtype) for c in spec.centres)
    ia, iv, it = rule_indices()

    def mu(x, c):  # [n_sets, B]
        x = np.clip(x, c[0], c[-1])
        left, right = _feet(c)
        rise = (x[None, :] - left[:, None]) / (c - left)[:, None]
        fall = (right[:, None] - x[None, :]) / (right - c)[:, None]
        return np.maximum(np.minimum(rise, fall), 0)

    w = np.minimum(mu(e, ca)[ia], mu(e_dot, cv)[iv])  # [n_rules, B]
    n = ct.shape[0]
    if spec.defuzz == "singleton":
        den = w.sum(axis=0)
        num = (w * ct[it][:, None]).sum(axis=0)
    else:
        s = np.zeros((n,) + e.shape, dtype)
        for j in range(n):
            rows = it == j
            if rows.any():
                s[j] = w[rows].max(axis=0)
        a, b = s[:-1], s[1:]  # [n - 1, B]
        h = (ct[1:] - ct[:-1])[:, None]
        area_g = a - a * a / 2
        moment_g = (1 - (1 - a) ** 3) / 6
        area_k = b - b * b / 2
        moment_k = area_k - (1 - (1 - b) ** 3) / 6
        cc = np.minimum(np.minimum(a, b), 0.5)
        area_m = cc - cc * cc
        area = area_g + area_k - area_m
        moment = moment_g + moment_k - area_m / 2
        den = (h * area).sum(axis=0)
        num = (h * (ct[:-1, None] * area + h * moment)).sum(axis=0)
    fires = den > 0
    return np.where(fires, num / np.where(fires, den, 1), 0).astype(dtype)


def numpy_closed_loop(plant: dict[str, np.ndarray], spec: LoopSpec, x0: np.ndarray, force: np.ndarray, noise: np.ndarray, record: bool = False) -> dict[str, Any]:
    """Batched closed loop in NumPy: Python time loop, batch in arrays.

    Args:
      plant: ``Ad`` [n_x, n_x], ``Bd`` [n_x, 1], ``Ed`` [n_x, 1], ``C`` [2, n_x], ``Cz`` [3, n_x]
        and ``dt``, NumPy arrays of the working dtype.
      spec: the controller.
      x0: [B, n_x] initial states; force: [T, 1] and noise: [T, 2], shared by the batch.
      record: also return the trajectories ``x`` [T, B, n_x] and ``u`` [T, B].

    Returns:
      ``tip_ise`` [B], ``control_effort`` [B], ``peak_tip`` [B], ``x_end`` [B, n_x] (and the
      trajectories when ``record``).
    """
    Ad, Bd, Ed, C, Cz = (plant[k] for k in ("Ad", "Bd", "Ed", "C", "Cz"))
    dt = plant["dt"]
    X = np.ascontiguousarray(x0.T)  # [n_x, B] state-major
    steps, batch = force.shape[0], X.shape[1]
    dtype = X.dtype
    size = spec.capacity + 1
    buf = None
    tip_ise = np.zeros(batch, dtype)
    effort = np.zeros(batch, dtype)
    peak = np.zeros(batch, dtype)
    xs, us = [], []
    for k in range(steps):
        Y = C @ X + noise[k][:, None]  # [2, B]
        U = np.zeros(batch, dtype)
        if spec.has_dfs:
            theta = Y[0]
            if buf is None:
                buf = np.repeat(theta[None, :], size, axis=0)  # history = theta(0)
            buf[k % size] = theta
            U = U - spec.k * (theta - buf[(k - spec.delay_steps) % size])
        if spec.has_fuzzy:
            U = U + spec.k3 * fuzzy_surface_np(spec.k1 * Y[0], spec.k2 * Y[1], spec)
        tip = Cz[1] @ X
        tip_ise += tip * tip * dt
        effort += U * U * dt
        np.maximum(peak, np.abs(tip), out=peak)
        if record:
            xs.append(X.T.copy())
            us.append(U.copy())
        X = Ad @ X + Bd @ U[None, :] + Ed * force[k, 0]
    out = {"tip_ise": tip_ise, "control_effort": effort, "peak_tip": peak, "x_end": X.T}
    if record:
        out["x"], out["u"] = np.stack(xs), np.stack(us)
    return out


def _skfuzzy_system(spec: LoopSpec, n_universe: int = 2001):
    """scikit-fuzzy Mamdani system of the paper's rules (min AND, max aggregation, centroid)."""
    import skfuzzy as fz
    from skfuzzy import control as ctrl

    variables = []
    for name, c, cls in (("angle", spec.centres[0], ctrl.Antecedent), ("velocity", spec.centres[1], ctrl.Antecedent), ("torque", spec.centres[2], ctrl.Consequent)):
        c = np.asarray(c, float)
        var = cls(np.linspace(c[0], c[-1], n_universe), name)
        left, right = _feet(c)
        for j, set_name in enumerate(SET_NAMES):
            var[set_name] = fz.trimf(var.universe, [left[j], c[j], right[j]])
        variables.append(var)
    angle, velocity, torque = variables
    torque.defuzzify_method = "centroid"
    rules = [ctrl.Rule(angle[a] & velocity[v], torque[t]) for a, v, t in PAPER_RULES]
    return ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules), clip_to_bounds=True)


def skfuzzy_closed_loop(plant: dict[str, np.ndarray], spec: LoopSpec, x0: np.ndarray, force: np.ndarray, noise: np.ndarray, n_universe: int = 2001) -> dict[str, np.ndarray]:
    """One scenario; one ``ControlSystemSimulation.compute`` per sample (float64).

    Returns the trajectories ``x`` [T, n_x] and ``u`` [T]. Where no rule fires scikit-fuzzy
    has no crisp output; the torque is then 0, as in jaxflex.
    """
    sim = _skfuzzy_system(spec, n_universe)
    Ad, Bd, Ed, C = (plant[k].astype(float) for k in ("Ad", "Bd", "Ed", "C"))
    x = x0.astype(float).copy()
    hist = []
    xs, us = [], []
    for k in range(force.shape[0]):
        y = C @ x + noise[k]
        u = 0.0
        if spec.has_dfs:
            hist.append(y[0])
            u -= spec.k * (y[0] - hist[max(k - spec.delay_steps, 0)])
        if spec.has_fuzzy:
            sim.input["angle"] = spec.k1 * y[0]
            sim.input["velocity"] = spec.k2 * y[1]
            try:
                with warnings.catch_warnings():  # scikit-fuzzy 0.5 calls np.maximum with 3 positional arguments
                    warnings.simplefilter("ignore", DeprecationWarning)
                    sim.compute()
                f = sim.output["torque"]
            except (ValueError, KeyError, AssertionError):  # no rule fired: no crisp output
                f = 0.0
            u += spec.k3 * f
        xs.append(x.copy())
        us.append(u)
        x = Ad @ x + Bd[:, 0] * u + Ed[:, 0] * force[k, 0]
    return {"x": np.array(xs), "u": np.array(us)}


def python_control_closed_loop(plant: dict[str, np.ndarray], spec: LoopSpec, x0: np.ndarray, force: np.ndarray) -> dict[str, np.ndarray]:
    """One scenario through ``control.input_output_response`` (float64, no sensor noise).

    The controller is a discrete ``control.nlsys`` (dt = plant dt) with the DFS delay register
    ``[theta[k-1], ..., theta[k-m]]`` as its states (history = theta(0)) and the exact
    closed-form fuzzy surface in its output map; the plant is ``control.ss`` with inputs
    ``u`` (torque) and ``w`` (tip force). The closed loop is ``control.interconnect``-ed by
    signal name, driven by the tip force.

    Returns ``x`` [T, n_x] (plant states) and ``u`` [T].
    """
    import control

    Ad, Bd, Ed, C = (plant[k].astype(float) for k in ("Ad", "Bd", "Ed", "C"))
    dt = float(plant["dt"])
    n_x = Ad.shape[0]
    m = spec.delay_steps if spec.has_dfs else 1
    sys_plant = control.ss(Ad, np.hstack([Bd, Ed]), C, np.zeros((2, 2)), dt, inputs=["u", "w"], outputs=["theta", "theta_dot"], name="plant")

    def torque(xc, y):
        u = 0.0
        if spec.has_dfs:
            u -= spec.k * (y[0] - xc[m - 1])
        if spec.has_fuzzy:
            f = fuzzy_surface_np(np.array([spec.k1 * y[0]]), np.array([spec.k2 * y[1]]), spec)[0]
            u += spec.k3 * f
        return u

    def update(t, xc, y, params):
        return np.concatenate([[y[0]], xc[:-1]])  # shift register: newest first

    def output(t, xc, y, params):
        return np.array([torque(xc, y)])

    sys_ctrl = control.nlsys(update, output, inputs=["theta", "theta_dot"], outputs=["u"], states=m, dt=dt, name="ctrl")
    closed = control.interconnect([sys_plant, sys_ctrl], inplist=["w"], outlist=["theta", "theta_dot", "u"], name="closed")
    theta0 = float(C[0] @ x0)
    X0 = np.concatenate([x0.astype(float), np.full(m, theta0)])
    t = np.arange(force.shape[0]) * dt
    resp = control.input_output_response(closed, t, force[:, 0].astype(float), X0)
    states = np.asarray(resp.states)  # [n_x + m, T]
    return {"x": states[:n_x].T, "u": np.asarray(resp.outputs)[2]}


def plant_arrays(plant: Any, dtype: Any = np.float64) -> dict[str, np.ndarray]:
    """A jaxflex DiscretePlant as NumPy arrays of ``dtype``."""
    return {k: np.asarray(getattr(plant, k), dtype) for k in ("Ad", "Bd", "Ed", "C", "Cz", "dt")}


def loop_spec(controller: str, defuzz: str = "centroid") -> LoopSpec:
    """The ``LoopSpec`` of ``jaxflex.bench.controller_and_params`` (paper values)."""
    if defuzz not in ("centroid", "singleton"):
        raise ValueError(f"baselines implement the faithful defuzzifiers only; got {defuzz!r}")
    return LoopSpec(kind=controller, defuzz=defuzz)
