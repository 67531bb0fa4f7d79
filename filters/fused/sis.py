"""Seed 004's SIS filters on the fused kernels: :func:`sis_fdi` (the NumPy twin: :func:`filters.fdi.run_sis`).

Sequential importance sampling without resampling, for models **with known inputs**
(``x+ = f(x, k, u_k) + G w``), with the detectors and likelihoods of :mod:`filters.fdi`,
one compiled call per run and filter:

* ``detector="normal"`` — the normal PF's (14)/(17) (:func:`filters.fdi.normal_detector`);
* ``detector="modified"`` — the modified PF's (36)/(58) with the corrected particles
  (:func:`filters.fdi.modified_detector`); ``"sampled"`` its non-Gaussian variant, the
  corrected particles drawn from each run's own ``aux_rngs[r]``;
* ``likelihood="additive"`` — the sensors' Gaussian densities
  (:func:`filters.particle.additive_noise_loglik`); ``"mixture"`` — seed 002's adapted to
  deception ``rho`` with probability ``attack_prob`` (:func:`filters.fdi.deception_mixture_loglik`);
  ``"uniform"`` — every particle equally likely (:func:`filters.fdi.uniform_loglik`);
* ``gamma_hat`` subtracted where an attack is declared (estimation mode (59));
  ``linear_weights`` — the NumPy engine's emulation of linear-domain weights, in the
  filter and in the normal detector alike (as the study uses it).

The SIS proposal is the transition, so the particles depend on no measurement and every
filter of a run sees the same ones (the paper's "same set of particles"): they are drawn
once (:func:`sis_particles`, kept with ``f(x_{k-1}, k - 1, u_{k-1})`` for the sampled
correction) and each filter weighs them (:func:`sis_fdi`).  Two functions are generated
per model (:mod:`filters.fused.codegen`): the propagation and the log-likelihood of every
particle (both densities' variants in one function); the loops, the detectors and the
weights are generic code compiled once.  Draws: per step ``n_w`` standard normals per
particle, particle after particle, as ``Gaussian.sample``; so with the same initial
particles and generator a run reproduces ``run_sis`` with one Generator per run to
rounding (the tests check it).  Memory: the particles of every step, ``2 R (K + 1) M n_x``
doubles.

Limitations: no switching modes; Gaussian process noise; Gaussian measurement noise.
"""
from __future__ import annotations

import time
from typing import NamedTuple, Sequence

import numpy as np
from numba.core import types

from designer.jit import scalar_statements
from designer.model import Model
from designer.noise import Gaussian
from designer.simulate import check_inputs
from designer.validation import InputError, check_finite, check_int, check_probability
from filters.fdi import (SISResult, check_gamma_hat, deception_mixture_loglik, detection_gain, measurement_cov,
                         measurement_matrix)
from filters.particle import LOG_TINY, check_finite_means

from .cache import njit
from .codegen import component_lines, components, compile_kernel, model_kernels, noise_terms
from .driver import B1, F1, F2, F3, check_generators, check_model, check_particles, spread
from .streams import STREAM, draw_normals, drawing, open_stream

__all__ = ["DETECTORS", "LIKELIHOODS", "SISParticles", "sis_particles", "sis_fdi"]

#: The detectors by name (None: no detector) and the likelihoods, as the kernel's codes.
DETECTORS = {None: 0, "normal": 1, "modified": 2, "sampled": 3}
LIKELIHOODS = {"additive": 0, "mixture": 1, "uniform": 2}
_NO_DRAWS = open_stream(np.random.default_rng(0))  # the aux stream of a filter that draws none (a placeholder)

PROP_T = types.FunctionType(types.void(F2, F2, F2, types.float64, STREAM, F1))
LIK_T = types.FunctionType(types.void(F2, types.float64, F1, F1, types.float64, types.float64, types.boolean, F1))


