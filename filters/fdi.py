"""Seed 004: false-data-injection (bias) attacks and the particle filters that detect them.

Sadeghzadeh-Nokhodberiz, Meskin, Hasanzadeh (IEEE Access 2022).  The plant is
``x_{k+1} = f(x_k, u_k) + w_k`` with a linear measurement ``y_k = G x_k + v_k``;
the attacker adds a bias with Bernoulli occurrences::

    ỹ_k = y_k + l_k γ_k,   l_k ~ Bernoulli(p_l),   γ_{k+1} = τ γ_k + (1 - τ) γ̄,   γ_0 = 0     (3)-(4)

Filters (sequential importance sampling, *no resampling*, as in the paper; the
particles ``x_k^i ~ p(x_k | x_{k-1}^i)`` do not depend on the measurements, so
every filter run from the same Generator sees the same particles):

* the **normal PF** — weights ``w_k ∝ w_{k-1} p(ỹ_k | x_k^i)`` (6)-(7); its
  probability of attack (14) weights the residuals ``ỹ_k - G x_k^i`` by the
  normalised likelihoods (17) (:func:`normal_detector`);
* the **modified PF** of section IV — detection mode: each particle corrected with
  the measurement, ``x̃^{i+} = x^i + K (ỹ - G x^i)``, ``K = Q Gᵀ (R + G Q Gᵀ)⁻¹``
  (35)-(36), and ``β̃_k`` = the share of corrected residuals longer than ``η`` (58)
  (:func:`modified_detector`); an attack is declared when ``β̃_k > ζ`` (46).
  Estimation mode (59): ``w_k ∝ w_{k-1} p(ỹ_k - l̂_k γ̂_k | x_k^i)`` with the
  detection ``l̂_k`` and an attack estimate ``γ̂_k`` (``gamma_hat`` of :func:`run_sis`);
* the **likelihood method of [31]** (seed 002) adapted as the paper does (no DoS,
  no flips, deception probability ``p_l`` per sensor, deception vector ``γ̄``)
  (:func:`deception_mixture_loglik`), or literally as the paper describes its
  outcome, uniform weights (:func:`uniform_loglik`).

Thresholds: ``η = ς ‖γ‖_min`` with ``ς = |σ̄ - 1|``, ``σ̄`` the singular value of
``G K`` nearest to 1 (45) (:func:`residual_threshold`); ``ζ = α (N - 1)/N`` with
``p_l N/(N - 1) <= α < 1`` (46), (53) (:func:`attack_threshold`).

The non-Gaussian variant.  (36) is the mean of the optimal proposal
``p(x_k | x_{k-1}, ỹ_k)`` (35) when the noises are Gaussian.  For any noise
densities :func:`corrected_proposal` draws from the Gaussian built from the
noises' covariances (35) and returns the importance correction
``log p(x | x_{k-1}) - log q(x | x_{k-1}, ỹ)`` computed with the *true* transition
density, so that weights ``w_{k-1} p(ỹ | x) p(x | x_{k-1}) / q`` remain exact
(usable as the proposal of :func:`filters.particle.run_sir`).  Its samples are the
corrected particles of ``modified_detector(..., correction="sampled")``, whose
residuals are weighted ``1/N`` as (58) prescribes (the paper's Theorem 1 proof).

Numerics.  Weights are kept in the log domain.  ``linear_weights=True`` emulates a
filter that keeps them (and the likelihoods of (17)) in linear double precision,
as a MATLAB implementation does: a value below the smallest positive double
becomes 0, and (17) with every likelihood 0 is 0/0, so no attack is declared.  That
underflow is what makes the normal PF miss *large* attacks (section III-B, Fig. 9):
with log-domain normalisation (17) stays a proper distribution and large attacks
are detected.
"""
from __future__ import annotations

import time
from typing import Callable, NamedTuple

import casadi as ca
import numpy as np
from scipy.linalg import block_diag, cho_factor, cho_solve

from designer.model import Model
from designer.noise import Gaussian
from designer.validation import InputError, check_covariance, check_finite, check_int, check_probability, check_rng

