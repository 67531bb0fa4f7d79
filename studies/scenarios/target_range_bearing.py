"""``target-range-bearing``: seed 000 (Song, Wang, Wang, Shan — RRP-PF-DA).

Constant-velocity target (16)-(17), four range-bearing sensors (18) with glint
noise (19); the Round-Robin schedule and the deception attack (4)-(6) are its
``channel`` (:class:`designer.attacks.RoundRobinDeception`).
"""
from __future__ import annotations

import numpy as np

from designer.attacks import AttackSpec, FDISignal, RoundRobinDeception
from designer.design import DesignOptions
from designer.network import SensorNetwork
from designer.noise import Gaussian, UniformBox
from designer.validation import InputError

from .base import Outline, Param, Scenario, ScenarioSpec
from .common import cv_process_cov, cv_transition, glint

N_X = 4  # [px, vx, py, vy]

PARAMS = (
    Param("period", 1.0, "sampling period T (s)", low=0.0, low_open=True),
    Param("accel_std", 0.055, "acceleration noise standard deviation sigma_w (17)", low=0.0, low_open=True),
    Param("x0", [20.0, 0.3, 20.0, 0.3], "true initial state [px, vx, py, vy]", kind="array", shape=(4,)),
    Param("prior_var", [4.0, 0.01, 4.0, 0.01], "diagonal of the filters' prior covariance around x0",
          kind="array", shape=(4,), low=0.0, low_open=True, source="assumption"),
    Param("sensor_positions", [[0.0, 0.0], [0.0, 30.0], [0.0, 60.0], [0.0, 90.0]],
          "sensor positions (m), one row per sensor", kind="array", shape=(None, 2), source="assumption"),
    Param("glint_prob", 0.2, "glint probability kappa (19)", low=0.0, high=1.0),
    Param("glint_cov1", [4.0, (np.pi / 180.0) ** 2], "diagonal of Sigma_1 (range^2, rad^2) (19)",
          kind="array", shape=(2,), low=0.0, low_open=True),
    Param("glint_cov2", [25.0, (np.pi / 90.0) ** 2], "diagonal of Sigma_2 (range^2, rad^2) (19)",
          kind="array", shape=(2,), low=0.0, low_open=True),
    Param("deception_prob", 0.2, "deception success probability eta-bar (6)", low=0.0, high=1.0, high_open=True),
    Param("deception_lower", [-10.0, -np.pi / 2], "lower corner of the uniform deception box (range, bearing)",
          kind="array", shape=(2,)),
    Param("deception_upper", [80.0, np.pi / 2], "upper corner of the uniform deception box (range, bearing)",
          kind="array", shape=(2,)),
    Param("rr_start", 1, "Round-Robin gamma_ini: the sensor (1-based) with the first access (3)", kind="int",
          low=1, source="assumption"),
    Param("steps", 120, "time steps K of the study", kind="int", low=1, source="assumption"),
    Param("edges", [[0, 1], [1, 2], [2, 3], [3, 0]], "undirected sensor links of the consensus network (comparison "
          "study), 0-based node pairs", kind="array", shape=(None, 2), low=0, source="assumption"),
    Param("dos_prob", 0.1, "DoS probability on every network channel (comparison study)", low=0.0, high=1.0,
          source="assumption"),
    Param("fdi_prob", 0.1, "FDI probability on every network channel (comparison study)", low=0.0, high=1.0,
          source="assumption"),
    Param("attack_amplitude", 5.0, "amplitude a (m) of the injected signal xi = a sin(s) on px and py "
          "(comparison study)", low=0.0, source="assumption"),
)