# ============================================================================ generated per model
def _propagation(model: Model):
    """``prop(X, XN, FX, k, rng, u)``: ``FX[m] = f(X[m], k, u)``, ``XN[m] = FX[m] + G (mean + L z)``, for every
    particle, its ``n_w`` normals drawn in a row (``Gaussian.sample``'s order)."""
    if "sis_prop" in model_kernels(model):
        return model_kernels(model)["sis_prop"]
    noise = model.process_noise
    if not isinstance(noise, Gaussian):
        raise InputError(f"process_noise of model {model.name!r} is {type(noise).__name__}; the fused SIS filter "
                         "needs Gaussian process noise")
    # f in a loop of its own (no generator call in it, so LLVM may vectorise it), then the draws
    lines = ["def prop(X, XN, FX, k, rng, u):", "    for m in range(X.shape[0]):"]
    lines += scalar_statements(model.casadi_f, ["X[m, {}]", "k", "u[{}]", None], "FX[m, {}]", indent="        ")
    lines += ["    S, h, l = _load(rng)  # the generator's state in registers", f"    z = _np.empty({noise.dim})",
              "    for m in range(X.shape[0]):",
              f"        for j in range({noise.dim}):  # one copy of the sampler's code",
              "            v, h, l = _normal(S, h, l)", "            z[j] = v"]
    lines += [f"        z{j} = z[{j}]" for j in range(noise.dim)]
    lines += [f"        XN[m, {i}] = FX[m, {i}] + ({t})" for i, t in enumerate(noise_terms(model, noise, "z"))]
    lines.append("    _keep(rng, h, l)")
    return compile_kernel(model, "sis_prop", "\n".join(lines), "prop", "the SIS propagation", PROP_T)


def _likelihood(model: Model):
    """``lik(X, k1, z, rho, lq, lp, mixture, ll)``: every particle's log-likelihood of ``z`` into ``ll``.

    ``Σ_s log p_s(z_s − h_s(x))`` (``filters.particle.additive_noise_loglik``), or with
    ``mixture`` ``Σ_s logaddexp(lq + log p_s(r_s), lp + log p_s(r_s − rho_s))``
    (``filters.fdi.deception_mixture_loglik``), each sensor's Gaussian constants inlined.
    """
    key = "sis_lik"
    if key in model_kernels(model):
        return model_kernels(model)[key]
    sensors = []
    for s, sensor in enumerate(model.sensors):
        comps = components(sensor.noise, f"model.sensors[{s}]")
        if len(comps) != 1:
            raise InputError(f"model.sensors[{s}] noise is {type(sensor.noise).__name__}; the fused SIS filter needs "
                             "Gaussian measurement noise")
        sensors.append(comps)
    offsets = model._offsets
    ind = " " * 12
    lines = ["def lik(X, k, z, rho, lq, lp, mixture, ll):", "    for m in range(X.shape[0]):"]
    lines += scalar_statements(model.casadi_h_all, ["X[m, {}]", "k"], "h{}", indent="        ")
    lines.append("        total = 0.0")
    for branch in ("if mixture:", "else:"):
        lines.append(f"        {branch}")
        for s, comps in enumerate(sensors):
            rows = range(int(offsets[s]), int(offsets[s + 1]))
            r = [f"r{j}" for j in range(len(rows))]
            lines += [f"{ind}r{j} = z[{a}] - h{a}" for j, a in enumerate(rows)]
            lines += component_lines(comps, r, ind)  # t0 = log p_s(r)
            if branch == "else:":
                lines.append(f"{ind}total = total + t0")
                continue
            lines.append(f"{ind}clean = lq + t0")
            lines += [f"{ind}r{j} = r{j} - rho[{a}]" for j, a in enumerate(rows)]
            lines += component_lines(comps, r, ind)
            lines.append(f"{ind}total = total + _logaddexp(clean, lp + t0)")
    lines.append("        ll[m] = total")
    return compile_kernel(model, key, "\n".join(lines), "lik", "the SIS likelihood", LIK_T)