from .particle import LOG_TINY, LogWeights, additive_noise_loglik, check_finite_means

__all__ = [
    "measurement_matrix", "measurement_cov", "detection_gain",
    "Thresholds", "residual_threshold", "attack_threshold", "false_alarm_condition", "correct_particles",
    "corrected_proposal", "normal_detector", "modified_detector", "deception_mixture_loglik", "uniform_loglik",
    "SISResult", "run_sis", "check_gamma_hat", "DetectionCounts", "detection_counts",
]


# --------------------------------------------------------------------------- gains and thresholds
def measurement_matrix(model: Model) -> np.ndarray:
    """``G`` of ``y = G x`` (all sensors stacked); the model's measurement must be linear and time-invariant."""
    h = ca.vertcat(*[s.h for s in model.sensors])
    J = ca.jacobian(h, model.x)
    if ca.depends_on(J, ca.vertcat(model.x, model.k)) or ca.depends_on(h, model.k):
        raise InputError("model: the modified PF needs a linear, time-invariant measurement y = G x + v")
    G = np.array(ca.evalf(J))
    if np.any(model.h_all(np.zeros(model.n_x)) != 0.0):
        raise InputError("model: the modified PF needs y = G x + v without an offset")
    return G


def measurement_cov(model: Model) -> np.ndarray:
    """``R``: the block-diagonal covariance of every sensor's noise, stacked."""
    return block_diag(*[s.noise.cov for s in model.sensors])


def detection_gain(G, Q, R) -> np.ndarray:
    """``K = Q Gᵀ (R + G Q Gᵀ)⁻¹`` of (35), by a Cholesky solve."""
    G = check_finite("G", G)
    if G.ndim != 2:
        raise InputError(f"G must be a matrix (n_y, n_x), got shape {G.shape}")
    Q = check_covariance("Q", Q, G.shape[1], semidefinite=True)
    R = check_covariance("R", R, G.shape[0])
    S = R + G @ Q @ G.T
    return cho_solve(cho_factor(S), G @ Q).T


class Thresholds(NamedTuple):
    eta: float  # η = ς ‖γ‖_min (45)
    varsigma: float  # ς = |σ̄ - 1|
    sigma_bar: float  # the singular value of G K nearest to 1
    gamma_min: float  # ‖γ‖_min


def residual_threshold(G, K, gamma_min: float) -> Thresholds:
    """``η = ς ‖γ‖_min`` of (45) from the singular values of ``G K``."""
    G, K = check_finite("G", G), check_finite("K", K)
    if G.ndim != 2 or K.shape != G.T.shape:
        raise InputError(f"K must have shape {G.T.shape} (n_x, n_y), got {K.shape}")
    gamma_min = float(check_finite("gamma_min", gamma_min))
    if gamma_min <= 0.0:
        raise InputError(f"gamma_min must be > 0, got {gamma_min!r}")
    sv = np.linalg.svd(G @ K, compute_uv=False)
    sigma_bar = float(sv[np.argmin(np.abs(sv - 1.0))])
    varsigma = abs(sigma_bar - 1.0)
    return Thresholds(varsigma * gamma_min, varsigma, sigma_bar, gamma_min)


def attack_threshold(particles: int, attack_prob: float | None = None, alpha: float | None = None):
    """``(ζ, α)`` with ``ζ = α (N - 1)/N`` (46); by default ``α = p_l N/(N - 1)``, the lower end of (53).

    An ``alpha`` below that bound is allowed (Remark 6: ``p_l`` unknown) but then
    Theorem 2 no longer excludes false alarms.
    """
    N = check_int("particles", particles, 2)
    if alpha is None:
        if attack_prob is None:
            raise InputError("attack_threshold needs attack_prob (p_l) or alpha")
        p = float(check_probability("attack_prob", attack_prob))
        alpha = p * N / (N - 1)
        if not 0.0 < alpha < 1.0:
            raise InputError(f"attack_prob: (53) needs p_l N/(N - 1) in (0, 1), got {alpha!r} for N = {N}")
    alpha = float(check_finite("alpha", alpha))
    if not 0.0 < alpha < 1.0:
        raise InputError(f"alpha must lie in (0, 1), got {alpha!r}")
    return alpha * (N - 1) / N, alpha


