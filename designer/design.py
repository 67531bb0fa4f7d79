"""The consensus design's parameters, their validation, and the option set every design command shares.

:class:`ConsensusDesign` is what the consensus filter runs with (ε, σ, β, τ, the
linearisation scalings ``U`` and ``V_i``, the FDI bound δ, the mode and the
linearisation rule).  :class:`DesignOptions` is what a user gives (``cfdesign design``
and ``cfdesign feasibility`` take the same options; a model file may declare its own
defaults as ``DESIGN = DesignOptions(...)``), and :func:`make_design` turns the options
into a design for a model, its network and its attack bound.

**Scalings U and V_i.**  The paper writes the Taylor remainders of ``f`` and of each
``h_i`` as ``U Ω e`` and ``V_i Θ e`` with ``Ω Ωᵀ <= I``, ``Θ Θᵀ <= I`` and gives no values.
``u_scale`` / ``v_scale`` take

* a number ``c``: ``c I``;
* a list of numbers: the diagonal (``U``: one per state component; ``V_i``: one per
  measurement component of the sensor);
* a square matrix;
* ``'prior'`` (the default of a model that declares none): derived once from the model's
  CasADi Hessians over the ``radius``-sigma ellipsoid of the prior around the operating
  point, per component, in the component's own unit (:func:`designer.linearization.component_scales`),
  so that metres, radians and pixels each get a scale of their own;
* for ``v_scale`` only: one entry per sensor (a list of the above, in sensor order) or a
  mapping from sensor name to an entry (key ``'*'``: every sensor not named; without it
  they keep the default).  A list of plain numbers is a diagonal when it has as many
  entries as every sensor has components, else one number per sensor.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any, Mapping, NamedTuple

import numpy as np

from .rule import BANK_MAX, CARRIES, EXCHANGES, ROBUSTNESS_MAX, ROUNDS_MAX, RULE_NAME, TABLE_KINDS, GainRule
from .linearization import DEFAULT_RADIUS, component_scales, remainder_gram, whitened_scales, whitening
from .network import SensorNetwork
from .validation import InputError, check_finite

if TYPE_CHECKING:  # CasADi is imported where a model is built, not here
    from .model import Model

__all__ = [
    "ConsensusDesign", "validate_design", "DesignOptions", "PAPER_DEFAULTS", "DESIGN_ASSUMPTIONS",
    "LINEARIZATIONS", "make_design", "resolve_scaling", "parse_scale", "describe_design", "whitened_scaling",
    "whitened",
]

LINEARIZATIONS = ("fixed", "hessian", "structured")

# The published choices of seed 003 and, marked, the values it leaves out.
PAPER_DEFAULTS = {
    "sigma": 0.1,
    "beta": 0.1,
    "tau": 0.01,
    "epsilon_fraction": 0.5,  # assumption: epsilon = 0.5 / d_max (not given)
}
DESIGN_ASSUMPTIONS = (
    "consensus design: the paper gives no scaling matrices U, V_i; a model without declared scalings gets them from "
    "its CasADi Hessians over the 3-sigma ellipsoid of the prior around the operating point, per component "
    "(--u-scale / --v-scale prior; override with a number, a diagonal or a matrix).",
    "consensus design: mode scheduled with the prior scalings measures the remainders in the prior's units: "
    "U Omega W e and V_i Theta W e with W = P0^(-1/2), U and V_i from the Hessians whitened by P0 over the same "
    "ellipsoid (remainder_structure in schedule.json); at each step they are taken times sqrt(min(1, max_i "
    "lambda_max(W P_i W'))), P_i the nodes' expected covariance of the step (the errors assumed within 3 sigma of "
    "it), and its gains count the sensor's remainder at that reach as measurement noise.",
    "consensus design: the paper gives no epsilon; default epsilon = 0.5 / d_max, the middle of (0, 1/d_max).",
    "consensus design: Phi_0|0 is the prior covariance and every node starts at the prior mean.",
    "consensus design: neighbours' Phi_{j,k+1|k} used in (27) are exchanged with the predictions and are not "
    "attacked (the attack model of the paper concerns the estimate packets).",
)


class ConsensusDesign(NamedTuple):
    """Design parameters of the consensus filter.

    ``U`` (n_x x n_x) and ``V`` (one ``n_z_i x n_z_i`` matrix per sensor, or one matrix
    for every sensor when they have the same dimension) scale the linearisation
    remainders ``U Ω e`` and ``V_i Θ e``; ``C_i = tau Φ_{i,k+1|k}`` (the paper's choice).
    ``delta`` bounds the injected signal, ``||xi|| <= delta``.  In ``'tuned'`` mode,
    ``sigma``, ``beta`` and ``tau`` are not used: σ, β, C and K come from the convex
    tuning layer (:mod:`designer.tuning`) at every node and step, with (28)-(29)
    kept at the relative margin ``designer.tuning.MARGIN``.  With
    ``linearization='hessian'``, ``U`` and ``V_i`` are replaced at every node and step by
    ``u I`` and ``v I`` derived from the CasADi Hessians over the ellipsoid of
    Φ (:mod:`designer.linearization`); the given U, V then only fix the shapes.  In
    ``'mse'`` mode the gains minimise the predicted mean-square error of every node
    (:mod:`designer.joint`, with ``fdi_moment`` = E[ξ ξᵀ] and ``fdi_mean`` = E[ξ] of the
    injected signal) and one σ and one β certify them (the smallest bound (26)-(27) of the
    stacked error of all nodes for those gains).  ``fdi_span`` (the projector onto the
    components the signal reaches) shapes the falsified packets' term of the tuned and mse
    bounds, ``δ² Π`` instead of ``δ² I``.
    """

    epsilon: float
    sigma: float
    beta: float
    tau: float
    U: np.ndarray
    V: Any  # tuple of (n_z_i, n_z_i) arrays, one per sensor (a single matrix is broadcast by validate_design)
    delta: float
    rule: GainRule  # the gain rule (designer.rule; its package rules/<name>/): how the gains are chosen
    linearization: str = "fixed"  # 'fixed': the given U, V; 'hessian': U, V from the model's Hessians per node/step;
    # 'structured': as 'hessian' but with the remainder written U Ω D e, D selecting the variables the model is
    # nonlinear in (the tighter variant: the multipliers act only along those directions)
    radius: float = DEFAULT_RADIUS  # 'hessian': the bound holds for errors within `radius` standard deviations of Φ
    fdi_moment: np.ndarray | None = None  # 'mse': E[ξ ξᵀ] (n_x x n_x) of one falsified packet (None: 0)
    fdi_mean: np.ndarray | None = None  # 'mse': E[ξ] (n_x,) of one falsified packet (None: 0)
    gate: float = 0.0  # false-rejection probability of the χ² gate on neighbour packets (0: no gate)
    fdi_signal: Any = None  # 'mse' with a gate: the designer.attacks.FDISignal (what of it passes the gate)
    fdi_span: np.ndarray | None = None  # tuned/mse: projector onto the components ξ can reach (None: all, ξξᵀ <= δ² I)
    tables: Any = None  # 'scheduled': the offline tables (rules.scheduled.design.ScheduledTables)
    exchange: str = "predictions"  # what a packet carries: 'predictions' (7), or 'measurements' too (mode scheduled)
    robustness: float = 0.0  # 'scheduled': the margin δ of the link gains (rules.scheduled.design.link_gains)
    rounds: int = 1  # 'scheduled': exchange rounds per step (the first with the measurements); relaying: hops
    bank: int = 0  # 'scheduled': axes of the bank of operating points off the nominal (rules.scheduled.design; 0: none)
    # 'scheduled': the tables' kind, 'per-step' or 'stationary' (rules.scheduled.design.own_steps); None: by their size
    table_kind: str | None = None
    # 'scheduled' with the 'prior' scalings: the remainders are U Ω W e and V_i Θ W e with this W (n_x x n_x), the
    # prior covariance's inverse root (designer.linearization.whitened_scales); None: W = I
    remainder_structure: np.ndarray | None = None
    # with it: the sensors' remainders at one common error as one (designer.linearization.remainder_gram), over the
    # sensors' components padded to the largest sensor's dimension (N mz, N mz)
    remainder_gram: np.ndarray | None = None
    # a rule whose nodes may carry their regions (GainRule.regional): one sorted index array per node, the region each
    # node answers for; the node then carries that region and what its measurements and dynamics need
    # (designer.regions.carried_states).  None: every node carries the whole state
    carried_regions: Any = None

    @property
    def mode(self) -> str:
        """The gain rule's name (``--mode``), as records and messages show it."""
        return self.rule.name


def validate_design(design: ConsensusDesign, model: Model, network: SensorNetwork) -> ConsensusDesign:
    """Check ranges and shapes; raise :class:`InputError` naming the parameter.

    Returns the design with ``V`` as a tuple of one matrix per sensor.
    """
    d_max = network.d_max
    eps = float(design.epsilon)
    upper = np.inf if d_max == 0 else 1.0 / d_max
    if not (0.0 < eps < upper):
        raise InputError(f"epsilon must lie in (0, 1/d_max) = (0, {upper:.6g}), got {eps!r}")
    if not (0.0 <= float(design.gate) < 1.0):
        raise InputError(f"gate must be a false-rejection probability in [0, 1), got {design.gate!r}")
    for name in ("sigma", "beta", "tau", "delta"):
        v = getattr(design, name)
        if not np.isfinite(v) or v < 0:
            raise InputError(f"{name} must be a finite number >= 0, got {v!r}")
    if design.linearization not in LINEARIZATIONS:
        raise InputError(f"linearization must be 'fixed', 'hessian' or 'structured', got {design.linearization!r}")
    if not np.isfinite(design.radius) or design.radius <= 0:
        raise InputError(f"radius must be > 0, got {design.radius!r}")
    if not isinstance(design.rule, GainRule):
        raise InputError(f"rule must be a gain rule (rules.get(name)), got {design.rule!r}")
    rule = design.rule
    rule.check_design(design)
    if network.n_nodes != model.n_sensors:
        raise InputError(f"the network has {network.n_nodes} nodes but the model has {model.n_sensors} sensors "
                         "(one node per sensor)")
    for name, p in (("dos probability", network.dos_prob), ("fdi probability", network.fdi_prob)):
        if np.any(p >= 1.0):
            raise InputError(f"{name} must lie in [0, 1) on every channel")
    U = check_finite("U", design.U)
    if U.shape != (model.n_x, model.n_x):
        raise InputError(f"U must have shape ({model.n_x}, {model.n_x}), got {U.shape}")
    V = design.V
    if isinstance(V, np.ndarray) or (not isinstance(V, (tuple, list))):
        V = check_finite("V", V)
        dims = set(model.sensor_dims)
        if len(dims) != 1:
            raise InputError("V must give one matrix per sensor when the sensors differ in dimension "
                             f"({list(model.sensor_dims)})")
        V = (V,) * model.n_sensors
    if len(V) != model.n_sensors:
        raise InputError(f"V must give one matrix per sensor ({model.n_sensors}), got {len(V)}")
    Vs = []
    for i, (Vi, s) in enumerate(zip(V, model.sensors)):
        Vi = check_finite(f"V[{i}]", Vi)
        if Vi.shape != (s.dim, s.dim):
            raise InputError(f"V of sensor {s.name!r} must have shape ({s.dim}, {s.dim}), got {Vi.shape}")
        Vs.append(Vi)
    if design.sigma == 0 and np.any(U) and rule.fixed_multipliers:
        raise InputError("sigma must be > 0 when U is nonzero")
    if design.beta == 0 and any(np.any(v) for v in Vs) and rule.fixed_multipliers:
        raise InputError("beta must be > 0 when V is nonzero")
    M = np.zeros((model.n_x, model.n_x)) if design.fdi_moment is None else check_finite("fdi_moment", design.fdi_moment)
    if M.shape != (model.n_x, model.n_x):
        raise InputError(f"fdi_moment must have shape ({model.n_x}, {model.n_x}), got {M.shape}")
    P = np.eye(model.n_x) if design.fdi_span is None else check_finite("fdi_span", design.fdi_span)
    if P.shape != (model.n_x, model.n_x) or not np.allclose(P @ P, P) or not np.allclose(P, P.T):
        raise InputError(f"fdi_span must be a symmetric projector of shape ({model.n_x}, {model.n_x})")
    mu = np.zeros(model.n_x) if design.fdi_mean is None else check_finite("fdi_mean", design.fdi_mean)
    if mu.shape != (model.n_x,):
        raise InputError(f"fdi_mean must have shape ({model.n_x},), got {mu.shape}")
    W = design.remainder_structure
    if W is not None:
        W = check_finite("remainder_structure", W)
        if W.shape != (model.n_x, model.n_x) or not rule.offline_tables:
            raise InputError(f"remainder_structure must be a ({model.n_x}, {model.n_x}) matrix of a rule with offline "
                             f"tables (mode 'scheduled'), got shape {W.shape} in mode {design.mode!r}")
    G = design.remainder_gram
    if G is not None:
        G = check_finite("remainder_gram", G)
        size = model.n_sensors * max(model.sensor_dims)
        if G.shape != (size, size) or W is None:
            raise InputError(f"remainder_gram must be a ({size}, {size}) matrix beside a remainder_structure, got "
                             f"shape {G.shape}")
    regions = design.carried_regions
    if regions is not None:
        if not rule.regional:
            raise InputError(f"carried_regions: mode {design.mode!r} carries the whole state at every node (a node "
                             "carries only its region in a rule that fuses its ball's measurements without consensus "
                             "on estimates)")
        try:
            regions = tuple(np.asarray(r, dtype=int).reshape(-1) for r in regions)
        except (TypeError, ValueError):
            raise InputError("carried_regions must hold one sequence of state indices per node") from None
        if len(regions) != network.n_nodes or any(r.size == 0 or r.min() < 0 or r.max() >= model.n_x
                                                  for r in regions):
            raise InputError(f"carried_regions must hold one non-empty sequence of state indices 0..{model.n_x - 1} "
                             f"per node ({network.n_nodes})")
        regions = tuple(np.unique(r) for r in regions)
    return design._replace(epsilon=eps, U=U, V=tuple(Vs), fdi_moment=M, fdi_span=P, fdi_mean=mu,
                           remainder_structure=W, remainder_gram=G, carried_regions=regions)


# ------------------------------------------------------------------------------------------- scalings
def parse_scale(name: str, text: str):
    """A command-line scale: ``prior``, a number, a comma list (diagonal) or a JSON matrix."""
    import json

    t = text.strip()
    if t == "prior":
        return "prior"
    try:
        value = json.loads(t) if t.startswith("[") else [float(v) for v in t.split(",")]
    except (ValueError, json.JSONDecodeError):
        raise InputError(f"--{name} must be 'prior', a number, a comma-separated diagonal or a JSON matrix, "
                         f"got {text!r}") from None
    arr = check_finite(f"--{name}", value)
    if np.any(arr < 0) and arr.ndim == 1:
        raise InputError(f"--{name} must be >= 0 (a scale), got {text!r}")
    return float(arr[0]) if arr.ndim == 1 and arr.size == 1 else arr.tolist()


def _one_scale(name: str, value, dim: int, prior_diag: np.ndarray) -> np.ndarray:
    if isinstance(value, str):
        if value != "prior":
            raise InputError(f"{name} must be 'prior', a number, a diagonal or a matrix, got {value!r}")
        return np.diag(prior_diag)
    arr = check_finite(name, value)
    if arr.ndim == 0:
        if arr < 0:
            raise InputError(f"{name} must be >= 0, got {float(arr)!r}")
        return float(arr) * np.eye(dim)
    if arr.ndim == 1:
        if arr.shape != (dim,) or np.any(arr < 0):
            raise InputError(f"{name} as a diagonal must have {dim} entries >= 0, got {arr.tolist()}")
        return np.diag(arr)
    if arr.shape != (dim, dim):
        raise InputError(f"{name} as a matrix must be {dim} x {dim}, got shape {arr.shape}")
    return arr


def _is_per_sensor(value, model: Model) -> bool:
    """A list with one entry per sensor (not a diagonal or a matrix)."""
    if isinstance(value, (str, Mapping)) or not isinstance(value, (list, tuple)) or len(value) != model.n_sensors:
        return False
    if any(isinstance(v, (str, list, tuple, np.ndarray)) for v in value):
        return True
    # plain numbers: a diagonal when every sensor has that many components, else one number per sensor
    return set(model.sensor_dims) != {len(value)}


def resolve_scaling(model: Model, u_scale, v_scale, *, x0, P0, u0=None, radius: float = DEFAULT_RADIUS
                    ) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """``U`` (n_x, n_x) and one ``V_i`` per sensor from the option values (see the module docstring)."""
    prior_u = prior_v = None

    def hessians():
        nonlocal prior_u, prior_v
        if prior_u is None:
            x0a, P = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
            # each component's Hessian on its structural support (model.hessian_blocks): on a field or a grid a few
            # numbers per component where the dense Hessians are n_x² (gigabytes at a hundred states)
            f_at = model.hessian_blocks()[1]
            fh = lambda pts: [b for m in range(max(model.n_modes, 1))  # noqa: E731 - every mode's, mode by mode
                              for b in f_at(pts, 0, u0, m if model.n_modes else None)]
            comps = component_scales(fh, x0a, P, radius)
            prior_u = comps[: model.n_x] if not model.n_modes else comps.reshape(model.n_modes, model.n_x).max(0)
            prior_v = [component_scales(lambda pts, i=i: model.hessian_blocks(i)[1](pts, 1), x0a, P, radius)
                       for i in range(model.n_sensors)]
        return prior_u, prior_v

    u_val = "prior" if u_scale is None else u_scale
    U = _one_scale("u_scale", u_val, model.n_x, hessians()[0] if u_val == "prior" else np.zeros(model.n_x))
    v_val = "prior" if v_scale is None else v_scale
    names = [s.name for s in model.sensors]
    if isinstance(v_val, Mapping):
        unknown = [k for k in v_val if k not in names and k != "*"]
        if unknown:
            raise InputError(f"v_scale names unknown sensors {unknown}; sensors: {', '.join(names)}")
        rest = v_val.get("*", "prior")
        if isinstance(rest, Mapping):
            raise InputError("v_scale '*' (the other sensors) must be one scale, not a mapping")
        entries = [v_val.get(n, rest) for n in names]
    elif _is_per_sensor(v_val, model):
        entries = list(v_val)
    else:
        entries = [v_val] * model.n_sensors
    Vs = []
    for i, (s, e) in enumerate(zip(model.sensors, entries)):
        diag = hessians()[1][i] if isinstance(e, str) else np.zeros(s.dim)
        Vs.append(_one_scale(f"v_scale of sensor {s.name!r}", e, s.dim, diag))
    return U, tuple(Vs)


def whitened(rule: GainRule, options: "DesignOptions") -> bool:
    """Whether a design of ``rule`` with ``options`` takes the scalings in the prior's own units
    (:func:`whitened_scaling`: a rule with offline tables, linearization 'fixed', both scalings 'prior'), whose
    whitened Hessians are dense (n_x² numbers per component), rather than :func:`resolve_scaling`'s."""
    return rule.offline_tables and (options.linearization or "fixed") == "fixed" and all(
        isinstance(s, str) and s == "prior" or s is None for s in (options.u_scale, options.v_scale))


def whitened_scaling(model: Model, *, x0, P0, u0=None, radius: float = DEFAULT_RADIUS
                     ) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray, np.ndarray]:
    """The 'prior' scalings of the scheduled design's certificate in the prior's own units: ``U``, one ``V_i`` per
    sensor and ``W = P0^{-1/2}``, the remainders ``U Ω W e`` and ``V_i Θ W e``
    (:func:`designer.linearization.whitened_scales`, over the ``radius``-sigma ellipsoid of ``P0`` at ``x0``), and the
    sensors' joint remainder matrix (:func:`designer.linearization.remainder_gram`, every sensor's components padded
    to the largest sensor's dimension)."""
    x0a, P = np.asarray(x0, dtype=float), np.asarray(P0, dtype=float)
    if model.n_modes:
        fh = lambda pts: np.concatenate([model.f_hessian(pts, 0, u0, m) for m in range(model.n_modes)], axis=1)  # noqa
    else:
        fh = lambda pts: model.f_hessian(pts, 0, u0)  # noqa: E731
    u = whitened_scales(fh, x0a, P, radius)
    u = u[: model.n_x] if not model.n_modes else u.reshape(model.n_modes, model.n_x).max(0)
    V = tuple(np.diag(whitened_scales(lambda pts, i=i: model.h_hessian(i, pts, 1), x0a, P, radius))
              for i in range(model.n_sensors))
    mz = max(model.sensor_dims)
    comp = np.concatenate([i * mz + np.arange(m) for i, m in enumerate(model.sensor_dims)])
    joint = remainder_gram(lambda pts: np.concatenate([model.h_hessian(i, pts, 1) for i in range(model.n_sensors)],
                                                      axis=-3), x0a, P, radius)
    gram = np.zeros((model.n_sensors * mz, model.n_sensors * mz))
    gram[np.ix_(comp, comp)] = joint
    return np.diag(u), V, whitening(P), gram


