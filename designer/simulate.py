"""Sampling trajectories of the generative model."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .validation import InputError, check_finite, check_int, check_rng

if TYPE_CHECKING:  # CasADi is imported where a model is built, not here
    from .model import Model

__all__ = ["Trajectory", "simulate", "simulate_runs", "check_inputs", "check_simulated"]


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A simulated run (or a batch of runs).

    Attributes
    ----------
    x : ndarray, shape (*batch, K + 1, n_x)
        True states ``x_0 .. x_K``.
    z : ndarray, shape (*batch, K, n_z)
        Stacked measurements of all sensors; ``z[..., k, :]`` measures ``x[..., k + 1, :]``.
    modes : ndarray of int, shape (*batch, K), or None
        Switching mode used in the transition ``x_k -> x_{k+1}``.
    inputs : ndarray, shape (K, n_u)
        Known inputs ``u_0 .. u_{K-1}``.
    """

    x: np.ndarray
    z: np.ndarray
    modes: np.ndarray | None
    inputs: np.ndarray

    def per_sensor(self, model: Model) -> np.ndarray:
        """Measurements as ``(*batch, K, n_sensors, max n_z_i)``, padded with NaN."""
        parts = model.split(self.z)
        width = max(model.sensor_dims)
        out = np.full(self.z.shape[:-1] + (model.n_sensors, width), np.nan)
        for i, p in enumerate(parts):
            out[..., i, : p.shape[-1]] = p
        return out


def check_inputs(model: Model, steps: int, inputs) -> np.ndarray:
    """``inputs`` checked as ``(steps, n_u)`` known inputs of ``model`` (``(steps, 0)`` for a model without)."""
    if model.n_u == 0:
        if inputs is not None and np.size(inputs) != 0:
            raise InputError("inputs given but the model has no known inputs")
        return np.zeros((steps, 0))
    if inputs is None:
        raise InputError(f"inputs of shape ({steps}, {model.n_u}) are required by model {model.name!r}")
    u = check_finite("inputs", inputs)
    if u.shape != (steps, model.n_u):
        raise InputError(f"inputs must have shape ({steps}, {model.n_u}), got {u.shape}")
    return u


def check_simulated(model: Model, xs: np.ndarray, zs: np.ndarray) -> None:
    """Refuse simulated states ``xs`` (*batch, K + 1, n_x) or measurements ``zs`` (*batch, K, n_z) that left the
    reals, naming the first step where the model's ``f`` or a sensor's ``h`` is not finite, the sensor and, for
    several runs simulated together, the run (its index in the batch)."""
    batch = xs.shape[:-2]
    runs = int(np.prod(batch))  # not -1: no measurement yet (a state that left the reals at the first step) is empty
    X = xs.reshape(runs, *xs.shape[-2:])
    Z = zs.reshape(runs, *zs.shape[-2:])
    bad_x = ~np.isfinite(X).all(axis=-1)  # (runs, K + 1)
    bad_z = ~np.isfinite(Z)  # (runs, K, n_z); z[k - 1] measures x[k]
    never = X.shape[1] + 1
    k_x = int(np.argmax(bad_x.any(axis=0))) if bad_x.any() else never
    k_z = int(np.argmax(bad_z.any(axis=(0, 2)))) + 1 if bad_z.any() else never
    if k_x == never and k_z == never:
        return

    def at(r: int, k: int) -> str:
        if not batch:
            return f"step {k}"
        where = ", ".join(map(str, np.unravel_index(r, batch)))
        return f"step {k} of run {where} (of {int(np.prod(batch))} simulated together)"

    def vec(x) -> str:
        return "[" + ", ".join(f"{v:.6g}" for v in x) + "]"

    if k_x <= k_z:
        r = int(np.argmax(bad_x[:, k_x]))
        raise InputError(f"the transition f is not finite at {at(r, k_x)}: f(x) from x = {vec(X[r, k_x - 1])}")
    r = int(np.argmax(bad_z[:, k_z - 1].any(axis=-1)))
    comp = int(np.argmax(bad_z[r, k_z - 1]))
    sensor = int(np.searchsorted(model.sensor_offsets[1:], comp, side="right"))
    raise InputError(f"sensor {model.sensors[sensor].name!r}: h is not finite at {at(r, k_z)} "
                     f"(x = {vec(X[r, k_z])})")