def false_alarm_condition(R, eta: float) -> tuple[float, bool]:
    """Theorem 2's Gaussian noise condition ``3 tr(R)^{1/2} <= η``: returns (left side, holds)."""
    lhs = 3.0 * float(np.sqrt(np.trace(check_finite("R", R))))
    return lhs, bool(lhs <= eta)


# --------------------------------------------------------------------------- corrected particles
def correct_particles(x, y, G, K) -> np.ndarray:
    """(36): ``x̃^{i+} = x^i + K (ỹ - G x^i)`` for particles (runs, M, n_x) and measurements (runs, n_y)."""
    r = np.asarray(y)[..., None, :] - x @ G.T
    return x + r @ K.T


def _transition_density(model: Model):
    """``log p(x | x_prev) = log p_w(G_w⁻¹ (x - f(x_prev))) - log|det G_w|`` (square, invertible noise gain)."""
    Gw = model.noise_gain
    if Gw.shape[0] != Gw.shape[1] or np.linalg.matrix_rank(Gw) < Gw.shape[0]:
        raise InputError("model: the transition density needs a square, invertible noise_gain")
    Gw_inv = np.linalg.inv(Gw)
    log_det = float(np.linalg.slogdet(Gw)[1])
    return lambda x, fx: model.process_noise.logpdf((x - fx) @ Gw_inv.T) - log_det


def corrected_proposal(model: Model, inputs=None, *, G=None, R=None) -> Callable:
    """The measurement-corrected proposal (35) for any noise densities, with its importance correction.

    Returns ``proposal(x_prev, k, z_k, rng) -> (x, log_correction)`` (the protocol of
    :func:`filters.particle.run_sir`): ``x ~ N(f + K (z - G f), Q - K G Q)`` with ``Q``
    the process noise's covariance (``G_w Q_w G_wᵀ``) and ``R`` the measurement
    noise's (default: the sensors' covariances), and ``log_correction = log p(x |
    x_prev) - log q(x | x_prev, z)`` with the model's true transition density.
    """
    if model.n_modes:
        raise InputError("model: the corrected proposal needs a single transition density (no switching modes)")
    G = measurement_matrix(model) if G is None else check_finite("G", G)
    R = measurement_cov(model) if R is None else R
    Q = model.process_cov
    K = detection_gain(G, Q, R)
    Sigma = Q - K @ G @ Q
    q = Gaussian.zero_mean(0.5 * (Sigma + Sigma.T))
    log_p = _transition_density(model)

    def propose(x_prev, k, z_k, rng):
        u = None if model.n_u == 0 else np.asarray(inputs)[k]
        fx = model.f(x_prev, k, u)
        mu = correct_particles(fx, z_k, G, K)
        x = mu + q.sample(rng, x_prev.shape[:-1])
        return x, log_p(x, fx) - q.logpdf(x - mu)

    return propose


# --------------------------------------------------------------------------- detectors
def _exceed(x, y, G, eta: float) -> np.ndarray:
    """``‖ỹ - G x^i‖ > η`` per particle, (runs, M)."""
    r = np.asarray(y)[..., None, :] - x @ G.T
    return np.linalg.norm(r, axis=-1) > eta


