"""``four-tank``: seed 004 (Sadeghzadeh-Nokhodberiz, Meskin, Hasanzadeh — FDI detection).

Johansson's quadruple-tank process (IEEE TCST 2000) at its minimum-phase
operating point, discretised by classical Runge-Kutta over the sampling period
(written symbolically, so Jacobians are exact for the discrete map), with four
level sensors ``y = G x + v``; the bias attack (3)-(4) is its ``channel``
(:class:`designer.attacks.BiasFDI`).

The filters' model always has the process noise ``w_k ~ N(0, Q)``; the simulated
plant has it only with ``plant_noise=true``.  By default the plant is
deterministic, as a Simulink simulation of the tank equations is: only then do
the paper's detection results (no false alarm at the low noise, a few at the
high one) come out (see the ``fdi-four-tank`` study's sensitivity block).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from designer.attacks import BiasFDI
from designer.noise import Gaussian
from designer.simulate import Trajectory, simulate

from .base import Outline, Param, Scenario, ScenarioSpec

if TYPE_CHECKING:
    from designer.model import Model

N_X = 4  # the four levels

R_SETTINGS = {"low": [1e-3, 1e-3, 0.5e-3, 0.5e-3], "high": [5e-3, 5e-3, 2.5e-3, 2.5e-3]}

PARAMS = (
    Param("tank_area", [28.0, 32.0, 28.0, 32.0], "cross sections A1..A4 (cm^2), Johansson", kind="array",
          shape=(4,), low=0.0, low_open=True),
    Param("outlet_area", [0.071, 0.057, 0.071, 0.057], "outlet areas a1..a4 (cm^2), Johansson", kind="array",
          shape=(4,), low=0.0, low_open=True),
    Param("gravity", 981.0, "g (cm/s^2)", low=0.0, low_open=True),
    Param("pump_gain", [3.33, 3.35], "pump gains k1, k2 (cm^3/(V s))", kind="array", shape=(2,), low=0.0),
    Param("valve_split", [0.70, 0.60], "valve ratios gamma1, gamma2", kind="array", shape=(2,), low=0.0, high=1.0),
    Param("voltage", [3.0, 3.0], "pump voltages v1, v2 (V), constant", kind="array", shape=(2,), low=0.0),
    Param("x0", [12.4, 12.7, 1.8, 1.4], "operating-point levels h0 (cm), the true initial state", kind="array",
          shape=(4,), low=0.0),
    Param("period", 1.0, "sampling period (s)", low=0.0, low_open=True, source="assumption"),
    Param("substeps", 4, "Runge-Kutta substeps per sampling period", kind="int", low=1, high=100,
          source="assumption"),
    Param("G", np.eye(4).tolist(), "measurement matrix G of y = G x + v", kind="array", shape=(4, 4),
          source="assumption"),
    Param("process_var", 1e-4, "process-noise variance per level (cm^2), Q = q I", low=0.0, low_open=True,
          source="assumption"),
    Param("noise", "low", "measurement-noise setting: low R = 1e-3 diag{1, 1, 0.5, 0.5}, high = 5x",
          kind="choice", choices=("low", "high")),
    Param("prior_var", 1e-2, "prior variance per level around x0 (cm^2)", low=0.0, low_open=True,
          source="assumption"),
    Param("attack_prob", 0.5, "p_l: probability that the bias attack is injected (4)", low=0.0, high=1.0),
    Param("attack_tau", 0.9, "tau of the attack dynamics gamma_{k+1} = tau gamma_k + (1 - tau) gamma-bar (4)",
          low=0.0, high=1.0, low_open=True, high_open=True),
    Param("attack_bias", [0.5, 0.5, 0.5, 0.5], "gamma-bar: attack limit (4)", kind="array", shape=(4,)),
    Param("attack_norm_min", 0.28, "||gamma||_min: the smallest attack norm the detector is designed for (45)",
          low=0.0, low_open=True),
    Param("attack_estimate_var", 1e-2, "variance per component of the error of the attack estimate gamma-hat "
          "(the paper's third scenario, Fig. 13)", low=0.0),
    Param("plant_noise", False, "the simulated plant has the process noise N(0, Q) too (the filters always assume "
          "it); false: a deterministic plant", kind="bool", source="assumption"),
    Param("steps", 200, "time steps of the study", kind="int", low=1, source="assumption"),
)


def _assumptions(p: dict) -> tuple[str, ...]:
    return (
        "four-tank: the paper gives no tank equations or parameters; we use Johansson's quadruple-tank process "
        "(IEEE TCST 2000), minimum-phase setting P-, with constant pump voltages.",
        f"four-tank: discretised by classical Runge-Kutta with {p['substeps']} substeps over a {p['period']} s "
        "period (the paper's sampling period is not given); outflows use sqrt(max(h, 0)) so levels are kept "
        "non-negative in the dynamics.",
        "four-tank: G = I (four levels measured directly) and Q = 1e-4 I: together they reproduce the paper's "
        "threshold eta = 0.233 from ||gamma||_min = 0.28 via (45).",
        f"four-tank: horizon {p['steps']} steps and prior N(h0, {p['prior_var']} I) are not given in the paper.",
        "four-tank: the simulated plant is " + ("the model with its process noise N(0, Q)" if p["plant_noise"] else
        "deterministic (no process noise; the filters still assume Q): the paper simulates the tank equations in "
        "Simulink and says nothing of plant noise; its Theorem 2 (no false alarm when 3 tr(R)^1/2 <= eta) involves "
        "R only, i.e. presumes the corrected particles match the plant up to measurement noise. With plant noise "
        "the truth drifts ~0.1 cm from the never-resampled SIS particles and false alarms appear at the low noise "
        "too (the fdi-four-tank study reports that case beside the main one)") + ".",
    )


def outline(p: dict) -> Outline:
    """n_x, sensors, steps and assumptions of :func:`build` without the model."""
    return Outline(N_X, len(p["G"]), p["steps"], _assumptions(p))  # one sensor per row of G


def build(p: dict) -> Scenario:
    import casadi as ca  # here, not at the top: listing the scenarios needs no model (outline)

    from designer.model import Model, Sensor

    x = ca.SX.sym("x", N_X)
    u = ca.SX.sym("u", 2)
    A = np.asarray(p["tank_area"])
    a = np.asarray(p["outlet_area"])
    k1, k2 = p["pump_gain"]
    g1, g2 = p["valve_split"]
    g = p["gravity"]

    def rate(h):
        q = [a[i] * ca.sqrt(2.0 * g * ca.fmax(h[i], 0.0)) for i in range(4)]  # outflow; levels kept >= 0
        return ca.vertcat(
            (-q[0] + q[2] + g1 * k1 * u[0]) / A[0],
            (-q[1] + q[3] + g2 * k2 * u[1]) / A[1],
            (-q[2] + (1.0 - g2) * k2 * u[1]) / A[2],
            (-q[3] + (1.0 - g1) * k1 * u[0]) / A[3],
        )

    dt = p["period"] / p["substeps"]
    h = x
    for _ in range(p["substeps"]):
        r1 = rate(h)
        r2 = rate(h + 0.5 * dt * r1)
        r3 = rate(h + 0.5 * dt * r2)
        r4 = rate(h + dt * r3)
        h = h + dt / 6.0 * (r1 + 2 * r2 + 2 * r3 + r4)
    G = np.asarray(p["G"], dtype=float)
    Rdiag = R_SETTINGS[p["noise"]]
    sensors = [
        Sensor(f"level{i + 1}", ca.mtimes(ca.DM(G[i : i + 1, :]), x), Gaussian.zero_mean([[Rdiag[i]]]))
        for i in range(4)
    ]
    x0 = np.asarray(p["x0"], dtype=float)
    model = Model(
        "four-tank",
        x,
        h,
        sensors,
        Gaussian.zero_mean(p["process_var"] * np.eye(4)),
        Gaussian(x0, p["prior_var"] * np.eye(4)),
        u=u,
        state_names=("h1", "h2", "h3", "h4"),
        description="Johansson's quadruple-tank process, minimum-phase operating point (seed 004)",
    )
    v = np.asarray(p["voltage"], dtype=float)

    def inputs(steps: int) -> np.ndarray:
        return np.tile(v, (steps, 1))

    return FourTankScenario(
        "four-tank",
        model,
        dict(p),
        _assumptions(p),
        steps=p["steps"],
        x0=x0,
        input_fn=inputs,
        channel=BiasFDI(prob=p["attack_prob"], bias=p["attack_bias"], tau=p["attack_tau"],
                        norm_min=p["attack_norm_min"], estimate_var=p["attack_estimate_var"]),
        plant_noise=p["plant_noise"],
    )


@dataclass(frozen=True, eq=False)
class FourTankScenario(Scenario):
    """The four-tank scenario: simulates the plant, with or without process noise (``plant_noise``)."""

    plant_noise: bool = True

    @cached_property
    def plant(self) -> Model:
        """The simulated plant: the model itself, or the model with its process noise switched off."""
        from designer.model import Model

        m = self.model
        if self.plant_noise:
            return m
        # A zero noise gain keeps the draw order (so a seed gives the same measurement noise either way).
        return Model(f"{m.name} (deterministic plant)", m.x, m.f_expr, m.sensors, m.process_noise, m.prior, u=m.u,
                     noise_gain=np.zeros((m.n_x, m.process_noise.dim)), state_names=m.state_names,
                     description=m.description)

    def simulate(self, rng: np.random.Generator, steps: int | None = None, *, batch=()) -> Trajectory:
        steps = self.steps if steps is None else steps
        return simulate(self.plant, steps, rng, batch=batch, x0=self.x0, inputs=self.inputs(steps))


SPEC = ScenarioSpec(
    "four-tank",
    "Quadruple-tank process with four level sensors under false-data-injection attacks",
    "004",
    "Johansson's four-tank process, y = G x + v, bias FDI attack (3)-(4)",
    PARAMS,
    build,
    outline,
)