# ============================================================================ the generic loop
@njit()
def _normalise(lw, W):
    """``W`` = :attr:`filters.particle.LogWeights.W` of the log weights ``lw``; returns ``Σ W²``."""
    M = lw.shape[0]
    mx = -np.inf
    for m in range(M):
        mx = lw[m] if lw[m] > mx else mx
    a = mx if (mx > -np.inf and mx < np.inf) else 0.0
    acc = 0.0
    for m in range(M):
        acc += np.exp(lw[m] - a)
    ln = np.log(acc) + a  # scipy's logsumexp
    if not (ln > -np.inf and ln < np.inf):  # every weight vanished (or an infinite one): uniform
        for m in range(M):
            W[m] = 1.0 / M
    else:
        tot = 0.0
        for m in range(M):
            W[m] = np.exp(lw[m] - ln)
            tot += W[m]
        if abs(tot - 1.0) > 1e-9:  # |lw| so large that ln lost its digits: normalise by the maximum
            tot = 0.0
            for m in range(M):
                W[m] = np.exp(lw[m] - mx)
                tot += W[m]
            for m in range(M):
                W[m] /= tot
    s2 = 0.0
    for m in range(M):
        s2 += W[m] * W[m]
    return s2


@njit()
def _logsumexp(lw):
    mx = -np.inf
    for m in range(lw.shape[0]):
        mx = lw[m] if lw[m] > mx else mx
    a = mx if (mx > -np.inf and mx < np.inf) else 0.0
    acc = 0.0
    for m in range(lw.shape[0]):
        acc += np.exp(lw[m] - a)
    return np.log(acc) + a


@njit()
def _exceeds(x, z, G, eta, r):
    """``‖z − G x‖ > η`` (``r`` scratch of length n_y)."""
    ny, n = G.shape
    s = 0.0
    for j in range(ny):
        gx = 0.0
        for i in range(n):
            gx += G[j, i] * x[i]
        r[j] = z[j] - gx
        s += r[j] * r[j]
    return np.sqrt(s) > eta


@njit()
def _correct(x, z, G, Kd, r, out):
    """(36): ``out = x + K (z − G x)``."""
    ny, n = G.shape
    for j in range(ny):
        gx = 0.0
        for i in range(n):
            gx += G[j, i] * x[i]
        r[j] = z[j] - gx
    for i in range(n):
        acc = 0.0
        for j in range(ny):
            acc += Kd[i, j] * r[j]
        out[i] = x[i] + acc


def _sis_particles(prop, x0, rng, U, X, FX):
    """The particles of one run: ``X[0] = x0``, ``X[k + 1] = f(X[k], k, u_k) + G w`` (``FX[k]`` = the ``f`` part)."""
    X[0] = x0
    for k in range(FX.shape[0]):
        prop(X[k], X[k + 1], FX[k], float(k), rng, U[k])