def normal_detector(model: Model, eta: float, *, loglik: Callable | None = None,
                    linear_weights: bool = False) -> Callable:
    """The normal PF's probability of attack (14) with the residual weights (17).

    ``β_k = Σ_{i: ‖ỹ_k - G x_k^i‖ > η} p(ỹ_k | x_k^i) / Σ_j p(ỹ_k | x_k^j)``.  With
    ``linear_weights`` the likelihoods are taken in linear double precision: when all
    of them underflow, (17) is 0/0 and ``β_k`` NaN (no attack declared).
    Returns ``detector(x_prev, x, k1, z_k, rng) -> β`` (runs,).
    """
    G = measurement_matrix(model)
    loglik = additive_noise_loglik(model) if loglik is None else loglik
    eta = _positive("eta", eta)

    def detect(x_prev, x, k1, z_k, rng):
        ll = loglik(x, k1, z_k)
        if linear_weights:
            p = np.exp(ll)  # underflows to 0 below the smallest double
            total = p.sum(axis=-1)
            with np.errstate(invalid="ignore"):
                W = p / total[:, None]
        else:
            W = LogWeights.of(ll).W
        return np.sum(np.where(_exceed(x, z_k, G, eta), W, 0.0), axis=-1)

    return detect


def modified_detector(model: Model, eta: float, *, correction: str = "mean", inputs=None, G=None,
                      R=None) -> Callable:
    """The modified PF's probability of attack (58): the share of corrected residuals longer than ``η``.

    ``correction="mean"``: the corrected particles of (36) (the paper's Gaussian
    case).  ``"sampled"``: draws from :func:`corrected_proposal` given the previous
    particles (the non-Gaussian variant; uses the ``rng`` passed to the detector).
    Returns ``detector(x_prev, x, k1, z_k, rng) -> β̃`` (runs,).
    """
    G = measurement_matrix(model) if G is None else check_finite("G", G)
    R = measurement_cov(model) if R is None else R
    K = detection_gain(G, model.process_cov, R)
    eta = _positive("eta", eta)
    if correction == "mean":
        if inputs is not None:
            raise InputError("inputs: only correction='sampled' uses the inputs (it propagates x_prev itself)")

        def detect(x_prev, x, k1, z_k, rng):
            return _exceed(correct_particles(x, z_k, G, K), z_k, G, eta).mean(axis=-1)
    elif correction == "sampled":
        propose = corrected_proposal(model, inputs, G=G, R=R)

        def detect(x_prev, x, k1, z_k, rng):
            if rng is None:
                raise InputError("aux_rng: the sampled correction draws particles; pass aux_rng to run_sis")
            xc, _ = propose(x_prev, k1 - 1, z_k, rng)
            return _exceed(xc, z_k, G, eta).mean(axis=-1)
    else:
        raise InputError(f"correction must be 'mean' or 'sampled', got {correction!r}")
    return detect


def _positive(name: str, value) -> float:
    v = float(check_finite(name, value))
    if v <= 0.0:
        raise InputError(f"{name} must be > 0, got {value!r}")
    return v


# --------------------------------------------------------------------------- likelihoods of [31]
def deception_mixture_loglik(model: Model, *, attack_prob: float, deception) -> Callable:
    """Seed 002's likelihood with no DoS and no flips (φ̄ = ᾱ = 0), deception probability ``ϕ̄ = p_l``.

    Per sensor ``s`` (its own Bernoulli, as in [31]):
    ``p(ỹ_s | x) = (1 - p_l) p_{v,s}(ỹ_s - h_s(x)) + p_l p_{v,s}(ỹ_s - ρ_s - h_s(x))``, the
    deception being the additive vector ``ρ = γ̄`` (the paper's adaptation).
    """
    p = float(check_probability("attack_prob", attack_prob, open_upper=True))
    rho = check_finite("deception", deception)
    if rho.shape != (model.n_z,):
        raise InputError(f"deception must have shape ({model.n_z},), got {rho.shape}")
    with np.errstate(divide="ignore"):
        lp, lq = np.log(p), np.log1p(-p)

    def loglik(x, k1, z_k):
        h = model.h_all(x, k1)
        total = 0.0
        for i, s in enumerate(model.sensors):
            a, b = model._offsets[i], model._offsets[i + 1]
            r = z_k[..., None, a:b] - h[..., a:b]
            total = total + np.logaddexp(lq + s.noise.logpdf(r), lp + s.noise.logpdf(r - rho[a:b]))
        return total

    return loglik


def uniform_loglik(x, k1, z_k) -> np.ndarray:
    """Every particle equally likely: the outcome the paper states for the method of [31] (weights 1/N)."""
    return np.zeros(x.shape[:-1])


