"""Seed 000's packet likelihoods on the fused kernels: :func:`sir_packets` (the NumPy twin: :mod:`filters.rrp`).

At step ``k`` a set of ``P`` packets, packet ``p`` from sensor ``sensors[k, p]`` with
received value ``y[r, k, p]``::

    log p(y_k | x) = Σ_p logaddexp(log_clean + log p_ν(wrap(y − h_s(x))), attack[r, k, p])

with ``p_ν`` the sensor's Gaussian or Gaussian-mixture noise.  ``log_clean = 0`` and
``attack = −inf`` give the standard likelihood; ``log_clean = log(1 − η̄)`` and
``attack = log η̄ + log p_ξ(y)`` (:func:`filters.rrp.deception_terms`) the attack-aware
one of seed 000 (14).  ``P = 1`` with the Round-Robin schedule gives the RRP filters,
``P = N`` with every sensor PF-DA: :func:`filters.rrp.rrp_loglik` and
:func:`filters.rrp.all_sensors_loglik` are the NumPy engine's forms of the same.

Numbers: the kernels' draws (:mod:`filters.fused.streams`) are NumPy's
``Generator.standard_normal`` and ``Generator.random`` bit for bit, in the NumPy engine's order (per step
``n_w`` normals per particle, particle after particle, then the resampler's uniforms),
so a one-run call reproduces ``run_sir(..., runs=1)`` with the same generator to
rounding (given the same initial particles; the tests check it).

Limitations: models without known inputs and without switching modes; Gaussian
process noise (any ``noise_gain``); Gaussian or Gaussian-mixture measurement noise.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numba.core import types

from designer.jit import scalar_statements
from designer.model import Model
from designer.validation import InputError
from filters.result import FilterResult
from filters.rrp import angle_sets

from .codegen import component_lines, components, compile_kernel, max_others_lines, model_kernels, propagation, \
    shared_bodies, weights
from .driver import BLOCK, F2, F3, I2, check_generators, check_model, check_options, check_particles, \
    drivers, lik_type, run_all

__all__ = ["sir_packets", "packets_loglik"]

#: The family's data per run: sensors (K, P), values (K, P, n_y), attack terms (K, P), log_clean.
DATA = types.Tuple((I2, F3, F2, types.float64))
LIK_T = lik_type(DATA)


def sir_packets(
    model: Model,
    x0: np.ndarray,
    rngs: Sequence[np.random.Generator],
    sensors: np.ndarray,
    y: np.ndarray,
    *,
    attack: np.ndarray | None = None,
    log_clean: float = 0.0,
    angles: Sequence = (),
    resampler: str = "systematic",
    ess_threshold: float = 1.0,
    covariance: bool = False,
    threads: int = 1,
    linear_weights: bool = False,
) -> FilterResult:
    """Bootstrap filter on packets of sensor measurements, many runs, fused numba kernels.

    Parameters
    ----------
    model : Model
        Without known inputs or switching modes; Gaussian process noise; every
        sensor's noise Gaussian or GaussianMixture.
    x0 : ndarray, shape (R, M, n_x)
        Initial particles of every run (sampled by the caller, e.g. with each run's generator).
    rngs : sequence of R numpy.random.Generator
        One distinct generator per run.
    sensors : int ndarray, shape (K, P) (or (K,) for P = 1)
        Sensor of packet ``p`` at step ``k`` (the step's packets measure ``x_{k+1}``).
    y : ndarray, shape (R, K, P, n_y) (or (R, K, n_y) for P = 1)
        Received values; ``n_y`` is the largest sensor dimension and a smaller
        sensor uses the leading components.  Must be finite where used.
    attack : ndarray, shape (R, K, P) (or (R, K) for P = 1), optional
        ``log η̄ + log p_ξ(y)`` per packet (:func:`filters.rrp.deception_terms`); ``-inf`` (the
        default, everywhere) gives the standard likelihood.
    log_clean : float
        ``log(1 − η̄)`` (0 for the standard likelihood).
    angles : sequence
        Residual components wrapped into (−π, π]: component indices (for every
        sensor) or ``(sensor, component)`` pairs (as a model's
        ``angle_components``, from its sensors' ``angles``).
    resampler : {'systematic', 'stratified', 'multinomial', 'residual'}
    ess_threshold : float in (0, 1]
        Resample when ESS < ``ess_threshold * M``; 1 resamples at every step.
    covariance : bool
        Also return the weighted covariance at every step.
    threads : int
        Threads the runs are spread over (the results do not depend on it).
    linear_weights : bool
        Emulate linear-domain weights as :func:`filters.particle.run_sir` does: a normalised
        weight that underflows double precision becomes zero, and a step where every weight
        does is a collapse (:mod:`filters.fused.driver`).  Default: log domain.

    Returns
    -------
    FilterResult
        The fusion centre's runs (:func:`filters.result.centralized_result`: ``P`` messages per step, its
        packets; ``cov`` None unless ``covariance``), ``detail`` the :class:`filters.fused.FastSIRResult`
        (means, covariances, ESS, log marginal likelihood, the steps resampled and collapsed).
    """
    model = check_model(model)
    x0 = check_particles(x0, model.n_x)
    R = x0.shape[0]
    gens = check_generators(rngs, R)
    scheme, thr, threads, covariance = check_options(resampler, ess_threshold, threads, covariance)
    if not isinstance(linear_weights, (bool, np.bool_)):
        raise InputError(f"linear_weights must be True or False, got {linear_weights!r}")
    sens, yy, att, lc = packet_data(model, R, sensors, y, attack, log_clean)
    lik, ne = packet_lik(model, wrap_set(angles, model), bool(np.any(att > -np.inf)))
    kernels = (propagation(model), 0, lik, sens.shape[1], ne, weights(model))
    return run_all(DATA, kernels, lambda r: (sens, yy[r], att[r], lc), x0, gens, sens.shape[0], scheme, thr,
                   covariance, threads, sens.shape[1], linear_weights=bool(linear_weights))


def packets_loglik(model: Model, x, k1: int, sensors, y, *, attack=None, log_clean: float = 0.0,
                   angles: Sequence = ()) -> np.ndarray:
    """One step's packet log-likelihood for particles ``x`` (R, M, n_x), evaluated by the kernels' code.

    ``sensors`` (P,), ``y`` (R, P, n_y) (or (R, n_y) for P = 1), ``attack`` (R, P) (or (R,));
    returns (R, M), a non-finite value as ``-inf`` (as the filter weighs it).  ``k1`` is
    the time of the measured state (``h(x, k1)``).  For tests and diagnostics: it runs
    the same generated code as :func:`sir_packets`.
    """
    model = check_model(model)
    x = check_particles(x, model.n_x, "x")
    R = x.shape[0]
    sens = np.asarray(sensors)
    sens = sens.reshape(1, -1) if sens.ndim <= 1 else sens
    yy = np.asarray(y, dtype=np.float64)
    yy = yy[:, None] if yy.ndim in (2, 3) else yy
    att = None if attack is None else np.asarray(attack, dtype=np.float64)[:, None]
    sens, yy, att, lc = packet_data(model, R, sens, yy, att, log_clean)
    lik, ne = packet_lik(model, wrap_set(angles, model), bool(np.any(att > -np.inf)))
    rows = drivers(DATA, 1)
    out = np.empty(x.shape[:2])
    for r in range(R):
        rows(lik, sens.shape[1], ne, x[r], float(k1), (sens, yy[r], att[r], lc), out[r])
    return out


# ============================================================================ generated likelihood and checks
def packet_lik(model: Model, wrap: tuple, attacked: bool):
    """``(lik, NE)`` of the packet likelihood (see :func:`likelihood_block`), ``data = (sens, Y, att, lc)``.

    For packet ``p`` of step ``t`` from sensor ``s = sens[t, p]`` with ``a = att[t, p]``
    and, per particle, ``r = wrap(Y[t, p] − h_s(X[m], k))``::

        logaddexp(lc + log p_ν_s(r), a) = mx + log(1 + Σ_{i < NE} exp(slot_i))

    the log-sum-exp over ``lc +`` each mixture component's log term and ``a``, split
    into its largest term (added to ``b[m]``) and the others relative to it (the
    ``NE`` slots of the packet).  Model, noise constants and the wrapping are
    inlined (generated per model, wrap set and ``attacked``); ``NE`` is the largest
    number of components of a sensor, less one unless ``attacked``
    (``attacked=False`` leaves ``a`` out: for ``a = -inf`` everywhere).  One loop over
    the block per sensor, without branches or calls when ``h`` has none, so that
    it vectorises.
    """
    key = ("packet", wrap, attacked)
    cache = model_kernels(model)
    if key in cache:
        return cache[key]
    comps = [components(sensor.noise, f"model.sensors[{s}]") for s, sensor in enumerate(model.sensors)]
    ne = max(len(c) for c in comps) - (0 if attacked else 1)  # the terms less the largest
    # views indexed from 0 (no negative-index wraparound in the loop, which then vectorises), X flat: the stride
    # of its rows a constant
    nx = model.n_x
    lines = ["def lik(X, m0, n, k, data, t, b, ex):", "    sens, Y, att, lc = data",
             f"    Xf = X.reshape(-1)[m0 * {nx}:(m0 + n) * {nx}]", "    bb = b[m0:m0 + n]",
             "    for p in range(sens.shape[1]):", "        s = sens[t, p]", "        a = att[t, p]"]
    for i in range(ne):  # the packet's slots
        q = f"p * {ne * BLOCK} + {i * BLOCK}"
        lines.append(f"        x{i} = ex[{q}:{q} + n]")
    ind = " " * 16
    bodies = []
    for s, (sensor, fun) in enumerate(zip(model.sensors, model.casadi_h)):
        body = [f"            y{j} = Y[t, p, {j}]" for j in range(sensor.dim)] + ["            for mm in range(n):"]
        body += scalar_statements(fun, [f"Xf[mm * {nx} + {{}}]", "k"], "h{}", indent=ind)
        # angles into (-pi, pi] as filters.rrp.wrap_angles (a no-op inside, to rounding)
        body += [f"{ind}r{j} = {'_wrap(' if (s, j) in wrap else '('}y{j} - h{j})" for j in range(sensor.dim)]
        body += component_lines(comps[s], [f"r{j}" for j in range(sensor.dim)], ind)
        terms = [f"lc + t{c}" for c in range(len(comps[s]))] + (["a"] if attacked else [])
        bodies.append("\n".join(body + max_others_lines(terms, ne, ind)))
    tables = []  # module-level constants: the literals that differ between the sensors of a group, one row per sensor
    for g, (members, body, table) in enumerate(shared_bodies(bodies)):
        lines.append(f"        {'if' if g == 0 else 'elif'} {' or '.join(f's == {i}' for i in members)}:")
        lines += [f"            c{j} = _K{g}[s, {j}]" for j in range(table.shape[1])]
        lines.append(body)
        tables.append(f"_K{g} = _np.array({table.tolist()!r}).reshape({table.shape})")
    lines += ["        else:", "            bb[:] = _m.nan"]
    cache[key] = compile_kernel(model, ("lik", key), "\n".join(tables + lines), "lik", "the packet likelihood",
                                LIK_T), ne
    return cache[key]


def wrap_set(angles, model: Model) -> tuple:
    """Sorted ``(sensor, component)`` pairs of the angular components (:func:`filters.rrp.angle_sets`)."""
    return tuple((s, j) for s, comps in enumerate(angle_sets(model, angles)) for j in comps)


def packet_data(model: Model, R: int, sensors, y, attack, log_clean):
    """Validated ``(sens (K, P), y (R, K, P, n_y), attack (R, K, P), log_clean)``."""
    S = model.n_sensors
    dims = np.asarray(model.sensor_dims, dtype=np.int64)
    width = int(dims.max())
    sens = np.asarray(sensors)
    if sens.dtype.kind not in "iu":
        raise InputError(f"sensors must be an integer array, got dtype {sens.dtype}")
    if sens.ndim == 1:
        sens = sens[:, None]
    if sens.ndim != 2 or sens.shape[0] < 1 or sens.shape[1] < 1:
        raise InputError(f"sensors must have shape (K, P) (or (K,) for one packet per step), got {np.shape(sensors)}")
    if np.any((sens < 0) | (sens >= S)):
        raise InputError(f"sensors must hold sensor indices in 0..{S - 1}")
    sens = np.require(sens, np.int64, ["C", "W"])
    K, P = sens.shape
    try:
        yy = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"y must be numeric: {exc}") from None
    if P == 1 and yy.ndim == 3:
        yy = yy[:, :, None, :]
    if yy.shape != (R, K, P, width):
        raise InputError(f"y must have shape (runs, K, P, n_y) = ({R}, {K}, {P}, {width}), got {np.shape(y)}")
    used = np.arange(width) < dims[sens][..., None]  # (K, P, width): the components each packet carries
    if not np.all(np.isfinite(yy) | ~used):
        raise InputError("y must be finite in every received component (NaN measurements are not treated as missing)")
    yy = np.ascontiguousarray(np.where(used, yy, 0.0))
    if attack is None:
        att = np.full((R, K, P), -np.inf)
    else:
        try:
            att = np.asarray(attack, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"attack must be numeric: {exc}") from None
        if P == 1 and att.shape == (R, K):
            att = att[..., None]
        if att.shape != (R, K, P):
            raise InputError(f"attack must have shape (runs, K, P) = ({R}, {K}, {P}), got {np.shape(attack)}")
        if np.any(np.isnan(att) | (att == np.inf)):
            raise InputError("attack must hold finite values or -inf (no NaN or +inf log terms)")
        att = np.require(att, np.float64, ["C", "W"])
    if isinstance(log_clean, bool) or not isinstance(log_clean, (int, float, np.integer, np.floating)) \
            or not float(log_clean) <= 0.0:
        raise InputError(f"log_clean must be a number <= 0 (a log probability), got {log_clean!r}")
    return sens, yy, att, float(log_clean)
