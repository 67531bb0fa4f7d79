"""The centralized filters' view of attacked uplinks: received measurements and the attack-aware likelihood.

The uplink attacks themselves (DoS and FDI on each sensor's uplink to a fusion centre,
driven by the diagonal of the consensus channels' draws) are simulated in
:mod:`filters.attacks` (:func:`~filters.attacks.uplink_attacks`,
:func:`~filters.attacks.receive`).  Received measurements are laid out as
``(steps, n_z + N)``: the received values (0 where lost), then each sensor's
availability α_i in {0, 1}, as :func:`filters.edpf.received`.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from designer.attacks import FDISignal
from designer.model import Model
from designer.noise import Gaussian
from designer.validation import InputError, check_probability

from .rrp import angle_sets, wrap_angles

__all__ = ["fdi_covariances", "uplink_loglik", "split_received"]


def split_received(model: Model, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(values (..., n_z), available (..., N) bool)`` of measurements laid out by :func:`receive`."""
    if y.shape[-1] != model.n_z + model.n_sensors:
        raise InputError(f"received measurements must have width n_z + N = {model.n_z + model.n_sensors}, "
                         f"got {y.shape[-1]}")
    return y[..., :model.n_z], y[..., model.n_z:] > 0.5


def fdi_covariances(model: Model, x_ref, signal: FDISignal, *, k: int = 1) -> list[np.ndarray]:
    """Covariance of the falsification ``H_i ξ`` per sensor, ``H_i`` at ``x_ref``: ``E[g²] Σ_c a_c² h_c h_cᵀ``.

    ``h_c`` is column ``c`` of ``H_i`` and ``a_c`` the signal's amplitude on component ``c``:
    the components are treated as independently attacked (a moment match that is wider than
    the fully correlated ``ξ = a g(s)`` in every direction but ``a``'s).
    """
    sig = signal.resolve(model.n_x)
    comps = list(sig.components)
    a2 = np.asarray(sig.amplitude) ** 2
    return [((a2 * sig.second_moment) * model.H(i, x_ref, k)[:, comps]) @ model.H(i, x_ref, k)[:, comps].T
            for i in range(model.n_sensors)]


def uplink_loglik(model: Model, *, fdi_prob: float = 0.0, fdi_covs=None, angles=None) -> Callable:
    """``loglik(x, k1, y)`` for :func:`filters.particle.run_sir` over received uplink measurements.

    Per available sensor: ``log[(1 - q) p_i(ỹ_i - h_i(x)) + q N(ỹ_i; h_i(x), R_i + C_i)]`` with
    ``p_i`` the sensor's own noise density (any noise, e.g. glint), ``R_i`` its covariance,
    ``q = fdi_prob`` (a scalar, one value per run of a batch, or ``(runs, N)``: one per run and
    sensor) the probability that a received packet was falsified and ``C_i`` the
    falsification's covariance (:func:`fdi_covariances`; a moment-matched Gaussian of
    ``H_i ξ``).  ``fdi_prob = 0`` is the plain likelihood that trusts every packet; lost
    packets (α_i = 0) contribute nothing.  ``angles``: ``(sensor, component)`` pairs whose
    residuals are wrapped into (-π, π] (default: the sensors' declared ``angles``).
    """
    q = np.asarray(check_probability("fdi_prob", fdi_prob), dtype=float)
    if q.ndim > 2 or (q.ndim == 2 and q.shape[1] != model.n_sensors):
        raise InputError(f"fdi_prob must be a probability, one per run (1-D) or one per run and sensor "
                         f"(runs, {model.n_sensors}), got shape {q.shape}")
    clean = [s.noise for s in model.sensors]
    wraps = angle_sets(model, model.angle_components if angles is None else angles)
    attacked = None
    if np.any(q > 0):
        if fdi_covs is None or len(fdi_covs) != model.n_sensors:
            raise InputError(f"fdi_covs must give one covariance per sensor ({model.n_sensors}) when fdi_prob > 0")
        attacked = [Gaussian.zero_mean(model.measurement_cov(i) + np.asarray(c)) for i, c in enumerate(fdi_covs)]
    with np.errstate(divide="ignore"):
        if q.ndim == 2:  # per run and sensor: column i for sensor i, broadcast over particles
            lqs = [(np.log(q[:, i])[:, None], np.log1p(-q[:, i])[:, None]) for i in range(model.n_sensors)]
        else:  # per run (or one for all), broadcast over particles
            lqs = [(np.log(q)[..., None], np.log1p(-q)[..., None])] * model.n_sensors
    offsets = model.sensor_offsets

    def loglik(x, k1, y):
        values, avail = split_received(model, np.asarray(y, dtype=float))
        h = model.h_all(x, k1)
        total = np.zeros(h.shape[:-1])
        for i in range(model.n_sensors):
            a, b = offsets[i], offsets[i + 1]
            lq, l1q = lqs[i]
            r = wrap_angles(values[..., None, a:b] - h[..., a:b], wraps[i])
            t = clean[i].logpdf(r) + l1q
            if attacked is not None:
                t = np.logaddexp(t, attacked[i].logpdf(r) + lq)
            total = total + np.where(avail[..., i:i + 1], t, 0.0)
        return total

    return loglik