# --------------------------------------------------------------------------- the SIS filter
class SISResult(NamedTuple):
    mean: np.ndarray  # (runs, K + 1, n_x) weighted means (k = 0: the prior sample's mean)
    beta: np.ndarray  # (runs, K) probability of attack (NaN without a detector, or where (17) is 0/0)
    detected: np.ndarray  # (runs, K) bool: β_k > ζ
    ess: np.ndarray  # (runs, K) effective sample size after weighting
    collapsed: np.ndarray  # (runs, K) bool: every weight underflowed (linear weights); uniform weights kept
    wall_time_s: float  # time of the filter loop (all runs)


def _draw(noise, rng, runs: int, M: int) -> np.ndarray:
    if isinstance(rng, np.random.Generator):
        return noise.sample(rng, (runs, M))
    return np.stack([noise.sample(g, M) for g in rng])


def _generators(rng, runs: int):
    if isinstance(rng, np.random.Generator):
        return rng
    rng = list(rng)
    if len(rng) != runs:
        raise InputError(f"rng must be one Generator or one per run ({runs}), got {len(rng)}")
    for g in rng:
        check_rng(g)
    return rng


def check_gamma_hat(gamma_hat, shape: tuple, detects: bool) -> np.ndarray:
    """The attack estimate of (59) for measurements of ``shape`` (runs, K, n_z): given as that or (K, n_z)."""
    if not detects:
        raise InputError("gamma_hat needs a detector (it is subtracted where an attack is declared)")
    gh = check_finite("gamma_hat", gamma_hat)
    if gh.shape not in (shape, shape[1:]):
        raise InputError(f"gamma_hat must have shape {shape} or {shape[1:]}, got {gh.shape}")
    return np.broadcast_to(gh, shape)


