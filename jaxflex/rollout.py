"""The closed loop: one ``lax.scan`` over time for any controller and any scenario.

At sample k the controller sees ``y[k] = C x[k] + noise[k]``, returns ``u[k]``, and the
plant advances ``x[k+1] = Ad x[k] + Bd u[k] + Ed force[k]`` (inputs held over the sample).

``rollout`` is pure and unjitted: callers compose ``jax.jit``, ``jax.vmap`` (over
scenarios, plants or parameters) and ``jax.grad`` around it. It also runs a batch of
scenarios itself (``scenario.x0`` of shape ``[B, n_x]``, with an optional batch of plants
and per-scenario inputs), which is how the Monte Carlo runner, the tuner and the benchmark
call it, and faster than ``vmap`` over single scenarios (below). With ``output="metrics"``
the same loop keeps only running metrics in its carry (:class:`RunMetrics`), so memory does
not grow with the horizon.

How the loop is laid out (same arithmetic, measured in ``benchmarks/README.md``; a bare
``Ad @ x`` loop under ``vmap`` on CPU runs 5.5x faster state-major than with a vector state):

* A batch is the last axis of every value in the loop: the state components are ``[B]``,
  the measurement ``[2, B]``, a controller's ring buffer ``[slots, 1, B]``. ``vmap`` puts
  the batch first in every carry instead, so a ring buffer would be ``[B, slots]`` and each
  sample's write and read strided, one cache line per scenario; with the batch last they
  are one contiguous row. The built-in controllers take the batch as it is
  (``Controller.batched``); others are mapped over it with ``vmap``. A single scenario is
  the same loop with no batch axis.
* The state is carried as a tuple of its ``n_x`` components, and ``Ad @ x`` is written out
  as ``n_x^2`` multiply-adds. Each component is then one contiguous ``[B]`` array
  (state-major), so every operation of a step is elementwise over the batch and XLA fuses
  it; a vector state would be ``[B, n_x]`` with the batch first, and its small matvecs run
  several times slower.
* The loop is rotated: iteration k updates the metrics with ``(x[k], u[k])``, advances the
  plant to ``x[k+1]`` and runs the controller at ``k + 1``, so ``u`` is a loop-carried value.
  Computed and consumed in the same iteration, ``u`` would be recomputed by XLA inside each
  of the ``n_x + 1`` fused kernels that read it (it duplicates cheap producers into their
  consumers). The last iteration's controller output ``u[T]`` is discarded (one extra
  controller evaluation per rollout).
* ``y[k+1]`` is formed from ``x[k]`` with ``C Ad``, ``C Bd`` and ``C Ed`` computed once
  outside the loop, and each measured component gets its noise before the components are
  stacked: otherwise the controller's kernel recomputes the next state or reads ``y`` out of
  a stacked ``[batch, 2]`` array, several times slower.
* A plant closed over by ``jit`` (concrete, as in the Monte Carlo runner, the benchmark and
  the tuner's nominal plant) is read as NumPy matrices and their exact zeros are skipped:
  the tip deflection reads 2 of the 6 state components, the hub angle 1, and no component
  of the next state reads the hub angle but its own. Each kernel then does less and reads
  fewer arrays (the open loop 1.5x, DFS+fuzzy 1.1-1.2x faster). A traced plant (a batch of
  plants) keeps every term; both give the same loop (tested).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex import checks
from jaxflex.analysis.metrics import DIVERGENCE_THRESHOLD
from jaxflex.controllers.base import Controller, check_controller, check_params, is_concrete, same_dt
from jaxflex.plant import DiscretePlant, check_sampled
from jaxflex.scenarios import Scenario, check_scenario


class Trajectory(NamedTuple):
    """A simulated response; time is the first axis.

    Attributes:
      t: [T] sample times (s), starting at 0.
      x: [T, n_x] state at each sample.
      u: [T, 1] hub torque (N*m) held from each sample to the next.
      y: [T, 2] measurement seen by the controller (hub angle rad, hub velocity rad/s).
      z: [T, 3] hub angle (rad), elastic tip deflection (m), tip position (m).
    """

    t: jax.Array
    x: jax.Array
    u: jax.Array
    y: jax.Array
    z: jax.Array


class RunMetrics(NamedTuple):
    """Running metrics of one rollout over samples k = 0..T-1 (each shape ()).

    They equal the same quantities computed from the Trajectory (tested).

    Attributes:
      peak_tip_m: max |tip deflection| (m).
      tip_ise: sum of tip deflection^2 dt (m^2 s).
      tip_iae: sum of |tip deflection| dt (m s).
      hub_ise: sum of hub angle^2 dt (rad^2 s).
      control_effort: sum of u^2 dt (N^2 m^2 s).
      final_hub_angle_rad: hub angle at the end of the horizon, t = T dt (rad).
      settling_time_s: time after which |tip deflection| stays within ``settling_band`` of its
        peak, measured from 0 (the equilibrium of the elastic deflection); +inf if the last
        sample is outside the band. Computed exactly in one pass: when the running peak grows
        at sample k, sample k itself is outside the band, so earlier exceedances never matter.
      peak_abs_state: max |x| over all states and samples (inf or NaN if a sample was: NaN wins).
      diverged: peak_abs_state non-finite or above ``DIVERGENCE_THRESHOLD``.
      modal_energy: [n_f] energy of the tip deflection at each frequency of
        ``mode_freqs_hz``: ``|sum_k w_k tip_k exp(-2 pi i f t_k) dt|^2`` with ``w`` the periodic
        Hann window over the horizon (m^2 s^2); shape (0,) when no frequencies are given.
        A streaming single-bin DFT, so it needs no stored trajectory.
    """

    peak_tip_m: jax.Array
    tip_ise: jax.Array
    tip_iae: jax.Array
    hub_ise: jax.Array
    control_effort: jax.Array
    final_hub_angle_rad: jax.Array
    settling_time_s: jax.Array
    peak_abs_state: jax.Array
    diverged: jax.Array
    modal_energy: jax.Array


OUTPUTS = ("trajectory", "metrics")
MAX_UNROLL = 64
"""``unroll``'s largest value: each sample of an iteration is compiled once more (10^5 never
finished compiling)."""


def _wider(value: Any, dtype: Any) -> bool:
    """Whether ``value`` is a float array that would widen arithmetic in ``dtype``: not weakly
    typed (a Python float adapts), and canonical (without x64 JAX reads a NumPy float64, a
    gain from ``np.linspace``, as float32)."""
    value_dtype = getattr(value, "dtype", None)
    weak = getattr(getattr(value, "aval", value), "weak_type", False)
    return value_dtype is not None and jnp.issubdtype(value_dtype, jnp.floating) and not weak and jnp.promote_types(jax.dtypes.canonicalize_dtype(value_dtype), dtype) != dtype


def _check_inputs(plant: DiscretePlant, scenario: Scenario, params: Any, settling_band: Any, mode_freqs_hz: Any) -> tuple[tuple[int, ...], float]:
    """Shapes and dtypes of the loop's inputs, and the metrics' options, named when wrong;
    returns the batch shape (``()`` or ``(B,)``, from ``scenario.x0``) and ``settling_band``
    as a Python float (a constant of the loop)."""
    check_sampled(plant)
    check_scenario(scenario)
    for name in ("x0", "force", "noise"):
        value = getattr(scenario, name)
        if not isinstance(value, (jax.Array, np.ndarray)):
            raise ValueError(f"scenario.{name} must be an array in the plant's dtype (jnp.asarray(..., dtype)); got {type(value).__name__}")
    n_x = plant.Ad.shape[-1]
    if plant.Ad.ndim not in (2, 3) or plant.Ad.shape[-2] != n_x:
        raise ValueError(f"Ad must be square, [n_x, n_x], or a batch of plants [B, n_x, n_x]; got {plant.Ad.shape}")
    if scenario.x0.ndim not in (1, 2) or scenario.x0.shape[-1] != n_x:
        raise ValueError(f"scenario.x0 must have shape ({n_x},) for this plant, or (B, {n_x}) for a batch of B scenarios; got {scenario.x0.shape}")
    batch = tuple(scenario.x0.shape[:-1])
    if batch == (0,):
        raise ValueError(f"scenario.x0 must hold at least one scenario (B >= 1); got shape {scenario.x0.shape}")
    shared = "shared by the batch" if batch else "one scenario"
    steps = scenario.force.shape[-2] if scenario.force.ndim >= 2 else -1
    if scenario.force.shape not in ((steps, 1), batch + (steps, 1)) or steps < 1:
        first = f", or ({', '.join(map(str, batch))}, T, 1) with the batch first" if batch else ""
        raise ValueError(f"scenario.force must have shape (T, 1) with T >= 1 ({shared}){first}; got {scenario.force.shape}")
    if scenario.noise.shape not in ((steps, 2), batch + (steps, 2)):
        # the horizon T is read from force: a force cut short blamed the noise alone
        raise ValueError(
            f"scenario.noise must have shape ({steps}, 2){f' or {batch + (steps, 2)}' if batch else ''}, the horizon T = {steps} of scenario.force; "
            f"got {scenario.noise.shape} (force and noise hold one row per sample)"
        )
    plant_batch = tuple(plant.Ad.shape[:-2])
    if batch and not plant_batch and scenario.plant is not None:  # a hand-written Monte Carlo ran every scenario on the nominal plant, silently
        raise ValueError(
            "scenario.plant holds each scenario's plant uncertainty, which rollout does not apply to one plant shared by the batch: "
            "pass batch_plant(params, n_modes, dt, method, scenario, plant) (jaxflex.scenarios) as plant, or scenario._replace(plant=None) "
            "to run every scenario on this one"
        )
    if plant_batch and plant_batch != batch:
        raise ValueError(f"a batch of plants {plant.Ad.shape} needs a batch of as many scenarios (scenario.x0 of shape {plant_batch + (n_x,)}); got scenario.x0 of shape {scenario.x0.shape}")
    for name, rows, cols in (("Bd", n_x, 1), ("Ed", n_x, 1), ("C", 2, n_x), ("Cz", 3, n_x)):
        if getattr(plant, name).shape != plant_batch + (rows, cols):
            raise ValueError(f"plant.{name} must have shape {plant_batch + (rows, cols)} to match Ad {plant.Ad.shape}; got {getattr(plant, name).shape}")
    if jnp.shape(plant.dt) != plant_batch:
        raise ValueError(f"plant.dt must have shape {plant_batch} to match Ad {plant.Ad.shape}; got {jnp.shape(plant.dt)}")
    dtype = plant.Ad.dtype
    for name in ("x0", "force", "noise"):
        value = getattr(scenario, name)
        if value.dtype != dtype:
            raise ValueError(f"scenario.{name} is {value.dtype} but the plant is {dtype}: build both in one dtype")
        if is_concrete(value) and not np.all(np.isfinite(np.asarray(value))):  # traced ones (vmap, jit) run NaN and report themselves diverged
            raise ValueError(f"scenario.{name} must be finite; got inf or NaN")
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        leaf_dtype = getattr(leaf, "dtype", None)
        if _wider(leaf, dtype):
            raise ValueError(
                f"params{jax.tree_util.keystr(path)} is {leaf_dtype}, wider than the plant's {dtype}: "
                f"build the parameters in {dtype} (e.g. by_name(..., dtype=...))"
            )
    # A number or a concrete 0-d array (a jnp scalar); bools (kind "b"), strings and traced
    # values are refused.
    if not (is_concrete(settling_band) and np.ndim(settling_band) == 0 and np.asarray(settling_band).dtype.kind in "iuf" and 0 < float(settling_band) < 1):
        raise ValueError(f"settling_band must be a number in (0, 1) (a fraction of the peak), concrete (not traced); got {settling_band!r}")
    if mode_freqs_hz is not None:
        if is_concrete(mode_freqs_hz):
            checks.real_array("mode_freqs_hz", mode_freqs_hz)
        freqs = jnp.asarray(mode_freqs_hz)
        if freqs.ndim == 0 or freqs.ndim > 1 + len(batch) or (freqs.ndim == 2 and freqs.shape[0] != batch[0]):
            raise ValueError(f"mode_freqs_hz must be a 1-D array of frequencies (Hz){f', or {batch[0]} of them (one row per scenario)' if batch else ''}; got shape {freqs.shape}")
        if is_concrete(freqs) and not np.all(np.isfinite(np.asarray(freqs)) & (np.asarray(freqs) >= 0)):  # NumPy: no tracer under jit
            raise ValueError(f"mode_freqs_hz must be finite frequencies >= 0 (Hz); got {np.asarray(freqs)}")
        # a frequency at or above Nyquist reads the energy of its alias, not its own
        if is_concrete(freqs) and is_concrete(plant.dt) and np.any(np.asarray(freqs) >= 0.5 / np.max(plant.dt)):
            raise ValueError(f"mode_freqs_hz must be below the Nyquist frequency, {0.5 / np.max(plant.dt):.6g} Hz (dt = {np.max(plant.dt):g} s); got {np.asarray(freqs)}")
    return batch, float(settling_band)


def rollout(
    plant: DiscretePlant,
    controller: Controller,
    params: Any,
    scenario: Scenario,
    *,
    output: str = "trajectory",
    settling_band: float = 0.02,
    mode_freqs_hz: Any = None,
    unroll: int = 1,
) -> Trajectory | RunMetrics:
    """Simulate the closed loop over the scenario's horizon.

    Args:
      plant: sampled plant (``plant.discretize``); for a batch of scenarios, one plant for
        all or a batch of B plants (every field with a leading B axis).
      controller: any :class:`~jaxflex.controllers.base.Controller`.
      params: the controller's parameter pytree (leaves may be traced).
      scenario: one scenario, in the plant's dtype (``x0`` [n_x], ``force`` [T, 1],
        ``noise`` [T, 2]), or a batch of B: ``x0`` [B, n_x], with ``force`` [B, T, 1] and
        ``noise`` [B, T, 2] or shared by the batch ([T, 1], [T, 2]). Its ``plant``
        perturbation is not applied here: pass the perturbed plant,
        ``scenarios.scenario_plant(...)`` (``scenarios.batch_plant(...)`` for a batch), as
        ``plant``; a batch that holds perturbations with one shared plant is refused.
      output: ``"trajectory"`` (every sample, memory O(T)) or ``"metrics"`` (running
        metrics only, memory O(1) in T).
      settling_band: band of the running settling time, as a fraction of the peak, in (0, 1):
        a number or a concrete 0-d array.
      mode_freqs_hz: [n_f] frequencies (Hz, finite, in [0, Nyquist)) of ``RunMetrics.modal_energy``
        (metrics only); for a batch, shared or [B, n_f].
      unroll: samples per iteration of the compiled loop (``lax.scan``'s ``unroll``), an
        integer in [1, ``MAX_UNROLL``]. It changes the speed, not the model: XLA may fuse and round otherwise
        (on the H100 every finite value of the Monte Carlo's metrics was the same to the bit; on the
        CPU, in float32, a final hub angle moved by 1e-9 rad, a settling time by one sample,
        and the largest dB reductions, where the closed-loop energy nears the float's
        resolution, by up to 1.8 dB at 116 dB, the median one by 0.005 dB). Measured
        (benchmarks/README.md, "Scan unrolling"): on an H100, 8 runs forward-only rollouts
        1.4-3.8x as fast as 1, after 5-6 s more compiling, and gradients 15 % slower; on the
        CPU, 2 runs forward-only rollouts 2.4-3.2x slower and gradients 1.2x slower.
        ``MCConfig.unroll`` passes it for the Monte Carlo runs.

    Raises:
      ValueError: naming a plant that is not a DiscretePlant, a controller that is not a
        Controller (a factory passed uncalled), a scenario that is not a Scenario of arrays
        or (when concrete) not finite, a shape, dtype or option that is wrong (parameter values through
        the controller's ``check`` where they are concrete), or a controller built for
        another sample time than the plant's (a traced plant, e.g. under ``jit``, runs
        NaN instead and reports itself diverged).

    Returns:
      Trajectory with fields [T, ...], or RunMetrics; for a batch, each field with a leading
      B axis (as ``vmap`` over single scenarios gives them). A loop that diverges returns
      non-finite or huge values; ``RunMetrics.diverged`` and
      :func:`jaxflex.analysis.metrics.diverged` report it. A loop that grows without blowing
      up (a tip deflection beyond the arm's length, every state below 1e6) only
      :func:`jaxflex.analysis.metrics.run_diverged` reports, from ``peak_tip_m`` and the
      arm's length, as the commands do.
    """
    check_controller("controller", controller)
    unroll = checks.integer("unroll", unroll, high=MAX_UNROLL)
    batch, settling_band = _check_inputs(plant, scenario, params, settling_band, mode_freqs_hz)
    if output not in OUTPUTS:
        raise ValueError(f"output must be one of {OUTPUTS}; got {output!r}")
    # The sample times first: parameters checked against another dt give misleading messages.
    if controller.dt is not None and is_concrete(plant.dt) and not np.all(same_dt(controller.dt, np.asarray(plant.dt, np.float64))):
        raise ValueError(f"the controller was built for dt = {controller.dt:g} s but the plant is sampled at dt = {np.asarray(plant.dt).ravel()[0]:g} s: build both with one dt")
    check_params(controller, params)  # the concrete leaves: a traced out-of-range value runs NaN

    n_x = plant.Ad.shape[-1]
    steps = scenario.force.shape[-2]
    # Inside the loop every per-scenario value carries the batch as its last axis (shape
    # ``batch`` = () or (B,)): moved there once, before the loop.
    last = (lambda a: jnp.moveaxis(a, 0, -1)) if batch else (lambda a: a)
    maps = (plant.Ad, plant.Bd, plant.Ed, plant.C, plant.Cz)
    if plant.Ad.ndim == 3:  # a batch of plants: [n, m, B]
        Ad, Bd, Ed, C, Cz = (last(m) for m in maps)
    else:  # closed over by jit (concrete): NumPy matrices, so that _dot sees their zeros
        Ad, Bd, Ed, C, Cz = (np.asarray(m) for m in maps) if is_concrete(maps) else maps
    init, step = controller.init, controller.step
    if batch and not controller.batched:  # a controller written for one scenario: its state
        # batch first, as vmap over single rollouts lays it out (a ring buffer with the batch
        # last would be transposed by vmap at every read and write), y and u batch last
        init = jax.vmap(init, in_axes=(None, -1), out_axes=0)
        step = jax.vmap(step, in_axes=(None, 0, -1), out_axes=(0, -1))

    # The measurement of the next sample from the current one: y[k+1] = C x[k+1] + noise[k+1]
    # = (C Ad) x[k] + (C Bd) u[k] + (C Ed) force[k] + noise[k+1], with the products formed
    # once, outside the loop.
    next_y = tuple(_matmul(C, m) for m in (Ad, Bd, Ed))  # [2, n_x], [2, 1], [2, 1]

    def advance(x, state, u, force, noise_next):
        """Sample k -> k + 1: the plant under the held u[k], then the controller at k + 1."""
        x_next = _affine((Ad, Bd, Ed), x, u, force)
        y_next = jnp.stack([y_i + noise_next[i] for i, y_i in enumerate(_affine(next_y, x, u, force))])
        state, u_next = step(params, state, y_next)
        return x_next, state, u_next, y_next

    # A traced plant (under jit) cannot refuse another dt than the controller's: its run is
    # NaN from the start and reports itself diverged.
    x0 = tuple(scenario.x0[..., i] for i in range(n_x))
    if not is_concrete(plant.dt) and controller.dt is not None:
        x0 = tuple(jnp.where(same_dt(controller.dt, plant.dt), x_i, jnp.nan) for x_i in x0)
    # The inputs time-major: [T, 1] and [T, 2] shared by the batch, or [T, 1, B] and [T, 2, B].
    force = last(scenario.force) if scenario.force.ndim == 3 else scenario.force
    noise = last(scenario.noise) if scenario.noise.ndim == 3 else scenario.noise
    y0 = jnp.stack([y_i + noise[0][i] for i, y_i in enumerate(_matvec(C, x0))])
    state1, u0 = step(params, init(params, y0), y0)
    if jnp.shape(u0) != (1,) + batch:
        if batch and not controller.batched:  # it runs under vmap: the scalar it returned came out as (B,)
            raise ValueError(f"the controller's step must return the torque u with shape (1,) for one scenario (N*m; rollout maps it over the batch of {batch[0]}); "
                             f"got shape {jnp.shape(u0)[:-1]} per scenario")
        raise ValueError(f"the controller's step must return the torque u with shape {(1,) + batch} (N*m{', a trailing batch axis when batched' if batch else ''}); got shape {jnp.shape(u0)}")
    if not jnp.issubdtype(jnp.result_type(u0), jnp.floating):  # an int torque ran, with a gradient of 0
        raise ValueError(f"the controller's step must return the torque u as floats, in the plant's dtype {y0.dtype}; got {jnp.result_type(u0)}")
    # a state that changes shape or dtype failed in lax.scan, naming carry[1]; the loop needs
    # the step's state to come back as it went in (init's may differ: a list, a Python float)
    described = lambda tree: jax.tree.map(lambda a: f"{a.dtype}{list(a.shape)}", jax.eval_shape(lambda t: t, tree))  # noqa: E731
    following = jax.eval_shape(lambda s: step(params, s, y0)[0], state1)
    if jax.tree.structure(following) != jax.tree.structure(state1) or described(following) != described(state1):
        raise ValueError(f"the controller's step must return a state of the shapes and dtypes it was given (the loop carries it): {described(state1)} became {described(following)}")
    if _wider(u0, y0.dtype):  # else lax.scan refuses the carry with a message that names no controller
        raise ValueError(f"the controller's step returns the torque u in {u0.dtype}, wider than the plant's {y0.dtype}: build its constants in the plant's dtype, or cast u with .astype(y.dtype)")
    # noise[k + 1] for iteration k; the last iteration's controller step (its u[T] is never
    # used) sees zero noise.
    inputs = (force, jnp.concatenate([noise[1:], jnp.zeros_like(noise[:1])]))
    if output == "trajectory":

        def body(carry, inputs):
            x, state, u, y = carry
            record = (jnp.stack(x), u, y, jnp.stack(_matvec(Cz, x)))
            return advance(x, state, u, *inputs), record

        _, records = jax.lax.scan(body, (x0, state1, u0, y0), inputs, unroll=unroll)
        x, u, y, z = (jnp.moveaxis(r, -1, 0) for r in records) if batch else records  # [B, T, n]
        dt = jnp.asarray(plant.dt, x.dtype)
        t = jnp.arange(steps, dtype=x.dtype).reshape((1,) * dt.ndim + (steps,)) * dt[..., None]  # [T] or [B, T]
        return Trajectory(jnp.broadcast_to(t, x.shape[:-1]), x, u, y, z)

    dtype = scenario.x0.dtype
    zero = jnp.zeros(batch, dtype)
    dt = jnp.broadcast_to(jnp.asarray(plant.dt).astype(dtype), batch)  # a shared constant is free to broadcast
    # [n_f, *batch]: the frequencies shared by the batch or one row per scenario
    freqs = jnp.zeros((0,), dtype) if mode_freqs_hz is None else jnp.asarray(mode_freqs_hz, dtype)
    omega = 2 * jnp.pi * (last(freqs) if freqs.ndim == 2 else jnp.broadcast_to(freqs.reshape((-1,) + (1,) * len(batch)), freqs.shape + batch))

    def metrics_body(carry, inputs):
        x, state, u, k, peak, last_out, ise_t, iae_t, ise_h, effort, peak_x, dft_re, dft_im = carry
        hub, tip = _dot(Cz[0], x), _dot(Cz[1], x)
        peak = _peak_abs(peak, (tip,))
        last_out = jnp.where(jnp.abs(tip) > settling_band * peak, k, last_out)
        t_k = k.astype(dtype) * dt
        windowed = (0.5 - 0.5 * jnp.cos(2 * jnp.pi * k.astype(dtype) / steps)) * tip * dt
        peak_x = _peak_abs(peak_x, x)
        x, state, u_next, _ = advance(x, state, u, *inputs)
        carry = (
            x,
            state,
            u_next,
            k + 1,
            peak,
            last_out,
            ise_t + tip**2 * dt,
            iae_t + jnp.abs(tip) * dt,
            ise_h + hub**2 * dt,
            effort + jnp.sum(u**2, axis=0) * dt,
            peak_x,
            dft_re + windowed[None] * jnp.cos(omega * t_k[None]),
            dft_im - windowed[None] * jnp.sin(omega * t_k[None]),
        )
        return carry, None

    dft0 = jnp.zeros_like(omega)
    carry0 = (x0, state1, u0, jnp.zeros((), jnp.int32), zero, jnp.full(batch, -1, jnp.int32), zero, zero, zero, zero, zero, dft0, dft0)
    final, _ = jax.lax.scan(metrics_body, carry0, inputs, unroll=unroll)
    x_end, _, _, _, peak, last_out, ise_t, iae_t, ise_h, effort, peak_x, dft_re, dft_im = final
    settling = jnp.where(last_out >= steps - 1, jnp.inf, (last_out + 1).astype(dtype) * dt)
    diverged = ~jnp.isfinite(peak_x) | (peak_x > DIVERGENCE_THRESHOLD)
    energy = dft_re**2 + dft_im**2
    return RunMetrics(peak, ise_t, iae_t, ise_h, effort, x_end[0], settling, peak_x, diverged, jnp.moveaxis(energy, 0, -1) if batch else energy)


def _peak_abs_exact(peak: jax.Array, values: tuple[jax.Array, ...]) -> jax.Array:
    """``max(peak, |v_0|, |v_1|, ...)`` elementwise with ``jnp.maximum`` (NaN if any is NaN)."""
    for v in values:
        peak = jnp.maximum(peak, jnp.abs(v))
    return peak


@jax.custom_jvp
def _peak_abs(peak: jax.Array, values: tuple[jax.Array, ...]) -> jax.Array:
    """A running peak of magnitudes: :func:`_peak_abs_exact`, on the floats' bits.

    ``jnp.maximum`` lowers to IEEE 754-2019 ``maximum`` (a NaN wins), which x86 has no
    instruction for: LLVM expands each into a max, compares and blends, and the running
    maxima are a metric kernel of every step. For floats with the sign bit clear (a
    magnitude, and a ``peak`` >= 0 or NaN), the order of their bits read as signed integers
    is the order of the values, +inf above every finite one and every NaN above +inf; so
    clearing the sign bits and taking integer maxima (one ``and`` and one ``max`` each) gives
    the same peak, NaN if any operand is NaN. The derivative is the exact chain's.
    """
    itype = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[peak.dtype.itemsize]
    magnitude = jnp.iinfo(itype).max  # every bit but the sign
    bits = jax.lax.bitcast_convert_type(peak, itype)
    for v in values:
        bits = jnp.maximum(bits, jax.lax.bitcast_convert_type(v, itype) & magnitude)
    return jax.lax.bitcast_convert_type(bits, peak.dtype)


@_peak_abs.defjvp
def _peak_abs_jvp(primals, tangents):
    return jax.jvp(_peak_abs_exact, primals, tangents)


def _dot(row: jax.Array | np.ndarray, x: tuple[jax.Array, ...]) -> jax.Array:
    """``row @ x`` for a state held as a tuple of components, summed left to right.

    The exact zeros of a NumPy ``row`` are skipped: the kernels of a step then read only the
    components they use (the tip deflection two of six, the hub angle one; no state
    component depends on the hub angle's value). The sum is the same for finite ``x``; a
    non-finite component still reaches ``RunMetrics.peak_abs_state``.
    """
    terms = [j for j in range(len(x)) if isinstance(row, jax.Array) or row[j] != 0] or [0]
    total = row[terms[0]] * x[terms[0]]
    for j in terms[1:]:
        total = total + row[j] * x[j]
    return total


def _matmul(A: jax.Array | np.ndarray, B: jax.Array | np.ndarray) -> jax.Array | np.ndarray:
    """``A @ B``, for matrices or batches of them with the batch last ([m, n, B] @ [n, k, B]);
    NumPy for NumPy matrices, so that a concrete plant's products stay concrete."""
    if A.ndim == 2:
        return A @ B
    return jnp.einsum("ijb,jkb->ikb", A, B)


def _matvec(M: jax.Array, x: tuple[jax.Array, ...]) -> tuple[jax.Array, ...]:
    """``M @ x`` [m] as a tuple of components, for ``M`` [m, n] and ``x`` n components."""
    return tuple(_dot(M[i], x) for i in range(M.shape[0]))


def _affine(maps: tuple[jax.Array, jax.Array, jax.Array], x: tuple[jax.Array, ...], u: jax.Array, force: jax.Array) -> tuple[jax.Array, ...]:
    """``A x + B u + E force`` as a tuple of components, for ``maps = (A, B, E)``."""
    A, B, E = maps
    return tuple(_dot(A[i], x) + B[i, 0] * u[0] + E[i, 0] * force[0] for i in range(A.shape[0]))
