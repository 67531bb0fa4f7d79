"""``target-binary-energy``: seed 002 (Song et al. — Sec-PF with binary sensors).

Constant-velocity target (27)-(28) observed by 16 received-energy sensors (29)
with glint noise; thresholding, DoS, deception, flipping and the channel noise are
its ``channel`` (:class:`designer.attacks.BinarySensorChannel`, Table I).
"""
from __future__ import annotations

import numpy as np

from designer.attacks import BinarySensorChannel
from designer.noise import Gaussian, PolarVelocityPrior, UniformBox
from designer.validation import InputError

from .base import Outline, Param, Scenario, ScenarioSpec
from .common import cv_process_cov, cv_transition, glint

N_X = 4  # [px, vx, py, vy]

_GRID = [[float(a), float(b)] for b in (10, 30, 50, 70) for a in (10, 30, 50, 70)]

PARAMS = (
    Param("period", 1.0, "sampling period t (s)", low=0.0, low_open=True),
    Param("accel_var", 0.045**2, "acceleration variance Xi (28); printed '0.0452', read as 0.045^2",
          low=0.0, low_open=True, source="assumption"),
    Param("x0", [15.0, 0.4, 20.0, 0.3], "true initial state [px, vx, py, vy]", kind="array", shape=(4,)),
    Param("sensor_positions", _GRID, "sensor positions, one row per sensor", kind="array", shape=(None, 2),
          source="assumption"),
    Param("energy", 4000.0, "Upsilon: energy at the reference distance (Table I)", low=0.0, low_open=True),
    Param("ref_distance", 1.0, "d0: reference distance (Table I)", low=0.0, low_open=True),
    Param("path_loss", 2.8, "lambda_s: path-loss exponent (Table I)", low=0.0, low_open=True),
    Param("glint_prob", 0.15, "beta_s: glint probability (Table I)", low=0.0, high=1.0),
    Param("glint_var1", 0.01, "Sigma_1: variance of the narrow glint component (Table I)", low=0.0, low_open=True),
    Param("glint_var2", 0.25, "Sigma_2: variance of the wide glint component (Table I)", low=0.0, low_open=True),
    Param("dos_prob", 0.1, "phi-bar: DoS probability (Table I)", low=0.0, high=1.0, high_open=True),
    Param("deception_prob", 0.1, "varphi-bar: deception probability (Table I)", low=0.0, high=1.0, high_open=True),
    Param("flip_prob", 0.1, "alpha-bar: bit-flipping probability (Table I)", low=0.0, high=1.0, high_open=True),
    Param("deception_low", -3.0, "a: lower bound of the uniform deception signal (Table I)"),
    Param("deception_high", 3.0, "b: upper bound of the uniform deception signal (Table I)"),
    Param("threshold", 0.3, "T_delta: binary threshold (Table I)", low=0.0, low_open=True),
    Param("channel_gain", 0.5, "tau_s: channel gain (Table I)", low=0.0, low_open=True),
    Param("channel_std", 0.1, "sigma_eps: channel noise std (Table I)", low=0.0, low_open=True),
    Param("steps", 100, "time steps K of the study", kind="int", low=1, source="assumption"),
)


def _assumptions(p: dict) -> tuple[str, ...]:
    return (
        "target-binary-energy: the acceleration variance is printed '0.0452'; superscripts were lost in the source "
        f"(cf. 'diag{{0.252, (pi/6)2}}'), so Xi = 0.045^2 = {p['accel_var']:.6g} is used.",
        "target-binary-energy: sensor positions appear only in the paper's Fig. 2 (one at (10, 10)); we use the "
        "4 x 4 grid {10, 30, 50, 70}^2, spacing 20 below the ~29.7 detection radius.",
        f"target-binary-energy: K = {p['steps']} steps (not given).",
        "target-binary-energy: the energy model is guarded at distance 1e-6 (h is singular at a sensor).",
        "target-binary-energy: prior as in section IV-C: position N([15, 20], 100 I); speed N(0.5, 0.25^2), "
        "heading N(arctan(3/4), (pi/6)^2), vx = s cos(a), vy = s sin(a).",
    )


def outline(p: dict) -> Outline:
    """n_x, sensors, steps and assumptions of :func:`build` without the model."""
    return Outline(N_X, len(p["sensor_positions"]), p["steps"], _assumptions(p))


def build(p: dict) -> Scenario:
    import casadi as ca  # here, not at the top: listing the scenarios needs no model (outline)

    from designer.model import Model, Sensor

    pos = np.asarray(p["sensor_positions"], dtype=float)
    if pos.shape[0] < 1:
        raise InputError("parameter sensor_positions needs at least one sensor")
    x = ca.SX.sym("x", N_X)
    noise = glint(p["glint_prob"], [[p["glint_var1"]]], [[p["glint_var2"]]])
    scale = p["energy"] * p["ref_distance"] ** p["path_loss"]
    sensors = []
    for i, (sx, sy) in enumerate(pos):
        d2 = ca.fmax((x[0] - sx) ** 2 + (x[2] - sy) ** 2, 1e-12)  # guard the singularity at the sensor
        sensors.append(Sensor(f"s{i + 1}", scale * d2 ** (-p["path_loss"] / 2.0), noise, (float(sx), float(sy))))
    x0 = np.asarray(p["x0"], dtype=float)
    prior = PolarVelocityPrior([15.0, 20.0], 100.0 * np.eye(2), 0.5, 0.25, float(np.arctan(0.75)), np.pi / 6)
    model = Model(
        "target-binary-energy",
        x,
        cv_transition(x, p["period"]),
        sensors,
        Gaussian.zero_mean(cv_process_cov(p["accel_var"], p["period"])),
        prior,
        state_names=("px", "vx", "py", "vy"),
        position_index=(0, 2),
        velocity_index=(1, 3),
        description="2-D constant-velocity target, received-energy sensors with glint noise (seed 002)",
    )
    return Scenario(
        "target-binary-energy",
        model,
        dict(p),
        _assumptions(p),
        steps=p["steps"],
        x0=x0,
        channel=BinarySensorChannel(
            dos_prob=p["dos_prob"],
            deception_prob=p["deception_prob"],
            flip_prob=p["flip_prob"],
            deception=UniformBox([p["deception_low"]], [p["deception_high"]]),
            threshold=p["threshold"],
            gain=p["channel_gain"],
            channel_noise=Gaussian.zero_mean([[p["channel_std"] ** 2]]),
        ),
    )


SPEC = ScenarioSpec(
    "target-binary-energy",
    "Target tracking with binary received-energy sensors under DoS, deception and flipping attacks",
    "002",
    "CV target (27)-(28), 16 received-energy sensors (29), Table I parameters",
    PARAMS,
    build,
    outline,
)