def simulate(
    model: Model,
    steps: int,
    rng: np.random.Generator,
    *,
    batch: tuple[int, ...] | int = (),
    x0=None,
    inputs=None,
) -> Trajectory:
    """Sample ``steps`` steps of the model.

    Draw order (fixed, so a seed reproduces a run bit for bit): ``x_0`` from the
    prior (unless given), then at every step the mode, the process noise, and
    the measurement noise of each sensor in turn.

    Parameters
    ----------
    model : Model
    steps : int
        Number of transitions ``K >= 1``.
    rng : numpy.random.Generator or sequence of numpy.random.Generator
        One Generator, or one per run (then ``batch`` is ``(R,)`` or omitted): run ``r``
        draws from ``rng[r]`` exactly as ``simulate(model, steps, rng[r])`` does, and the
        runs are propagated together, so a run's numbers are that call's wherever ``f``
        and ``h`` compute element by element (their NumPy translations do; tested bit for
        bit on the four-tank).
    batch : int or tuple of int
        Leading shape for independent runs drawn together.
    x0 : array_like, shape (n_x,) or (*batch, n_x), optional
        Initial state; sampled from the prior when omitted.
    inputs : array_like, shape (K, n_u), optional
        Known inputs, required when the model has inputs.
    """
    steps = check_int("steps", steps, 1)
    batch = (batch,) if isinstance(batch, (int, np.integer)) else tuple(batch)
    gens = None
    if isinstance(rng, np.random.Generator):
        check_rng(rng)
    else:  # one Generator per run, each drawing as a run of its own
        try:
            gens = [check_rng(g) for g in rng]
        except TypeError:
            raise InputError(f"rng must be a numpy.random.Generator or one per run, got {type(rng).__name__}") from None
        if not gens or batch not in ((), (len(gens),)):
            raise InputError(f"with one Generator per run ({len(gens)}), batch must be ({len(gens)},) or omitted, "
                             f"got {batch}")
        batch = (len(gens),)

    def draw(sample):
        """``sample(rng, shape)`` for the batch: one call, or one per run's Generator (its own draw order)."""
        return sample(rng, batch) if gens is None else np.stack([sample(g, ()) for g in gens])

    u = check_inputs(model, steps, inputs)
    if x0 is None:
        x = draw(model.prior.sample)
    else:
        x = check_finite("x0", x0)
        if x.shape[-1:] != (model.n_x,):
            raise InputError(f"x0 must have shape (..., {model.n_x}), got {x.shape}")
        x = np.broadcast_to(x, batch + (model.n_x,)).copy()
    xs = np.empty(batch + (steps + 1, model.n_x))
    zs = np.empty(batch + (steps, model.n_z))
    modes = np.empty(batch + (steps,), dtype=int) if model.n_modes else None
    xs[..., 0, :] = x
    G = model.noise_gain
    for k in range(steps):
        mode = None
        if modes is not None:
            mode = draw(lambda g, shape: g.choice(model.n_modes, size=shape, p=model.mode_probs))
            modes[..., k] = mode
        w = draw(model.process_noise.sample)
        x = model.f(x, k, u[k], mode) + (w @ G.T if gens is None else np.stack([wr @ G.T for wr in w]))
        xs[..., k + 1, :] = x
        if not np.isfinite(x).all():  # named here: the next f or h would refuse the state without saying why
            check_simulated(model, xs[..., : k + 2, :], zs[..., :k, :])
        z = model.h_all(x, k + 1)
        for i, s in enumerate(model.sensors):
            a, b = model._offsets[i], model._offsets[i + 1]
            z[..., a:b] += draw(s.noise.sample)
        zs[..., k, :] = z
    check_simulated(model, xs, zs)
    return Trajectory(xs, zs, modes, u)