def _sis_weigh(lik, X, FX, aux, Z, GH, use_gh, G, Kd, Lq, eta, zeta, det, lin, kind, rho, lq, lp, mean, beta,
               detected, ess, collapsed):
    """One run of :func:`filters.fdi.run_sis` on its particles ``X`` (see :func:`sis_fdi`); outputs in place."""
    M, n = X.shape[1], X.shape[2]
    K, ny = Z.shape
    lw = np.zeros(M)
    ll = np.empty(M)
    lld = np.empty(M)
    W = np.empty(M)
    zk = np.empty(ny)
    r = np.empty(ny)
    xt = np.empty(n)
    zz = np.empty(n)
    _normalise(lw, W)
    x = X[0]
    for i in range(n):
        acc = 0.0
        for m in range(M):
            acc += W[m] * x[m, i]
        mean[0, i] = acc
    for k in range(K):
        x = X[k + 1]  # Step 1: the particles, drawn before (sis_particles)
        fx = FX[k]
        for j in range(ny):
            zk[j] = Z[k, j]
        if det != 0:  # Step 2: detection mode
            b = 0.0
            if det == 1:  # normal PF: (14) with the normalised likelihoods (17)
                lik(x, float(k + 1), zk, rho, 0.0, 0.0, False, lld)
                if lin:  # linear double precision: exp underflows to 0, and 0/0 is NaN (no attack declared)
                    tot = 0.0
                    for m in range(M):
                        W[m] = np.exp(lld[m])
                        tot += W[m]
                    for m in range(M):
                        W[m] = W[m] / tot
                else:
                    for m in range(M):
                        lld[m] = lld[m] if lld[m] == lld[m] else -np.inf
                    _normalise(lld, W)
                for m in range(M):
                    if _exceeds(x[m], zk, G, eta, r):
                        b += W[m]
            else:  # modified PF: the share of corrected residuals longer than eta (58)
                count = 0
                for m in range(M):
                    if det == 2:
                        _correct(x[m], zk, G, Kd, r, xt)
                    else:  # sampled from N(f + K (z - G f), Q - K G Q), the run's own aux Generator
                        draw_normals(aux, zz, 0, n)
                        _correct(fx[m], zk, G, Kd, r, xt)
                        for i in range(n):
                            acc = 0.0
                            for j in range(n):
                                acc += Lq[i, j] * zz[j]
                            xt[i] += acc
                    if _exceeds(xt, zk, G, eta, r):
                        count += 1
                b = count / M
            beta[k] = b
            detected[k] = b > zeta  # NaN declares nothing
            if use_gh and detected[k]:
                for j in range(ny):
                    zk[j] = zk[j] - GH[k, j]
        if kind == 2:
            ll[:] = 0.0
        else:
            lik(x, float(k + 1), zk, rho, lq, lp, kind == 1, ll)  # Step 3: estimation mode (59)
        prev = _logsumexp(lw)
        dead = True
        for m in range(M):
            v = lw[m] + ll[m]
            v = v if v == v else -np.inf
            if lin and v - prev < LOG_TINY:
                v = -np.inf
            lw[m] = v
            dead = dead and v == -np.inf
        if dead:
            collapsed[k] = True
            lw[:] = 0.0
        s2 = _normalise(lw, W)
        for i in range(n):
            acc = 0.0
            for m in range(M):
                acc += W[m] * x[m, i]
            mean[k + 1, i] = acc  # (60)
        ess[k] = 1.0 / s2


_RUN: dict = {}


def _driver(which: str):
    """The compiled entry point of :func:`_sis_particles` or :func:`_sis_weigh` (no type resolution per call, see
    :func:`filters.fused.driver.drivers`)."""
    if which not in _RUN:
        i8, f8, bo = types.int64, types.float64, types.boolean
        if which == "particles":
            fn, sig = _sis_particles, types.void(PROP_T, F2, STREAM, F2, F3, F3)
        else:
            fn, sig = _sis_weigh, types.void(LIK_T, F3, F3, STREAM, F2, F2, bo, F2, F2, F2, f8, f8, i8, bo, i8, F1, f8,
                                             f8, F2, F1, B1, F1, B1)
        disp = njit()(fn)
        disp.compile(sig)
        _RUN[which] = disp.overloads[tuple(sig.args)].entry_point
    return _RUN[which]


# ============================================================================ public
class SISParticles(NamedTuple):
    """The particles of every run of an SIS filter (``R`` runs, ``K`` steps, ``M`` particles): :func:`sis_particles`."""

    x: np.ndarray  # (R, K + 1, M, n_x): x_0 (the initial particles), then x_k ~ p(x_k | x_{k-1})
    fx: np.ndarray  # (R, K, M, n_x): f(x_{k-1}, k - 1, u_{k-1}) of step k, before the noise (the sampled correction's)
    wall_time_s: float  # time of the compiled loop over all runs