def _assumptions(p: dict) -> tuple[str, ...]:
    pos, edges = np.asarray(p["sensor_positions"], dtype=float), np.asarray(p["edges"], dtype=float)
    return (
        "target-range-bearing: the paper's sensor positions appear only in its Fig. 2; we place the four sensors on "
        f"the line px = 0 at {pos.tolist()}, so that every true range (<= ~80) and bearing lies inside the "
        "deception box and an attacked packet is not trivially separable.",
        f"target-range-bearing: the filters' prior is N(x0, diag{p['prior_var']}) (the paper gives none).",
        f"target-range-bearing: K = {p['steps']} steps, inferred from the 120 communications of Table 1 "
        "(one packet per step under Round-Robin).",
        f"target-range-bearing: Round-Robin starts at sensor {p['rr_start']} (gamma_ini not given).",
        "target-range-bearing: deception follows equations (4)-(6) (eta = 1 means the packet is replaced by xi); "
        "Remark 1's wording, which says the opposite, is taken as a typo.",
        "target-range-bearing: bearings are in (-pi, pi]; residuals are wrapped before the glint density.",
        f"target-range-bearing (comparison study only): the sensors form a consensus network with links "
        f"{edges.astype(int).tolist()} (a ring; the paper has no network), DoS {p['dos_prob']} and FDI "
        f"{p['fdi_prob']} on every channel, injected signal xi = {p['attack_amplitude']} sin(s) m on px and py "
        "(comparable to the glint range noise, 2-5 m).",
        "target-range-bearing (consensus designs): the linearisation scalings are those of any model that declares "
        "none ('prior'): U = 0, exact because the constant-velocity transition is linear, and V_i per component "
        "from the CasADi Hessians of range and bearing over the 3-sigma ellipsoid of the prior (in metres for the "
        "range, radians for the bearing); a single V_i = 0.1 I, as on the indoor robot, would claim a bearing "
        "remainder of 0.1 rad per metre of error, 7 to 100 times the bearing's at these ranges.",
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
    if not 1 <= p["rr_start"] <= pos.shape[0]:
        raise InputError(f"parameter rr_start must be an integer in [1, {pos.shape[0]}], got {p['rr_start']}")
    edges = np.asarray(p["edges"], dtype=float)
    if edges.size and (np.any(edges != np.round(edges)) or np.any(edges >= pos.shape[0])):
        raise InputError(f"parameter edges must hold integer node indices in [0, {pos.shape[0] - 1}]")
    if p["dos_prob"] + p["fdi_prob"] > 1.0:
        raise InputError("parameters dos_prob + fdi_prob must be <= 1 (DoS and FDI never occur together)")
    network = SensorNetwork.from_edges(pos.shape[0], edges.astype(int).reshape(-1, 2).tolist(),
                                       require_connected=False)
    attacks = AttackSpec(dos=p["dos_prob"], fdi=p["fdi_prob"], uplink_dos=p["dos_prob"], uplink_fdi=p["fdi_prob"],
                         signal=FDISignal(p["attack_amplitude"], components=(0, 2), law="sine"))
    x = ca.SX.sym("x", N_X)
    noise = glint(p["glint_prob"], np.diag(p["glint_cov1"]), np.diag(p["glint_cov2"]))
    sensors = []
    for i, (sx, sy) in enumerate(pos):
        dx, dy = x[0] - sx, x[2] - sy
        h = ca.vertcat(ca.sqrt(dx**2 + dy**2), ca.atan2(dy, dx))
        sensors.append(Sensor(f"s{i + 1}", h, noise, (float(sx), float(sy)), angles=(1,)))
    x0 = np.asarray(p["x0"], dtype=float)
    model = Model(
        "target-range-bearing",
        x,
        cv_transition(x, p["period"]),
        sensors,
        Gaussian.zero_mean(cv_process_cov(p["accel_std"] ** 2, p["period"])),
        Gaussian(x0, np.diag(p["prior_var"])),
        state_names=("px", "vx", "py", "vy"),
        position_index=(0, 2),
        velocity_index=(1, 3),
        description="2-D constant-velocity target, range-bearing sensors with glint noise (seed 000)",
    )
    lower, upper = np.asarray(p["deception_lower"]), np.asarray(p["deception_upper"])
    return Scenario(
        "target-range-bearing",
        model,
        dict(p),
        _assumptions(p),
        steps=p["steps"],
        x0=x0,
        network=network,
        attacks=attacks,
        design=DesignOptions(u_scale="prior", v_scale="prior"),
        channel=RoundRobinDeception(p["deception_prob"], UniformBox(lower, upper), p["rr_start"]),
    )


SPEC = ScenarioSpec(
    "target-range-bearing",
    "Target tracking with range-bearing sensors under Round-Robin and deception attacks",
    "000",
    "CV target (16)-(17), 4 range-bearing sensors (18), glint noise (19)",
    PARAMS,
    build,
    outline,
)
