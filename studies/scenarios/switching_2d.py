"""``switching-2d``: seed 001 (Song, Wang, Li — encryption-decryption PF).

x(t+1) = F x + gamma f(x) + (1 - gamma) g(x) + eta,  P(gamma = 1) = gamma_f;
two scalar sensors z_1 = 2 sin(x1 - x2), z_2 = -2 cos(x1 + x2) with standard
normal noise truncated to [-2, 2]; Gaussian-mixture process noise.  Sensor
resolution, quantizer, cipher and channel errors are its ``channel``
(:class:`filters.encryption.EncryptedChannel` with its :class:`filters.encryption.Codec`).
"""
from __future__ import annotations

import numpy as np

from designer.noise import Gaussian, GaussianMixture, TruncatedGaussian
from designer.validation import InputError
from filters.encryption import Codec, EncryptedChannel

from .base import Outline, Param, Scenario, ScenarioSpec

N_X = 2  # [x1, x2]

PARAMS = (
    Param("F", [[0.85, -0.2], [-0.2, 0.76]], "linear part F(t) of the dynamics", kind="array", shape=(2, 2)),
    Param("switch_prob", 0.5, "probability gamma_f that f (not g) is active (2)", low=0.0, high=1.0),
    Param("mixture_weight", 0.2, "weight rho of the wide process-noise component", low=0.0, high=1.0),
    Param("noise_std1", 0.02, "std of the narrow process-noise component", low=0.0, low_open=True),
    Param("noise_std2", 0.1, "std of the wide process-noise component", low=0.0, low_open=True),
    Param("meas_bound", 2.0, "truncation bound of the standard-normal measurement noise", low=0.0, low_open=True),
    Param("prior_mean", [2.0, -2.0], "mean of x(0)", kind="array", shape=(2,)),
    Param("prior_std", 1.2, "std of each component of x(0)", low=0.0, low_open=True),
    Param("resolution", 0.2, "sensor resolution l_s (3)", low=0.0, low_open=True),
    Param("quant_scale", 1.0, "quantizer scaling omega_s (4)", low=0.0, low_open=True),
    Param("quant_levels", 8, "number of quantization levels K = 2^L (4)", kind="int", low=2),
    Param("quant_range", 4.0, "quantizer range Lambda (4)", low=0.0, low_open=True),
    Param("bit_error_prob", 0.0, "probability that a transmitted bit (ciphertext or CRC) is flipped; a CRC failure "
          "makes the measurement unavailable (Remark 1; 0 = Assumption 3)", low=0.0, high=1.0, high_open=True),
    Param("dropout_prob", 0.0, "probability that a sensor's packet is lost (alpha_s = 0, Remark 2)", low=0.0,
          high=1.0, high_open=True),
    Param("steps", 120, "time steps T of the study", kind="int", low=1),
)


def _assumptions(p: dict) -> tuple[str, ...]:
    return (
        "switching-2d: the true x(0) of every run is drawn from the prior N([2, -2], 1.2^2 I) (the paper gives no "
        "fixed initial state).",
        "switching-2d: F has an eigenvalue of about 1.01, so the state drifts slowly; kept as printed.",
        "switching-2d: quantizer cells are half-open [lo, hi) and the index is clipped to 1..K; the key stream is "
        "i.i.d. Bernoulli(1/2) bits per sensor and step (the paper fixes neither).",
        "switching-2d: with bit_error_prob > 0 a CRC-4 (x^4 + x + 1) of the ciphertext detects transmission errors "
        "(Remark 1 names CRC without a polynomial); bit errors and dropouts are independent per bit and per packet.",
    )


def outline(p: dict) -> Outline:
    """n_x, sensors, steps and assumptions of :func:`build` without the model."""
    return Outline(N_X, 2, p["steps"], _assumptions(p))  # sensors s1, s2


def build(p: dict) -> Scenario:
    import casadi as ca  # here, not at the top: listing the scenarios needs no model (outline)

    from designer.model import Model, Sensor

    levels = p["quant_levels"]
    if levels & (levels - 1):
        raise InputError(f"parameter quant_levels must be a power of two >= 2, got {levels}")
    x = ca.SX.sym("x", N_X)
    r = ca.SX.sym("mode")
    F = ca.DM(p["F"])
    f = ca.vertcat(-0.25 * ca.tanh(x[1]), 0.35 * ca.tanh(x[0]))
    g = ca.vertcat(0.32 * ca.tanh(x[0]), -0.28 * ca.tanh(x[1]))
    # mode 1 <=> gamma(t) = 1 (f active), mode 0 <=> g active.
    trans = ca.mtimes(F, x) + r * f + (1 - r) * g
    b = p["meas_bound"]
    vnoise = TruncatedGaussian([0.0], [1.0], [-b], [b])
    sensors = [
        Sensor("s1", 2.0 * ca.sin(x[0] - x[1]), vnoise),
        Sensor("s2", -2.0 * ca.cos(x[0] + x[1]), vnoise),
    ]
    rho = p["mixture_weight"]
    wnoise = GaussianMixture(
        np.array([1.0 - rho, rho]),
        (Gaussian.zero_mean(p["noise_std1"] ** 2 * np.eye(2)), Gaussian.zero_mean(p["noise_std2"] ** 2 * np.eye(2))),
    )
    model = Model(
        "switching-2d",
        x,
        trans,
        sensors,
        wnoise,
        Gaussian(p["prior_mean"], p["prior_std"] ** 2 * np.eye(2)),
        mode=r,
        mode_probs=[1.0 - p["switch_prob"], p["switch_prob"]],
        description="2-state system with randomly switching nonlinearities f/g (seed 001)",
    )
    return Scenario(
        "switching-2d",
        model,
        dict(p),
        _assumptions(p),
        steps=p["steps"],
        x0=None,
        channel=EncryptedChannel(Codec(p["resolution"], p["quant_scale"], levels, p["quant_range"]),
                                 bit_error_prob=p["bit_error_prob"], dropout_prob=p["dropout_prob"]),
    )


SPEC = ScenarioSpec(
    "switching-2d",
    "Two-state system with randomly switching nonlinearities, sensor resolution and encrypted channels",
    "001",
    "x+ = F x + gamma f(x) + (1-gamma) g(x) + eta; two sensors; Gaussian-mixture / truncated-Gaussian noise",
    PARAMS,
    build,
    outline,
)