def sis_particles(model: Model, x0: np.ndarray, rngs: Sequence[np.random.Generator], steps: int, *,
                  inputs: np.ndarray | None = None, threads: int = 1) -> SISParticles:
    """The particles of an SIS filter whose proposal is the transition (Step 1 of :func:`filters.fdi.run_sis`).

    They depend on no measurement, so every filter of :func:`sis_fdi` given them sees the
    same particles (the paper's "same set of particles"): drawn once, weighed by each.

    Parameters
    ----------
    model : Model
        Known inputs allowed, no switching modes; Gaussian process noise.
    x0 : ndarray, shape (R, M, n_x)
        Initial particles of every run (``model.prior.sample(rngs[r], M)``, as ``run_sis`` draws them).
    rngs : sequence of R numpy.random.Generator
        The particles' randomness, one per run: per step ``n_w`` normals per particle, particle after particle.
    steps : int
        ``K``.
    inputs : ndarray, shape (K, n_u)
        The known inputs (required by a model with inputs).
    threads : int
        Threads the runs are spread over (the results do not depend on it).
    """
    model = check_model(model, inputs=True)
    x0 = check_particles(x0, model.n_x)
    R, M, n = x0.shape
    gens = check_generators(rngs, R)
    K = check_int("steps", steps, 1)
    U = np.ascontiguousarray(check_inputs(model, K, inputs), dtype=np.float64)
    threads = check_int("threads", threads, 1)
    prop, run = _propagation(model), _driver("particles")
    X = np.empty((R, K + 1, M, n))
    FX = np.empty((R, K, M, n))
    t0 = time.perf_counter()
    spread(lambda r: drawing(gens[r], lambda st: run(prop, x0[r], st, U, X[r], FX[r])), R, threads)
    return SISParticles(X, FX, time.perf_counter() - t0)