def simulate_runs(
    model: Model,
    steps: int,
    rngs,
    *,
    x0=None,
    inputs=None,
) -> Trajectory:
    """Sample one run per Generator, the runs propagated together (batch ``(R,)``).

    Run ``r`` draws only from ``rngs[r]``, and all of it before any propagation, in
    this order (fixed, documented, so that a run's numbers depend on its own
    Generator only, never on the other runs or their number): ``x_0`` from the prior
    (unless given; ``prior.sample(rng)``), the ``K`` modes (``rng.choice`` with
    ``mode_probs``, if the model switches), the ``K`` process noises
    (``process_noise.sample(rng, K)``), then each sensor's ``K`` measurement noises
    in turn (``noise.sample(rng, K)``).  Then, for every run at once,
    ``x_{k+1} = f(x_k, k, u_k, r_k) + G w_k`` and ``z_k = h(x_{k+1}, k + 1) + v_k``.
    The distribution is :func:`simulate`'s; the numbers are not (it interleaves the
    draws step by step), but the per-run cost in Python is a few calls instead of a
    few per step.

    Parameters
    ----------
    model : Model
    steps : int
        Number of transitions ``K >= 1``.
    rngs : sequence of numpy.random.Generator
        One per run (``R >= 1``).
    x0 : array_like, shape (n_x,) or (R, n_x), optional
        Initial states; sampled from the prior when omitted.
    inputs : array_like, shape (K, n_u), optional
        Known inputs (shared by the runs), required when the model has inputs.
    """
    steps = check_int("steps", steps, 1)
    if isinstance(rngs, np.random.Generator):
        raise InputError("rngs must be a sequence of numpy.random.Generator, one per run (got a single Generator)")
    try:
        gens = [check_rng(g) for g in rngs]
    except TypeError:
        raise InputError(f"rngs must be a sequence of numpy.random.Generator, got {type(rngs).__name__}") from None
    if not gens:
        raise InputError("rngs must hold at least one Generator (one per run)")
    R = len(gens)
    u = check_inputs(model, steps, inputs)
    if x0 is not None:
        x0 = check_finite("x0", x0)
        if x0.shape not in ((model.n_x,), (R, model.n_x)):
            raise InputError(f"x0 must have shape ({model.n_x},) or ({R}, {model.n_x}), got {x0.shape}")
    xs = np.empty((R, steps + 1, model.n_x))
    modes = np.empty((R, steps), dtype=int) if model.n_modes else None
    w = np.empty((R, steps, model.process_noise.dim))
    v = np.empty((R, steps, model.n_z))
    for r, rng in enumerate(gens):
        xs[r, 0] = model.prior.sample(rng) if x0 is None else (x0 if x0.ndim == 1 else x0[r])
        if modes is not None:
            modes[r] = rng.choice(model.n_modes, size=steps, p=model.mode_probs)
        w[r] = model.process_noise.sample(rng, steps)
        for i, s in enumerate(model.sensors):
            v[r, :, model._offsets[i]:model._offsets[i + 1]] = s.noise.sample(rng, steps)
    Gw = w @ model.noise_gain.T
    x = xs[:, 0]
    for k in range(steps):
        x = model.f(x, k, u[k], None if modes is None else modes[:, k]) + Gw[:, k]
        xs[:, k + 1] = x
        if not np.isfinite(x).all():  # named here: the next f or h would refuse the state without saying why
            check_simulated(model, xs[:, : k + 2], np.zeros((R, 0, model.n_z)))
    zs = model.h_all(xs[:, 1:], np.arange(1, steps + 1)) + v
    check_simulated(model, xs, zs)
    return Trajectory(xs, zs, modes, u)