# ------------------------------------------------------------------------------------------- options
@dataclass(frozen=True)
class DesignOptions:
    """The options of ``cfdesign design`` and ``cfdesign feasibility`` (``None``: the default).

    Parameters
    ----------
    mode : str, the name of a gain rule (:mod:`rules`; resolved by the command, :func:`rules.get`)
        ``paper``: σ, β fixed, ``C = τ Φ_pred``, the gain (30); ``tuned``: the convex tuning layer
        minimises the bound (both ``local``: computed online at each node); ``mse``: gains minimising the
        predicted mean-square error (:mod:`designer.joint`), certified by the σ, β that make the bound
        smallest for them (``global``: an oracle needing the network's joint state, not deployable).
    epsilon : float in (0, 1/d_max)
    sigma, beta : float >= 0
        The multipliers of (26)-(27) in paper mode (the tuning layer chooses them otherwise).
    tau : float >= 0
        ``C = tau Φ_pred`` in paper mode.
    u_scale, v_scale
        The scalings ``U`` and ``V_i`` (see the module docstring).
    linearization : {'fixed', 'hessian', 'structured'}
        ``fixed``: the given scalings; ``hessian``: ``u I``, ``v I`` from the Hessians per node and
        step over the ``radius``-sigma ellipsoid of Φ; ``structured``: the same restricted to the
        variables the model is nonlinear in.
    radius : float > 0
        Standard deviations covered by the Hessian-derived scalings.
    dos, fdi : float in [0, 1)
        Override the attack specification's probability on every channel and uplink.
    delta : float >= 0
        Override the FDI bound (and scale the simulated signal to it).
    amplitude : float >= 0
        Override the injected signal's amplitude per attacked component (its bound follows).
    gate : float in [0, 1)
        The χ² gate on received neighbour packets: its false-rejection probability for a
        clean packet (0: no gate; see :func:`filters.consensus.gate`).
    exchange : {'measurements', 'predictions'}
        Mode ``scheduled``: a packet carries the sender's prediction and its measurement (the default),
        or its prediction alone, as in (7).  The other modes exchange predictions.
    robustness : float in [0, 100]
        Mode ``scheduled``: the margin δ of the link gains: each neighbour's difference is taken to carry an
        extra independent error of covariance δ P_ii besides its tabulated moments
        (default :data:`ROBUSTNESS`; 0: the tables' MMSE gains, fragile where the state
        leaves the nominal geometry).
    rounds : int in [1, 64]
        Mode ``scheduled``: exchange rounds per step, each one packet per channel: the first carries the
        senders' predictions (and measurements), the others their current estimates (default 1).  With more
        than one the design computes no certificate (its expected covariance treats the rounds' packet
        losses as fresh draws; the simulations hold one per step): check it with ``study consensus-robot``.
        Modes ``relay`` and ``flood``: the hops L over which every measurement is relayed per step, one packet per
        channel and round (default :func:`rules.relay.design.default_hops`: the network's diameter, at most 8).
    bank : int in [0, 3]
        Mode ``scheduled``: the axes A of its bank of operating points (default 0: none).  Besides the tables
        along the nominal trajectory the design computes stationary tables at ``3^A - 1`` points off it, on a
        lattice over the A principal axes of the open-loop covariance at the horizon, and each node uses, at
        every step, the tables of the point nearest its own prediction (:mod:`rules.scheduled.design`, "Bank of
        operating points"): for a state that may leave the region of the nominal geometry (a target leaving
        the sensor field).  Not covered by the certificate, which is the nominal design's.
    table_kind : {'per-step', 'stationary'}
        Mode ``scheduled``: ``per-step``, each step's own tables along the nominal trajectory; ``stationary``, at
        every step the tables of the expected recursion's fixed point at the operating point (one set per node: its
        C export is one step's size; its expected covariance and certificate are those of these tables).  Default:
        per-step while the per-step tables hold at most :data:`rules.scheduled.design.TABLES_PER_STEP_MAX`
        numbers; beyond, where the nominal trajectory keeps the operating point's linearisation, the first steps'
        own tables as far as they fit and the stationary ones after (:func:`rules.scheduled.design.own_steps`).
    carry : {'whole', 'region'}
        A rule whose nodes may carry their regions (:attr:`designer.rule.GainRule.regional`: the ones that relay) on
        a model that declares ``REGIONS``: ``region``, each node carries only the
        states its region, its ball's measurements and their dynamics need (:mod:`designer.regions`); its numbers
        on them are those of the whole-state design, and its bound and verdict are on its region; ``whole``: every
        node carries the whole state (default: ``region`` on a model with ``REGIONS``,
        :func:`studies.design_options.effective`; ``whole`` otherwise).
    """

    mode: str | None = None
    epsilon: float | None = None
    sigma: float | None = None
    beta: float | None = None
    tau: float | None = None
    u_scale: Any = None
    v_scale: Any = None
    linearization: str | None = None
    radius: float | None = None
    dos: float | None = None
    fdi: float | None = None
    delta: float | None = None
    amplitude: float | None = None
    gate: float | None = None
    exchange: str | None = None
    robustness: float | None = None
    rounds: int | None = None
    bank: int | None = None
    table_kind: str | None = None
    carry: str | None = None

    ATTACK_FIELDS = ("dos", "fdi", "delta", "amplitude")

    def __post_init__(self):
        if self.mode is not None and not (isinstance(self.mode, str) and RULE_NAME.fullmatch(self.mode)):
            raise InputError(f"mode must be the name of a gain rule (cfdesign design --help lists them), got "
                             f"{self.mode!r}")
        if self.exchange is not None and self.exchange not in EXCHANGES:
            raise InputError(f"exchange must be one of {', '.join(map(repr, EXCHANGES))}, got {self.exchange!r}")
        if self.rounds is not None and (isinstance(self.rounds, bool) or not isinstance(self.rounds, (int, np.integer))
                                        or not 1 <= self.rounds <= ROUNDS_MAX):
            raise InputError(f"rounds must be an integer in [1, {ROUNDS_MAX}], got {self.rounds!r}")
        if self.bank is not None and (isinstance(self.bank, bool) or not isinstance(self.bank, (int, np.integer))
                                      or not 0 <= self.bank <= BANK_MAX):
            raise InputError(f"bank must be an integer in [0, {BANK_MAX}], got {self.bank!r}")
        if self.table_kind is not None and self.table_kind not in TABLE_KINDS:
            raise InputError(f"table_kind must be one of {', '.join(map(repr, TABLE_KINDS))}, got {self.table_kind!r}")
        if self.linearization is not None and self.linearization not in LINEARIZATIONS:
            raise InputError(f"linearization must be 'fixed', 'hessian' or 'structured', got {self.linearization!r}")
        if self.carry is not None and self.carry not in CARRIES:
            raise InputError(f"carry must be one of {', '.join(map(repr, CARRIES))}, got {self.carry!r}")
        for name in ("epsilon", "sigma", "beta", "tau", "radius", "dos", "fdi", "delta", "amplitude", "gate",
                     "robustness"):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not np.isfinite(v):
                raise InputError(f"{name} must be a finite number, got {v!r}")
            if v < 0:
                raise InputError(f"{name} must be >= 0, got {v!r}")
        if self.radius is not None and self.radius <= 0:
            raise InputError(f"radius must be > 0, got {self.radius!r}")
        if self.robustness is not None and self.robustness > ROBUSTNESS_MAX:
            raise InputError(f"robustness must lie in [0, {ROBUSTNESS_MAX:g}], got {self.robustness!r}")
        for name in ("dos", "fdi", "gate"):
            v = getattr(self, name)
            if v is not None and v >= 1:
                raise InputError(f"{name} must be a probability in [0, 1), got {v!r}")

    def merged(self, over: "DesignOptions | None") -> "DesignOptions":
        """These options with every value that ``over`` sets replacing this one's."""
        if over is None:
            return self
        given = {f.name: getattr(over, f.name) for f in fields(over) if getattr(over, f.name) is not None}
        if isinstance(given.get("v_scale"), Mapping) and self.v_scale is not None and "*" not in given["v_scale"]:
            # per-sensor values given on top of a default: the sensors not named keep the default
            rest = self.v_scale.get("*", "prior") if isinstance(self.v_scale, Mapping) else self.v_scale
            given["v_scale"] = {**(self.v_scale if isinstance(self.v_scale, Mapping) else {}), "*": rest,
                                **given["v_scale"]}
        return replace(self, **given)

    def attack_overrides(self) -> dict:
        return {k: getattr(self, k) for k in self.ATTACK_FIELDS}

    def as_dict(self) -> dict:
        """JSON-ready values (arrays as lists)."""
        def plain(v):
            if isinstance(v, np.ndarray):
                return v.tolist()
            if isinstance(v, Mapping):
                return {k: plain(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [plain(x) for x in v]
            return v

        return {f.name: plain(getattr(self, f.name)) for f in fields(self)}


def make_design(model: Model, network: SensorNetwork, *, rule: GainRule, delta: float, options: DesignOptions, x0,
                P0=None, u0=None, signal=None, regions=None) -> ConsensusDesign:
    """The :class:`ConsensusDesign` of gain rule ``rule`` and ``options`` for ``model`` on ``network`` (validated).

    ``rule`` is the options' mode resolved (:func:`rules.get`; ``options.mode`` is its name or None) and ``options``
    hold only what it takes (:meth:`designer.rule.GainRule.check_options`).

    ``delta`` is the FDI bound of the resolved attack specification and ``signal`` its
    :class:`designer.attacks.FDISignal`: its ``E[ξ ξᵀ]`` (the mse design's statistics) and the
    components it reaches (the certificate's FDI term ``δ² Π``; all components without a
    signal); ``x0`` (and ``u0``) the operating point of the ``'prior'`` scalings, ``P0`` the
    prior covariance there; ``regions`` the states each node answers for (:mod:`designer.regions`), which the
    nodes carry alone with ``options.carry == 'region'``.
    """
    from .tuning import tuned_epsilon

    if not isinstance(rule, GainRule) or options.mode not in (None, rule.name):
        raise InputError(f"rule must be the gain rule of options.mode {options.mode!r} (rules.get), got {rule!r}")
    d_max = max(network.d_max, 1)
    epsilon = options.epsilon
    if epsilon is None:
        epsilon = PAPER_DEFAULTS["epsilon_fraction"] / d_max if rule.fixed_multipliers else tuned_epsilon(d_max)
    radius = DEFAULT_RADIUS if options.radius is None else float(options.radius)
    P0 = model.prior.cov if P0 is None else P0
    if options.carry == "region" and regions is None:
        raise InputError("carry 'region' needs each node's region: the model file's REGIONS (docs/model-files.md)")
    structure = gram = None
    if whitened(rule, options):
        U, V, structure, gram = whitened_scaling(model, x0=x0, P0=P0, u0=u0, radius=radius)
    else:
        U, V = resolve_scaling(model, options.u_scale, options.v_scale, x0=x0, P0=P0, u0=u0, radius=radius)
    des = ConsensusDesign(
        epsilon=float(epsilon),
        sigma=PAPER_DEFAULTS["sigma"] if options.sigma is None else float(options.sigma),
        beta=PAPER_DEFAULTS["beta"] if options.beta is None else float(options.beta),
        tau=PAPER_DEFAULTS["tau"] if options.tau is None else float(options.tau),
        U=U,
        V=V,
        delta=float(delta),
        rule=rule,
        linearization=options.linearization or "fixed",
        radius=radius,
        fdi_moment=None if signal is None else signal.moment(model.n_x),
        fdi_span=None if signal is None else signal.span(model.n_x),
        fdi_mean=None if signal is None else signal.mean(model.n_x),
        gate=0.0 if options.gate is None else float(options.gate),
        fdi_signal=signal,
        rounds=rule.rounds(network, options.rounds),
        **rule.design_fields(options),
        remainder_structure=structure,
        remainder_gram=gram,
        carried_regions=regions if options.carry == "region" else None,
    )
    return validate_design(des, model, network)


def describe_design(des: ConsensusDesign) -> dict:
    """JSON-ready parameters of a design."""
    return {"mode": des.mode, "exchange": des.exchange, "robustness": des.robustness, "rounds": des.rounds,
            "bank": des.bank, "table_kind": des.table_kind,
            "linearization": des.linearization, "epsilon": des.epsilon, "sigma": des.sigma,
            "beta": des.beta, "tau": des.tau, "delta": des.delta, "radius": des.radius, "gate": des.gate,
            "U": np.asarray(des.U).tolist(),
            "V": [np.asarray(v).tolist() for v in (des.V if isinstance(des.V, (tuple, list)) else (des.V,))],
            "remainder_structure": None if des.remainder_structure is None else
            np.asarray(des.remainder_structure).tolist(),
            "carry": "whole" if des.carried_regions is None else "region"}