def sis_fdi(model: Model, particles: SISParticles, z: np.ndarray, *, likelihood: str = "additive",
            attack_prob: float = 0.0, deception=None, detector: str | None = None, eta: float | None = None,
            zeta: float | None = None, gamma_hat=None, linear_weights: bool = False,
            aux_rngs: Sequence[np.random.Generator] | None = None, threads: int = 1):
    """Seed 004's SIS filter (no resampling) with a detector on given particles, fused numba kernels, many runs.

    ``sis_fdi(model, sis_particles(model, x0, rngs, K, inputs=u), z, ...)`` is
    ``run_sis(model, z, rngs, particles=M, inputs=u, ...)`` with the detector and
    likelihood named here (see the module notes), to rounding.

    Parameters
    ----------
    model : Model
        The model of the particles; Gaussian measurement noise; a linear measurement
        ``y = G x + v`` for the detectors.
    particles : SISParticles
        Of every run (:func:`sis_particles`).
    z : ndarray, shape (R, K, n_z)
        Received measurements; ``z[:, k]`` measures ``x_{k+1}``.
    likelihood : {'additive', 'mixture', 'uniform'}
        See the module notes; ``'mixture'`` takes ``attack_prob`` (``p_l``) and ``deception`` (``rho``, (n_z,)).
    detector : {None, 'normal', 'modified', 'sampled'}
        With ``eta`` (the residual threshold) and ``zeta`` (the detection threshold).
    gamma_hat : ndarray, shape (R, K, n_z) or (K, n_z), optional
        Attack estimate subtracted where an attack is declared (needs a detector).
    linear_weights : bool
        Emulate linear-domain weights (the filter's, and the normal detector's (17)).
    aux_rngs : sequence of R numpy.random.Generator
        The sampled correction's own draws, one per run (``detector='sampled'`` only).
    threads : int
        Threads the runs are spread over (the results do not depend on it).

    Returns
    -------
    filters.fdi.SISResult
        ``wall_time_s`` is the time of the compiled loops over all runs, the particles'
        (:attr:`SISParticles.wall_time_s`) included: the filter's cost had it drawn them alone.
    """
    model = check_model(model, inputs=True)
    if not isinstance(particles, SISParticles):
        raise InputError(f"particles must be the SISParticles of sis_particles, got {type(particles).__name__}")
    X, FX = particles.x, particles.fx
    if X.ndim != 4 or X.shape[3] != model.n_x or FX.shape != (X.shape[0], X.shape[1] - 1) + X.shape[2:]:
        raise InputError(f"particles must be of a model with {model.n_x} states (sis_particles)")
    R, K1, M, n = X.shape
    Z = np.ascontiguousarray(check_finite("z", z), dtype=np.float64)
    if Z.shape != (R, K1 - 1, model.n_z):
        raise InputError(f"z must have shape (runs, K, n_z) = ({R}, {K1 - 1}, {model.n_z}), the particles' runs and "
                         f"steps, got {Z.shape}")
    if likelihood not in LIKELIHOODS:
        raise InputError(f"likelihood must be one of {', '.join(LIKELIHOODS)}, got {likelihood!r}")
    rho = np.zeros(model.n_z)
    lq = lp = 0.0
    if likelihood != "mixture" and (deception is not None or attack_prob != 0.0):
        raise InputError("attack_prob and deception belong to likelihood='mixture'")
    if likelihood == "mixture":
        deception_mixture_loglik(model, attack_prob=attack_prob, deception=deception)  # its checks
        rho = np.array(check_finite("deception", deception), dtype=np.float64)
        p = float(check_probability("attack_prob", attack_prob, open_upper=True))
        with np.errstate(divide="ignore"):
            lp, lq = float(np.log(p)), float(np.log1p(-p))
    if detector not in DETECTORS:
        raise InputError(f"detector must be one of None, 'normal', 'modified', 'sampled', got {detector!r}")
    G = np.zeros((model.n_z, n))
    Kd = np.zeros((n, model.n_z))
    Lq = np.zeros((n, n))
    if detector is None and (eta is not None or zeta is not None):
        raise InputError("eta and zeta are the detector's thresholds: pass a detector")
    if detector is not None:
        if eta is None or zeta is None:
            raise InputError("eta (the residual threshold) and zeta (the detection threshold) are required with a "
                             "detector")
        eta = float(check_finite("eta", eta))
        if eta <= 0.0:
            raise InputError(f"eta must be > 0, got {eta!r}")
        zeta = float(check_finite("zeta", zeta))
        G = measurement_matrix(model)
        if detector != "normal":
            Kd = detection_gain(G, model.process_cov, measurement_cov(model))
        if detector == "sampled":
            S = model.process_cov - Kd @ G @ model.process_cov
            Lq = Gaussian.zero_mean(0.5 * (S + S.T))._chol  # the corrected proposal's q (filters.fdi)
    if detector == "sampled":
        if aux_rngs is None:
            raise InputError("aux_rngs: the sampled correction draws particles; pass one Generator per run")
        aux = check_generators(aux_rngs, R)
    else:
        if aux_rngs is not None:
            raise InputError("aux_rngs: only detector='sampled' draws from them")
        aux = [None] * R  # never drawn from
    if gamma_hat is not None:
        GH = np.ascontiguousarray(check_gamma_hat(gamma_hat, Z.shape, detector is not None), dtype=np.float64)
    else:
        GH = np.zeros((1, 1, model.n_z))
    if not isinstance(linear_weights, (bool, np.bool_)):
        raise InputError(f"linear_weights must be True or False, got {linear_weights!r}")
    threads = check_int("threads", threads, 1)
    lik, run = _likelihood(model), _driver("weigh")  # the uniform likelihood never calls lik
    mean = np.empty((R, K1, n))
    beta = np.full((R, K1 - 1), np.nan)
    detected = np.zeros((R, K1 - 1), dtype=np.bool_)
    ess = np.empty((R, K1 - 1))
    collapsed = np.zeros((R, K1 - 1), dtype=np.bool_)
    G, Kd, Lq = (np.ascontiguousarray(a, dtype=np.float64) for a in (G, Kd, Lq))
    det, kind = DETECTORS[detector], LIKELIHOODS[likelihood]

    def one(r: int) -> None:
        def call(st):
            run(lik, X[r], FX[r], st, Z[r], GH[r if gamma_hat is not None else 0], gamma_hat is not None, G, Kd, Lq,
                float(eta or 0.0), float(zeta or 0.0), det, bool(linear_weights), kind, rho, lq, lp, mean[r], beta[r],
                detected[r], ess[r], collapsed[r])
        if aux[r] is None:  # draws nothing
            call(_NO_DRAWS)
        else:
            drawing(aux[r], call)

    t0 = time.perf_counter()
    spread(one, R, threads)
    wall = time.perf_counter() - t0 + particles.wall_time_s
    return SISResult(check_finite_means(mean, "fused SIS particle filter"), beta, detected, ess, collapsed, wall)