def run_sis(model: Model, z, rng, *, particles: int, inputs=None, loglik: Callable | None = None,
            detector: Callable | None = None, zeta: float | None = None, gamma_hat=None,
            linear_weights: bool = False, aux_rng: np.random.Generator | None = None) -> SISResult:
    """Sequential importance sampling (no resampling) with an optional attack detector and compensation.

    At step ``k``: ``x_k^i ~ p(x_k | x_{k-1}^i)`` (Step 1); ``β_k = detector(...)`` and
    ``l̂_k = [β_k > ζ]`` (Step 2); ``w_k ∝ w_{k-1} p(z_k - l̂_k γ̂_k | x_k^i)`` (59) with
    ``γ̂`` = ``gamma_hat`` (zero when it is None), ``x̂_k = Σ w_k^i x_k^i`` (60).

    Parameters
    ----------
    z : ndarray, shape (runs, K, n_z)
        Received measurements; ``z[:, k]`` measures ``x_{k+1}``.
    rng : Generator or sequence of Generator
        The particles' randomness: one Generator for all runs, or one per run (then a
        run's particles depend only on its own Generator).  Filters given Generators
        in the same state see the same particles.
    loglik : callable, optional
        ``loglik(x, k1, z_k) -> (runs, M)``; default: the sensors' noise densities.
    detector : callable, optional
        ``detector(x_prev, x, k1, z_k, rng) -> β`` (runs,), e.g. :func:`modified_detector`.
    zeta : float
        Detection threshold on ``β`` (required with a detector).
    gamma_hat : ndarray, shape (runs, K, n_z) or (K, n_z), optional
        Attack estimate subtracted where an attack is declared (estimation mode (59)).
    linear_weights : bool
        Emulate weights in linear double precision (see the module notes).
    aux_rng : Generator, optional
        Randomness of the detector itself (the sampled correction), kept apart from
        the particles' so that the particles stay common to every filter.

    Raises :class:`~designer.validation.NonFiniteError` naming the first run and step whose
    estimate is not finite.
    """
    z = check_finite("z", z)
    if z.ndim != 3:
        raise InputError(f"z must have shape (runs, K, n_z), got {z.shape}")
    R_, K_ = z.shape[:2]
    M = check_int("particles", particles, 1)
    rng = _generators(rng, R_)
    if model.n_modes:
        raise InputError("model: run_sis has no switching modes")
    if model.n_u:
        if inputs is None:
            raise InputError(f"inputs of shape ({K_}, {model.n_u}) are required by model {model.name!r}")
        inputs = check_finite("inputs", inputs)
        if inputs.shape != (K_, model.n_u):
            raise InputError(f"inputs must have shape ({K_}, {model.n_u}), got {inputs.shape}")
    if detector is not None:
        if zeta is None:
            raise InputError("zeta (the detection threshold) is required with a detector")
        zeta = float(check_finite("zeta", zeta))
    if gamma_hat is not None:
        gamma_hat = check_gamma_hat(gamma_hat, z.shape, detector is not None)
    loglik = additive_noise_loglik(model) if loglik is None else loglik
    Gw = model.noise_gain

    t0 = time.perf_counter()
    x = _draw(model.prior, rng, R_, M)
    lw = LogWeights.of(np.zeros((R_, M)))
    mean = np.empty((R_, K_ + 1, model.n_x))
    beta = np.full((R_, K_), np.nan)
    detected = np.zeros((R_, K_), dtype=bool)
    ess = np.empty((R_, K_))
    collapsed = np.zeros((R_, K_), dtype=bool)
    mean[:, 0] = np.einsum("rm,rmn->rn", lw.W, x)
    for k in range(K_):
        u = None if model.n_u == 0 else inputs[k]
        x_prev = x
        x = model.f(x_prev, k, u) + _draw(model.process_noise, rng, R_, M) @ Gw.T  # Step 1
        zk = z[:, k]
        if detector is not None:  # Step 2: detection mode
            beta[:, k] = detector(x_prev, x, k + 1, zk, aux_rng)
            detected[:, k] = beta[:, k] > zeta  # NaN (0/0) declares nothing
            if gamma_hat is not None:
                zk = zk - detected[:, k, None] * gamma_hat[:, k]
        prev = lw.log_norm
        new = LogWeights.of(lw.lw + loglik(x, k + 1, zk)).lw  # Step 3: estimation mode (59)
        if linear_weights:
            new = np.where(new - prev[:, None] < LOG_TINY, -np.inf, new)
        dead = np.isneginf(new).all(axis=-1)
        if np.any(dead):
            collapsed[dead, k] = True
            new[dead] = 0.0
        lw = LogWeights(new)
        mean[:, k + 1] = np.einsum("rm,rmn->rn", lw.W, x)  # (60)
        ess[:, k] = lw.ess
    return SISResult(check_finite_means(mean, "SIS particle filter"), beta, detected, ess, collapsed,
                     time.perf_counter() - t0)


# --------------------------------------------------------------------------- scoring
class DetectionCounts(NamedTuple):
    false_alarms: int  # l_k = 0, l̂_k = 1
    missed: int  # l_k = 1, l̂_k = 0, ‖γ_k‖ > ‖γ‖_min
    stealthy: int  # l_k = 1, l̂_k = 0, ‖γ_k‖ <= ‖γ‖_min
    attacks: int  # l_k = 1
    detected: int  # l_k = 1, l̂_k = 1


def detection_counts(l, detected, gamma, gamma_min: float) -> DetectionCounts:
    """Score detections ``l̂`` (..., K) against the attacks ``l`` (..., K) with values ``γ`` (K, n_y)."""
    l, d = np.asarray(l, dtype=bool), np.asarray(detected, dtype=bool)
    if l.shape != d.shape:
        raise InputError(f"detected must have the shape of l {l.shape}, got {d.shape}")
    big = np.linalg.norm(np.asarray(gamma), axis=-1) > gamma_min
    if big.shape != l.shape[-1:]:
        raise InputError(f"gamma must have shape ({l.shape[-1]}, n_y), got {np.shape(gamma)}")
    miss = l & ~d
    return DetectionCounts(int((~l & d).sum()), int((miss & big).sum()), int((miss & ~big).sum()), int(l.sum()),
                           int((l & d).sum()))
