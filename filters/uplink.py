"""Sensor-to-fusion-centre uplinks under DoS and false-data injection, for centralized filters.

The consensus filter's attacks act on the node-to-node channels
(:func:`filters.consensus.attack_pattern`).  A centralized filter instead receives
every sensor's measurement over its own uplink.  Both are driven by one draw
(:func:`filters.consensus.channel_draws`): the network channels use the
off-diagonal entries, uplink ``i`` the diagonal entry ``[k, i, i]``, with the same
law — DoS iff ``u < dos_prob`` (the packet is lost and the centre knows it), FDI iff
``dos_prob <= u < dos_prob + fdi_prob``, injected signal ``ξ = a sin(s)`` on the
attacked state components.  On an uplink the attacker falsifies the measurement
as if the state were displaced by ``ξ``: ``ỹ_i = z_i + h_i(x + ξ) - h_i(x)`` (for a
sensor that is affine in the attacked components this is ``z_i + H_i ξ``), so the
same ``ξ`` misleads both architectures by the same distance.

Measurements for the filters: ``(steps, n_z + N)``: the received values (0 where
lost), then each sensor's availability α_i in {0, 1}, as :func:`filters.edpf.received`.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from designer.model import Model
from designer.noise import Gaussian
from designer.validation import InputError, check_probability

from .rrp import angle_sets, wrap_angles

__all__ = ["UplinkAttacks", "uplink_attacks", "receive", "SIN2_MEAN", "fdi_covariances", "uplink_loglik",
           "split_received"]

SIN2_MEAN = 0.5 * (1.0 - np.exp(-2.0))  # E[sin(s)^2] for s ~ N(0, 1)


class UplinkAttacks(NamedTuple):
    """Entry ``[k]`` concerns the measurement of ``x_{k+1}``."""

    dos: np.ndarray  # bool (steps, N)
    fdi: np.ndarray  # bool (steps, N)
    xi: np.ndarray  # (steps, N, n_x), zero where no FDI


def uplink_attacks(u: np.ndarray, s: np.ndarray, n_x: int, *, dos_prob: float, fdi_prob: float,
                   amplitude: float, components) -> UplinkAttacks:
    """Uplink attacks from the diagonal of the channel draws ``u``, ``s`` (steps, N, N)."""
    dos_prob = float(check_probability("dos_prob", dos_prob))
    fdi_prob = float(check_probability("fdi_prob", fdi_prob))
    if dos_prob + fdi_prob > 1.0:
        raise InputError(f"dos_prob + fdi_prob must be <= 1, got {dos_prob} + {fdi_prob}")
    u, s = np.diagonal(u, axis1=1, axis2=2), np.diagonal(s, axis1=1, axis2=2)
    dos = u < dos_prob
    fdi = ~dos & (u < dos_prob + fdi_prob)
    xi = np.zeros(u.shape + (n_x,))
    xi[..., list(components)] = (amplitude * np.sin(s) * fdi)[..., None]
    return UplinkAttacks(dos, fdi, xi)


def receive(model: Model, x: np.ndarray, z: np.ndarray, attacks: UplinkAttacks) -> np.ndarray:
    """The centre's measurements ``(steps, n_z + N)`` from the truth ``x`` (steps + 1, n_x) and clean ``z``."""
    steps, N = attacks.dos.shape
    if z.shape != (steps, model.n_z) or x.shape != (steps + 1, model.n_x) or N != model.n_sensors:
        raise InputError(f"z must be ({steps}, {model.n_z}) and x ({steps + 1}, {model.n_x}) for {N} uplinks; "
                         f"got z {z.shape}, x {x.shape}, model with {model.n_sensors} sensors")
    y = z.copy()
    for i in range(N):
        a, b = model._offsets[i], model._offsets[i + 1]
        for k in np.flatnonzero(attacks.fdi[:, i]):
            y[k, a:b] += model.h(i, x[k + 1] + attacks.xi[k, i], k + 1) - model.h(i, x[k + 1], k + 1)
        y[attacks.dos[:, i], a:b] = 0.0
    return np.concatenate([y, (~attacks.dos).astype(float)], axis=1)


def split_received(model: Model, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(values (..., n_z), available (..., N) bool)`` of measurements laid out by :func:`receive`."""
    if y.shape[-1] != model.n_z + model.n_sensors:
        raise InputError(f"received measurements must have width n_z + N = {model.n_z + model.n_sensors}, "
                         f"got {y.shape[-1]}")
    return y[..., :model.n_z], y[..., model.n_z:] > 0.5


def fdi_covariances(model: Model, x_ref, *, amplitude: float, components, k: int = 1) -> list[np.ndarray]:
    """Covariance of the falsification ``H_i ξ`` per sensor, ``H_i`` at ``x_ref``: ``a² E[sin²s] H_i,c H_i,cᵀ``."""
    comps = list(components)
    return [amplitude**2 * SIN2_MEAN * model.H(i, x_ref, k)[:, comps] @ model.H(i, x_ref, k)[:, comps].T
            for i in range(model.n_sensors)]


def uplink_loglik(model: Model, *, fdi_prob: float = 0.0, fdi_covs=None, angles=()) -> Callable:
    """``loglik(x, k1, y)`` for :func:`filters.particle.run_sir` over received uplink measurements.

    Per available sensor: ``log[(1 - q) p_i(ỹ_i - h_i(x)) + q N(ỹ_i; h_i(x), R_i + C_i)]`` with
    ``p_i`` the sensor's own noise density (any noise, e.g. glint), ``R_i`` its covariance,
    ``q = fdi_prob`` (a scalar, or one value per run of a batch) the probability that a
    received packet was falsified and ``C_i`` the
    falsification's covariance (:func:`fdi_covariances`; a moment-matched Gaussian of
    ``H_i ξ``).  ``fdi_prob = 0`` is the plain likelihood that trusts every packet; lost
    packets (α_i = 0) contribute nothing.  ``angles``: ``(sensor, component)`` pairs whose
    residuals are wrapped into (-π, π].
    """
    q = np.asarray(check_probability("fdi_prob", fdi_prob), dtype=float)
    if q.ndim > 1:
        raise InputError(f"fdi_prob must be a probability or one per run (1-D), got shape {q.shape}")
    clean = [s.noise for s in model.sensors]
    wraps = angle_sets(model, angles)
    attacked = None
    if np.any(q > 0):
        if fdi_covs is None or len(fdi_covs) != model.n_sensors:
            raise InputError(f"fdi_covs must give one covariance per sensor ({model.n_sensors}) when fdi_prob > 0")
        attacked = [Gaussian.zero_mean(model.measurement_cov(i) + np.asarray(c)) for i, c in enumerate(fdi_covs)]
    with np.errstate(divide="ignore"):
        lq, l1q = np.log(q)[..., None], np.log1p(-q)[..., None]  # per run, broadcast over particles

    def loglik(x, k1, y):
        values, avail = split_received(model, np.asarray(y, dtype=float))
        h = model.h_all(x, k1)
        total = np.zeros(h.shape[:-1])
        for i in range(model.n_sensors):
            a, b = model._offsets[i], model._offsets[i + 1]
            r = wrap_angles(values[..., None, a:b] - h[..., a:b], wraps[i])
            t = clean[i].logpdf(r) + l1q
            if attacked is not None:
                t = np.logaddexp(t, attacked[i].logpdf(r) + lq)
            total = total + np.where(avail[..., i:i + 1], t, 0.0)
        return total

    return loglik
