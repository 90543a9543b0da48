"""Disturbance scenarios: initial state, tip-force sequence, sensor noise, plant perturbation.

A :class:`Scenario` is an all-array pytree; batches of scenarios are the same pytree with a
leading batch axis (what ``jax.vmap`` maps over). The horizon is the (static) length of the
force sequence. :class:`ScenarioSpec` describes a distribution of scenarios declaratively;
:func:`sample_scenarios` draws a batch from a PRNG key (the paper's scenario can be its first
member), and :func:`scenario_plant` builds each member's perturbed plant.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jaxflex import beam, checks, fileio
from jaxflex.controllers.base import is_concrete, same_dt
from jaxflex.plant import DiscretePlant, LinearPlant, check_method, check_rk4_step, check_sampled, discretize, make_plant, n_modes_of

READINGS = ("printed", "block")


class Scenario(NamedTuple):
    """One disturbance scenario.

    Attributes:
      x0: [n_x] initial state: hub angle (rad), modal amplitudes (m), then their rates.
      force: [T, 1] transverse tip force (N), held over each sample.
      noise: [T, 2] additive sensor noise on the measured hub angle (rad) and velocity (rad/s).
      plant: the scenario's plant uncertainty, or None for the nominal plant. ``rollout``
        does not apply it: build the perturbed plant with ``scenario_plant`` (a batch's with
        ``batch_plant``) and pass it.
    """

    x0: jax.Array
    force: jax.Array
    noise: jax.Array
    plant: "PlantPerturbation | None" = None


class PlantPerturbation(NamedTuple):
    """Plant uncertainty of one scenario (each shape ()).

    Attributes:
      youngs_modulus_scale: factor on E (1 = nominal).
      density_scale: factor on rho.
      hub_inertia_scale: factor on I_H.
      payload_mass_kg: tip payload mass added to the nominal one (kg).
    """

    youngs_modulus_scale: jax.Array
    density_scale: jax.Array
    hub_inertia_scale: jax.Array
    payload_mass_kg: jax.Array


def check_scenario(scenario: Any) -> Scenario:
    """Refuse, by name, what is not a :class:`Scenario` (one, or a batch of them)."""
    return checks.instance("scenario", scenario, Scenario, "build one with paper_scenario(...), initial_condition(...) or, for a batch, sample_scenarios(...)")


def perturbed_params(params: beam.BeamParams, perturbation: PlantPerturbation | None) -> beam.BeamParams:
    """The beam parameters of one scenario (the nominal ones when ``perturbation`` is None)."""
    if perturbation is None:
        return params
    return params._replace(
        youngs_modulus_pa=params.youngs_modulus_pa * perturbation.youngs_modulus_scale,
        density_kg_m3=params.density_kg_m3 * perturbation.density_scale,
        hub_inertia_kg_m2=params.hub_inertia_kg_m2 * perturbation.hub_inertia_scale,
        payload_mass_kg=params.payload_mass_kg + perturbation.payload_mass_kg,
    )


def scenario_plant(params: beam.BeamParams, n_modes: int, dt: float, method: str, scenario: Scenario) -> DiscretePlant:
    """The sampled plant a scenario runs on (vmap this together with the rollout)."""
    return discretize(make_plant(perturbed_params(params, check_scenario(scenario).plant), n_modes), dt, method)


def batch_plant(params: beam.BeamParams, n_modes: int, dt: float, method: str, batch: Scenario, nominal: DiscretePlant) -> DiscretePlant:
    """The plant a batch of scenarios runs on in one ``rollout``: ``nominal`` (built from
    ``params``, shared by the batch) when the batch has no plant uncertainty, else one
    ``scenario_plant`` per scenario (every field with a leading batch axis).

    The drawn plants are not checked against ``method`` (they may be traced): with "rk4",
    call ``check_plants(spec, params, n_modes, method)`` once on the scenarios' spec, as
    tune and montecarlo do, or RK4's own growth on a stiffer drawn arm is counted as the
    controller diverging.

    Raises:
      ValueError: for a ``nominal`` that is not a sampled plant, or of another number of
        modes than ``n_modes``, or a concrete ``dt`` other than its (a 2 ms batch drawn
        beside a 1 ms ``nominal`` ran on either, by whether it held perturbations).
    """
    check_sampled(nominal, "nominal")
    if n_modes_of(nominal) != n_modes:
        raise ValueError(f"n_modes = {n_modes} must be the nominal plant's number of modes, {n_modes_of(nominal)}: build both with one n_modes")
    if is_concrete(dt) and is_concrete(nominal.dt) and np.ndim(dt) == 0 == np.ndim(nominal.dt):
        try:
            given, built = float(dt), float(nominal.dt)
        except (TypeError, ValueError):  # a dt that is no number: discretize names it
            given = built = None
        if given is not None and not same_dt(built, given):
            raise ValueError(f"dt = {given:g} s must be the nominal plant's sample time, {built:g} s: build both at one dt")
    if check_scenario(batch).plant is None:
        return nominal
    return jax.vmap(lambda scenario: scenario_plant(params, n_modes, dt, method, scenario))(batch)


def scenario_modes_hz(params: beam.BeamParams, n_modes: int, scenario: Scenario) -> jax.Array:
    """[n_modes] natural frequencies (Hz) of the arm a scenario runs on, where its vibration
    is measured (``rollout``'s ``mode_freqs_hz``): with plant uncertainty a drawn arm's peaks
    sit away from the nominal arm's."""
    return beam.natural_frequencies_hz(perturbed_params(params, check_scenario(scenario).plant), n_modes)


def batch_modes_hz(params: beam.BeamParams, n_modes: int, batch: Scenario) -> jax.Array:
    """``scenario_modes_hz`` of a batch, as ``rollout`` takes them: the nominal arm's
    [n_modes], shared by the batch, when it has no plant uncertainty, else one row per
    scenario, [B, n_modes]."""
    if check_scenario(batch).plant is None:
        return beam.natural_frequencies_hz(params, n_modes)
    return jax.vmap(lambda scenario: scenario_modes_hz(params, n_modes, scenario))(batch)


def check_plants(spec: "ScenarioSpec", params: beam.BeamParams, n_modes: int, method: str) -> None:
    """Build the nominal plant and the plants at each corner of ``spec``'s uncertainty box,
    refusing the first that ``make_plant`` refuses (not finite in the run's dtype) or, for
    ``method = "rk4"``, whose RK4 step at ``spec.dt`` amplifies a mode (``check_rk4_step``).

    Each natural frequency rises with E and falls with rho, I_H and the payload, so the
    fastest mode of any drawn plant is at a corner. Unchecked, RK4's growth of a stiffer drawn
    plant was counted as the controller diverging: 31 % of the scenarios at dt = 12 ms with
    ``youngs_modulus_rel = 0.5`` and k = 0, where ZOH gives none.

    Raises:
      ValueError: naming ``spec`` or ``method`` when not a ScenarioSpec or one of ``METHODS``;
        naming the corner (each factor) before the plant's own message.
    """
    checks.instance("spec", spec, ScenarioSpec, "build one with ScenarioSpec(...)")
    check_method(method)
    ranges = [
        (1 - spec.youngs_modulus_rel, 1 + spec.youngs_modulus_rel),
        (1 - spec.density_rel, 1 + spec.density_rel),
        (1 - spec.hub_inertia_rel, 1 + spec.hub_inertia_rel),
        (0.0, spec.payload_max_kg),
    ]
    corners = [None] + [PlantPerturbation(*c) for c in itertools.product(*(sorted(set(r)) for r in ranges)) if c != (1.0, 1.0, 1.0, 0.0)]
    for corner in corners:
        try:
            plant = make_plant(perturbed_params(params, corner), n_modes)
            if method == "rk4":
                check_rk4_step(plant, spec.dt)
        except ValueError as err:
            if corner is None:
                raise
            where = f"E x{corner.youngs_modulus_scale:g}, rho x{corner.density_scale:g}, I_H x{corner.hub_inertia_scale:g}, payload +{corner.payload_mass_kg:g} kg"
            raise ValueError(f"the scenarios' plant uncertainty reaches an arm ({where}) that cannot be run: {err}") from err


MAX_STEPS = 10**7
"""The most samples a horizon may hold: a scenario stores its force and noise for each (120 MB
in float32 at 10^7, 2.8 hours at 1 ms), and its recorded trajectory 13 more values at 2 modes
(1.3 GB a scenario in float64 all told); 10^12 ran out of memory with nothing named."""


def horizon_steps(horizon_s: float, dt: float) -> int:
    """Number of samples in ``horizon_s`` seconds at ``dt`` (both concrete, > 0), rounded to
    the nearest whole sample: a 1.004 s horizon at dt = 0.01 s runs 100 samples.

    Raises:
      ValueError: naming ``horizon_s`` or ``dt`` when it is not a finite number > 0 (a string
        such as ``"3"`` or a bool is refused, not converted), or a horizon shorter than ``dt``
        or longer than ``MAX_STEPS`` samples.
    """
    horizon_s = checks.number("horizon_s", horizon_s, strict=True, unit="seconds")
    dt = checks.number("dt", dt, strict=True, unit="seconds")
    steps = int(round(horizon_s / dt))
    if steps < 1:
        raise ValueError(f"horizon_s must cover at least one sample of dt = {dt}; got {horizon_s}")
    if steps > MAX_STEPS:
        raise ValueError(f"horizon_s / dt must be at most {MAX_STEPS:,} samples (each scenario holds its force and noise for every one); "
                         f"got {horizon_s:g} s at dt = {dt:g} s, {steps:,} samples")
    return steps


def paper_scenario(plant: LinearPlant | DiscretePlant, horizon_s: float = 3.0, dt: float | None = None, reading: str = "printed", dtype=None) -> Scenario:
    """The paper's disturbance: an initial condition, no force, no noise.

    The paper prints ``x0 = [0 0 1e-3 0 1e-5 0]`` beside a state printed as
    ``[theta theta_dot q1 q2 q1_dot q2_dot]``.

    Args:
      plant: the plant (its number of modes, and a sampled plant's ``dt``); for a batch of
        ``B`` plants (``batch_plant``), sharing one ``dt``, the scenario's ``x0`` is ``[B, n_x]``
        and its force and noise are shared.
      horizon_s: simulated time (s); the paper's figures show 3 s.
      dt: sample time (s); default: a sampled plant's own ``dt`` (needed when that is
        traced, under ``jit`` or ``vmap``), else the paper's 1 ms. A different ``dt`` than a
        sampled plant's is refused.
      reading: ``"printed"`` (default): in the printed order, q_1(0) = 1e-3 m and
        q_1_dot(0) = 1e-5 m/s. ``"block"``: the numbers read in jaxflex's state order,
        q_2(0) = 1e-3 m and q_1_dot(0) = 1e-5 m/s (needs n_modes >= 2).
      dtype: floating dtype of the arrays (default: the plant's).
    """
    n = n_modes_of(plant)
    batch = tuple(plant.C.shape[:-2])
    plant_dt = None
    if isinstance(plant, DiscretePlant) and is_concrete(plant.dt):
        dts = np.asarray(plant.dt)
        if dts.size == 0:
            raise ValueError("plant must hold at least one plant; got an empty batch")
        finite = bool(np.all(np.isfinite(dts)))  # a NaN dt is refused, as such, by the checks of dt below
        if finite and not np.all(dts == dts.flat[0]):
            raise ValueError(f"paper_scenario: the batch of plants has sample times from {dts.min():.7g} to {dts.max():.7g} s; they must share one dt (the horizon's number of samples)")
        plant_dt = float(fileio.shortest(dts.flat[0])) if finite else math.nan  # a float32 plant's 1 ms reads 0.001, not 0.0010000000474974513
    if dt is None and isinstance(plant, DiscretePlant) and plant_dt is None:
        raise ValueError("paper_scenario: the sampled plant's dt is traced (under jit or vmap), and the horizon's number of samples must be known: pass dt=... (s)")
    if dt is None:
        dt = 1e-3 if plant_dt is None else plant_dt
    elif plant_dt is not None and not math.isclose(checks.number("dt", dt, strict=True, unit="seconds"), plant_dt, rel_tol=1e-6):  # a float32 plant holds dt rounded
        raise ValueError(f"dt = {dt!r} s differs from the sampled plant's dt = {plant_dt:.7g} s: leave dt out, or sample the plant at it")
    steps = horizon_steps(horizon_s, dt)
    dtype = checks.float_dtype("dtype", plant.C.dtype if dtype is None else dtype)
    x0 = np.broadcast_to(_paper_x0(n, reading), batch + (2 * (n + 1),))
    return Scenario(jnp.asarray(x0, dtype), jnp.zeros((steps, 1), dtype), jnp.zeros((steps, 2), dtype))


def _key_shape(key: Any) -> tuple[int, ...] | None:
    """The shape of ``key`` counted in PRNG keys (``()`` for one): a typed key array, or
    legacy ``jax.random.PRNGKey`` data of the default implementation (2 words a key for
    threefry, 4 for rbg); None when it is neither."""
    if not isinstance(key, jax.Array):
        return None
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key.shape
    if key.dtype != jnp.uint32 or key.ndim < 1:
        return None
    try:
        return jax.random.wrap_key_data(key).shape
    except TypeError:
        return None


def _paper_x0(n_modes: int, reading: str = "printed") -> np.ndarray:
    """The paper's initial state for ``n_modes`` modes, in jaxflex's state order (see
    ``paper_scenario``)."""
    x0 = np.zeros(2 * (n_modes + 1))
    if reading == "printed":
        x0[1], x0[n_modes + 2] = 1e-3, 1e-5
    elif reading == "block":
        if n_modes < 2:
            raise ValueError(f"reading='block' sets q_2 and needs n_modes >= 2; got n_modes = {n_modes}")
        x0[2], x0[n_modes + 2] = 1e-3, 1e-5
    else:
        raise ValueError(f"reading must be one of {READINGS}; got {reading!r}")
    return x0


def initial_condition(x0: ArrayLike, steps: int, dtype=None) -> Scenario:
    """A scenario with the given initial state and no force or noise for ``steps`` samples.

    Args:
      x0: [n_x] initial state (a number array; integers are taken as floats).
      steps: number of samples (Python int >= 1).
      dtype: floating dtype of the arrays; default: that of a floating ``x0``, else JAX's
        default float.
    """
    if is_concrete(x0) and not np.all(np.isfinite(checks.real_array("x0", x0))):
        raise ValueError(f"x0 must be finite; got {np.asarray(x0).tolist()}")
    x0 = jnp.asarray(x0)
    if dtype is not None or not jnp.issubdtype(x0.dtype, jnp.floating):  # an int32 scenario would only be refused by rollout
        x0 = x0.astype(checks.float_dtype("dtype", dtype))
    if x0.ndim != 1:
        raise ValueError(f"x0 must have shape (n_x,); got {x0.shape}")
    steps = checks.integer("steps", steps)
    return Scenario(x0, jnp.zeros((steps, 1), x0.dtype), jnp.zeros((steps, 2), x0.dtype))


@dataclasses.dataclass(frozen=True)
class ScenarioSpec:
    """A declarative distribution of disturbance scenarios (SI units; 0 switches a term off).

    Each member starts from rest plus random initial conditions, may receive a tip-force
    impulse and a tip-force step at random times, sees Gaussian sensor noise, and runs on a
    plant drawn around the nominal one.

    Attributes:
      horizon_s: simulated time per scenario (s), > 0, rounded to the nearest whole number of
        samples of ``dt`` (``steps``).
      dt: sample time (s), > 0.
      q0_std_m: standard deviation of each initial modal displacement q_i(0) (m).
      qdot0_std_m_s: standard deviation of each initial modal rate (m/s).
      theta0_std_rad: standard deviation of the initial hub angle (rad).
      impulse_max_n: peak of a rectangular tip-force pulse, amplitude uniform in
        [-impulse_max_n, impulse_max_n] (N), lasting ``impulse_duration_s``, starting uniformly
        in the first half of the horizon.
      impulse_duration_s: pulse duration (s), in [dt, horizon_s / 2] when impulses are on (a
        pulse starts in the first half and must end within the horizon).
      step_max_n: amplitude of a tip-force step, uniform in [-step_max_n, step_max_n] (N),
        starting uniformly in the first half of the horizon.
      noise_angle_rad: standard deviation of the hub-angle sensor noise (rad).
      noise_velocity_rad_s: standard deviation of the hub-velocity sensor noise (rad/s).
      youngs_modulus_rel: E drawn uniformly in nominal * (1 +- youngs_modulus_rel), in [0, 1).
      density_rel: rho drawn uniformly in nominal * (1 +- density_rel), in [0, 1).
      hub_inertia_rel: I_H drawn uniformly in nominal * (1 +- hub_inertia_rel), in [0, 1).
      payload_max_kg: extra tip payload drawn uniformly in [0, payload_max_kg] (kg).
      include_paper: make member 0 the paper's scenario (printed reading, nominal plant).
    """

    horizon_s: float = 1.0
    dt: float = 1e-3
    q0_std_m: float = 1e-3
    qdot0_std_m_s: float = 1e-5
    theta0_std_rad: float = 0.0
    impulse_max_n: float = 0.0
    impulse_duration_s: float = 0.005
    step_max_n: float = 0.0
    noise_angle_rad: float = 0.0
    noise_velocity_rad_s: float = 0.0
    youngs_modulus_rel: float = 0.0
    density_rel: float = 0.0
    hub_inertia_rel: float = 0.0
    payload_max_kg: float = 0.0
    include_paper: bool = True

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "include_paper":
                if not isinstance(value, bool):
                    raise ValueError(f"include_paper must be true or false; got {value!r}")
                continue
            value = checks.number(f.name, value, strict=f.name in ("horizon_s", "dt"))
            object.__setattr__(self, f.name, value)
            if f.name.endswith("_rel") and value >= 1:
                raise ValueError(f"{f.name} must be in [0, 1); got {value}")
        if self.impulse_max_n > 0 and self.impulse_duration_s < self.dt:
            raise ValueError(f"impulse_duration_s must be >= dt = {self.dt} s when impulses are on; got {self.impulse_duration_s}")
        horizon_steps(self.horizon_s, self.dt)
        if self.impulse_max_n > 0 and self.impulse_duration_s > self.horizon_s / 2:
            raise ValueError(
                f"impulse_duration_s must be <= horizon_s / 2 = {self.horizon_s / 2:g} s when impulses are on (a pulse starts in "
                f"the first half of the horizon; a longer one was cut off at its end); got {self.impulse_duration_s:g}"
            )

    @property
    def steps(self) -> int:
        return horizon_steps(self.horizon_s, self.dt)

    @property
    def perturbs_plant(self) -> bool:
        return any(v > 0 for v in (self.youngs_modulus_rel, self.density_rel, self.hub_inertia_rel, self.payload_max_kg))

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "ScenarioSpec":
        """Build from a dict (e.g. a TOML table), refusing unknown keys by name."""
        fileio.check_keys(values, [f.name for f in dataclasses.fields(cls)], "scenario")
        return cls(**dict(values))


def sample_scenarios(spec: ScenarioSpec, key: jax.Array, n: int, n_modes: int = 2, dtype=None) -> Scenario:
    """Draw ``n`` scenarios from ``spec`` as one batched Scenario (leading axis n).

    Args:
      spec: the distribution.
      key: a JAX PRNG key (``jax.random.key(seed)``).
      n: number of scenarios (Python int >= 1).
      n_modes: number of assumed modes of the plant (sets the state size).
      dtype: floating dtype (default: JAX's default float). The scenarios are drawn in
        float32 and cast, so that a key gives the same ones in any dtype (the paper's member
        set in ``dtype``).

    Raises:
      ValueError: naming ``spec`` when it is not a ScenarioSpec, ``key`` when it is not one
        PRNG key (a batch of them included), ``n``, ``n_modes`` or ``dtype`` out of range.

    Returns:
      Scenario with fields [n, ...]; ``plant`` is None unless the spec perturbs the plant.
    """
    checks.instance("spec", spec, ScenarioSpec, "build one with ScenarioSpec(...) or ScenarioSpec.from_mapping({...})")
    key_shape = _key_shape(key)
    if key_shape is None:
        raise ValueError(f"key must be a JAX PRNG key (jax.random.key(seed)); got {type(key).__name__} {key!r}")
    if key_shape != ():  # a legacy batch, [3, 2] words, was refused as no key at all
        raise ValueError(f"key must be one PRNG key (shape ()); got a batch of shape {key_shape}: n draws the {n!r} scenarios from one key")
    n = checks.integer("n (number of scenarios)", n)
    n_modes = beam.check_n_modes(n_modes)
    dtype = checks.float_dtype("dtype", dtype)
    steps, dt = spec.steps, spec.dt
    n_q = n_modes + 1
    keys = jax.random.split(key, 10)
    # Drawn and built in float32 whatever the dtype, then cast: JAX's float64 draws from a key
    # are other numbers than its float32 ones, so a seed gave another batch under --x64 (its
    # Monte Carlo peak tip deflection 8 % off the float32 run's, which was sampling, not
    # precision), and a pulse's start compared in each dtype could move by a sample.
    f32 = jnp.float32
    normal = lambda k, shape: jax.random.normal(k, shape, f32)
    uniform = lambda k, shape, lo=-1.0, hi=1.0: jax.random.uniform(k, shape, f32, lo, hi)

    x0 = jnp.zeros((n, 2 * n_q), f32)
    x0 = x0.at[:, 0].set(spec.theta0_std_rad * normal(keys[0], (n,)))
    x0 = x0.at[:, 1:n_q].set(spec.q0_std_m * normal(keys[1], (n, n_modes)))
    x0 = x0.at[:, n_q + 1 :].set(spec.qdot0_std_m_s * normal(keys[2], (n, n_modes)))

    t = jnp.arange(steps, dtype=f32) * dt
    half = 0.5 * spec.horizon_s
    pulse_start = uniform(keys[3], (n, 1), 0.0, half)
    pulse = spec.impulse_max_n * uniform(keys[4], (n, 1)) * ((t[None, :] >= pulse_start) & (t[None, :] < pulse_start + spec.impulse_duration_s))
    step_start = uniform(keys[5], (n, 1), 0.0, half)
    step = spec.step_max_n * uniform(keys[6], (n, 1)) * (t[None, :] >= step_start)
    force = (pulse + step)[:, :, None]

    noise_std = jnp.asarray([spec.noise_angle_rad, spec.noise_velocity_rad_s], f32)
    noise = normal(keys[7], (n, steps, 2)) * noise_std[None, None, :]

    plant = None
    if spec.perturbs_plant:
        u = uniform(keys[8], (n, 3))
        plant = PlantPerturbation(
            1 + spec.youngs_modulus_rel * u[:, 0],
            1 + spec.density_rel * u[:, 1],
            1 + spec.hub_inertia_rel * u[:, 2],
            uniform(keys[9], (n,), 0.0, 1.0) * spec.payload_max_kg,
        )
        plant = PlantPerturbation(*(leaf.astype(dtype) for leaf in plant))
    x0, force, noise = (a.astype(dtype) for a in (x0, force, noise))
    if spec.include_paper:
        x0 = x0.at[0].set(jnp.asarray(_paper_x0(n_modes), dtype))
        force = force.at[0].set(0.0)
        noise = noise.at[0].set(0.0)
        if plant is not None:
            plant = PlantPerturbation(*(leaf.at[0].set(v) for leaf, v in zip(plant, (1.0, 1.0, 1.0, 0.0))))
    return Scenario(x0, force, noise, plant)


def pad_batch(batch: Any, multiple: int) -> Any:
    """``batch`` (a pytree with the scenarios on axis 0 of every leaf) with its last scenario
    repeated until the count is a multiple of ``multiple``, so that it splits evenly over that
    many devices; the caller drops the padding's results. Unchanged when it divides already.

    Raises:
      ValueError: ``multiple`` not an integer >= 1, or a batch with no scenarios (no leaves,
        or leaves with no leading axis or different counts on it).
    """
    multiple = checks.integer("multiple", multiple)
    counts = {jnp.shape(a)[0] if jnp.ndim(a) else None for a in jax.tree.leaves(batch)}
    if len(counts) != 1 or None in counts or 0 in counts:
        raise ValueError(f"batch must hold scenarios on axis 0 of every leaf, the same count in each; got leading sizes {sorted(counts, key=str)}")
    n = counts.pop()
    pad = -n % multiple
    if pad == 0:
        return batch
    return jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), batch)
