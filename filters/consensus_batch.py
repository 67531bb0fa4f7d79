"""The consensus EKF of :mod:`filters.consensus`, batched over Monte Carlo runs and nodes: its one implementation.

:func:`run_consensus_batch` runs many Monte Carlo runs of the filter at once; a run alone
(:func:`filters.consensus.run_consensus`) is a batch of one, and a run's numbers do not depend on
the other runs of its batch.  Run by run it computes the prediction (3), bound (26), the χ² gate
(``design.gate > 0``), exchange, gain (30), bound (27), conditions (28)-(29) and
Theorem 2 margins, the fallback recursion and ``valid`` flags (a node's own violations
and its neighbours' non-bound predictions), the violations node by node in step order, the
linearisation scalings of ``design.linearization``, wrapped angular residuals, sensors of
mixed dimensions (gains zero-padded), the bound-trace limit, and divergence: a run whose
estimate or covariance leaves finite numbers stops there (its arrays NaN from that step on,
a ``'diverged'`` violation) while the other runs go on.  Its step runs on the consensus family's one time loop,
:func:`filters.engine.run_batch`, which owns the steps, the records, the runs going on and that stop; this module
holds the result types of a run and of a batch (:class:`ConsensusResult`, :class:`ConsensusBatchResult`) and what
the modes' steps share (the channels' attacks and sums, the inputs checked, the prediction and update of stacked
nodes).

Every quantity of a step is a stack over (runs, nodes):

* the model's NumPy translation (:mod:`designer.codegen`) evaluates ``f`` and ``F`` at every
  run and node in one call, and ``h_i``, ``H_i`` per sensor over all runs (the numba kernels
  of :mod:`designer.jit` do not take known inputs; here the model evaluation costs well
  under a microsecond per node-step, the linear algebra dominates);
* the bounds are the functions of :mod:`designer.bounds` and :mod:`designer.linearization`
  over stacked ``(items, n, n)`` matrices (``np.linalg.eigh`` / ``eigvalsh`` / ``solve``);
* the exchange and the neighbour terms of (27) are sums over the network's directed
  channels (:class:`EdgeAttacks` holds the realised attacks on them), linear in the number
  of edges, so 512-node networks over hundreds of runs fit in memory.

The filter of a design is its gain rule's (``design.rule.batch_filter()``, :mod:`rules`): a
:class:`NodeRule`, a pair of batched functions over stacked items (a prediction and an update each node
applies on its own over Theorem 1's recursion; ``weighted``: the weighted (27), with one group slot per
incoming channel, each (run, node) carrying its weights per slot from one update to the next and
warm-starting from them, :func:`designer.tuning.warm_start_weights`), run by this module's loop; or a
function with :func:`run_consensus_batch`'s parameters, which this function hands the design to.  A fixed
gain schedule (``gains=``, e.g. a design's, replayed on other runs) takes the place of the rule: every node
on the fallback recursion with the given gains, nothing certified.  The straightforward per-node loop this batch was
written from is kept as the tests' reference (``tests/consensus_reference.py``).
"""
from __future__ import annotations

import inspect
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from designer.bounds import (
    BOUND_LIMIT,
    optimal_gain_from,
    prediction_recursion,
    shifted_inverse,
    spectrum,
    theorem2_margin,
    update_bound_from,
)
from designer.attacks import FDISignal
from designer.design import ConsensusDesign, validate_design
from designer.linearization import hessian_cover, prediction_scaling, selection, update_scaling
from designer.model import Model
from designer.network import SensorNetwork
from designer.tuning import neighbour_group_stack, warm_start_weights
from designer.validation import InputError, check_covariance, check_finite

from .attacks import AttackPattern, channel_attacks, channel_draws
from .channels import GATE_COUNTS, channel_packets, gate_channels
from .engine import Diagonal, Latest, Step, diagonals, history, run_batch
from .result import DIVERGED_REASON, HARD_CONDITIONS, FilterResult, constant_messages, diverged_nodes
from .rrp import wrap_angles

# the reason of a (28) violation where a bound's trace reached the limit (every mode that certifies a bound)
LIMIT_REASON = f"the bound's trace reached {BOUND_LIMIT:g}: it certifies nothing and (26) overflows"

__all__ = ["EdgeAttacks", "ConsensusResult", "ConsensusBatchResult", "run_consensus_batch", "consensus_result",
           "COVARIANCE_FIELDS", "PREDICTION_FIELDS",
           "NodeRule", "PredictionChoice",
           "UpdateChoice", "LIMIT_REASON", "wrap_residuals", "run_networks",
           "batch_inputs", "result_arrays", "consensus_arrays",
           "per_run", "predict_nodes", "update_nodes", "node_groups", "first_step_error", "weighted_items", "Exchange"]


# --------------------------------------------------------------------------- channels and their attacks
def _channels(network: SensorNetwork) -> tuple[np.ndarray, np.ndarray]:
    """``(receiver, sender)`` of every directed channel ``sender -> receiver``, receiver-major."""
    receiver, sender = np.nonzero(network.adjacency)
    return receiver, sender


class EdgeAttacks(NamedTuple):
    """Realised channel attacks of many runs, on the network's directed channels only.

    Channel ``e`` is ``sender[e] -> receiver[e]``, in the order of
    ``np.nonzero(network.adjacency)`` (receiver-major); entry ``[r, k, e]`` is what
    :class:`filters.attacks.AttackPattern` holds at ``[k, receiver[e], sender[e]]`` for run ``r``.
    """

    receiver: np.ndarray  # (E,) int
    sender: np.ndarray  # (E,) int
    dos: np.ndarray  # bool (runs, steps, E)
    fdi: np.ndarray  # bool (runs, steps, E)
    xi: np.ndarray  # (runs, steps, E, n_x), zero where no FDI

    @classmethod
    def from_patterns(cls, network: SensorNetwork, patterns: Sequence[AttackPattern]) -> "EdgeAttacks":
        """The attacks of one :class:`~filters.attacks.AttackPattern` per run, on the channels of ``network``."""
        receiver, sender = _channels(network)
        n = network.n_nodes
        dos, fdi, xi = [], [], []
        for r, p in enumerate(patterns):
            if not isinstance(p, AttackPattern):
                raise InputError(f"attacks[{r}] must be a filters.attacks.AttackPattern, got {type(p).__name__}")
            if not p.fits(n):
                raise InputError(f"attacks[{r}] must hold the channels of the {n}-node network: "
                                 f"{AttackPattern.expected(n)}; got dos {np.shape(p.dos)}, fdi {np.shape(p.fdi)}, "
                                 f"xi_fdi {np.shape(p.xi_fdi)}")
            dos.append(p.dos[:, receiver, sender])
            fdi.append(p.fdi[:, receiver, sender])
            xi.append(p.xi_of((slice(None), receiver, sender)))
        if not dos:
            raise InputError("attacks must hold one AttackPattern per run, got none")
        return cls(receiver, sender, np.stack(dos), np.stack(fdi), np.stack(xi))

    @classmethod
    def simulate(cls, network: SensorNetwork, steps: int, n_x: int, rngs: Sequence[np.random.Generator],
                 signal: FDISignal) -> "EdgeAttacks":
        """The attacks of :func:`filters.attacks.simulate_attacks` of one Generator per run (``rngs``), the same
        numbers as :meth:`from_patterns` of them, computed on the network's channels alone: a run's dense pattern
        holds N² x n_x numbers a step (0.8 GB over 60 steps of a 118-node grid), its channels 2|E| x n_x."""
        rngs = list(rngs)
        if not rngs:
            raise InputError("rngs must hold one Generator per run, got none")
        return cls.from_draws(network, [channel_draws(steps, network.n_nodes, rng) for rng in rngs], n_x, signal)

    @classmethod
    def from_draws(cls, network: SensorNetwork, draws: Sequence[tuple[np.ndarray, np.ndarray]], n_x: int,
                   signal: FDISignal) -> "EdgeAttacks":
        """The attacks that each run's channel draws ``(u, s)`` (:func:`filters.attacks.channel_draws`, (steps, N, N)
        each) make on the channels of ``network``: the numbers of :func:`filters.attacks.attack_pattern` of them on
        the channels alone (no dense N x N x n_x array a step)."""
        receiver, sender = _channels(network)
        dos, fdi, xi = [], [], []
        for u, s in draws:
            d, f, x = channel_attacks(u[:, receiver, sender], s[:, receiver, sender],
                                      network.dos_prob[receiver, sender], network.fdi_prob[receiver, sender], n_x,
                                      signal)
            dos.append(d)
            fdi.append(f)
            xi.append(x)
        return cls(receiver, sender, np.stack(dos), np.stack(fdi), np.stack(xi))

    def pattern(self, r: int, n_nodes: int) -> AttackPattern:
        """Run ``r``'s attacks as the N x N :class:`~filters.attacks.AttackPattern` of :func:`run_consensus`
        (``filters.consensus.run_consensus``)."""
        steps = self.xi.shape[1]
        dos = np.zeros((steps, n_nodes, n_nodes), dtype=bool)
        fdi = np.zeros_like(dos)
        dos[:, self.receiver, self.sender] = self.dos[r]
        fdi[:, self.receiver, self.sender] = self.fdi[r]
        k, e = np.nonzero(self.fdi[r])  # the falsified entries, in the pattern's row-major order
        order = np.argsort((k * n_nodes + self.receiver[e]) * n_nodes + self.sender[e], kind="stable")
        return AttackPattern(dos, fdi, self.xi[r][k[order], e[order]])


class Exchange:
    """Sums over each node's incoming channels, for stacks ``(runs, E, ...)`` of per-channel values.

    Every sum adds a node's channels in their order from the first, ``((v_0 + v_1) + v_2) + ...`` (:meth:`sum`,
    :meth:`weighted_sum`, and :meth:`node_sum` for one node alone): a node filter's numbers are the batch's bit for
    bit, whatever numpy's reductions do (``np.add.reduceat`` associates differently from 4 terms on, and from one
    numpy to another)."""

    def __init__(self, network: SensorNetwork):
        self.receiver, self.sender = _channels(network)
        self.n = network.n_nodes
        deg = np.bincount(self.receiver, minlength=self.n)
        first = np.cumsum(deg) - deg
        # a node's k-th incoming channel, for the nodes that have one: (nodes, channels) for k = 0, 1, ...
        self._positions = [(np.flatnonzero(deg > k), first[deg > k] + k) for k in range(int(deg.max(initial=0)))]

    def _fold(self, term, shape: tuple) -> np.ndarray:
        out = np.zeros(shape)
        for k, (nodes, chans) in enumerate(self._positions):
            if k:
                out[:, nodes] += term(chans)
            else:
                out[:, nodes] = term(chans)
        return out

    def sum(self, values: np.ndarray) -> np.ndarray:
        """Each node's sum of ``values`` (runs, E, ...) over its incoming channels: (runs, N, ...)."""
        return self._fold(lambda chans: values[:, chans], (values.shape[0], self.n) + values.shape[2:])

    def weighted_sum(self, w: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``sum(w * values[:, sender])`` for weights ``w`` (runs, E) and per-node ``values`` (runs, N, ...), the same
        bits, without forming the (runs, E, ...) products: a channel position at a time (64 nodes' 64 x 64
        information matrices in 2 runs: 17 ms a sum with the products, 6 without)."""
        tail = (slice(None), slice(None)) + (None,) * (values.ndim - 2)
        return self._fold(lambda chans: w[:, chans][tail] * values[:, self.sender[chans]],
                          (values.shape[0], self.n) + values.shape[2:])

    @staticmethod
    def node_sum(values: np.ndarray) -> np.ndarray:
        """One node's sum over its incoming channels ``(a, d, ...)`` -> ``(a, ...)``, added as :meth:`sum` adds
        every node's (a node filter's numbers are the batch's bit for bit)."""
        out = np.zeros(values.shape[:1] + values.shape[2:])
        for k in range(values.shape[1]):
            if k:
                out += values[:, k]
            else:
                out[...] = values[:, 0]
        return out


def edge_attacks(network: SensorNetwork, attacks, runs: int, steps: int, nx: int) -> EdgeAttacks | None:
    """The realised attacks as :class:`EdgeAttacks` on the network's channels, checked against the runs."""
    if attacks is None:
        return None
    if not isinstance(attacks, EdgeAttacks):
        if len(attacks) != runs:
            raise InputError(f"attacks must hold one AttackPattern per run ({runs}), got {len(attacks)}")
        attacks = EdgeAttacks.from_patterns(network, attacks)
    receiver, sender = np.nonzero(network.adjacency)
    if not (np.array_equal(attacks.receiver, receiver) and np.array_equal(attacks.sender, sender)):
        raise InputError("attacks are on other channels than the network's (EdgeAttacks.from_patterns builds them)")
    shape = attacks.dos.shape
    if len(shape) != 3 or shape[0] != runs or shape[1] < steps or shape[2] != receiver.size \
            or attacks.fdi.shape != shape or attacks.xi.shape != shape + (nx,):
        raise InputError(f"attacks must cover ({runs} runs, {steps} steps, {receiver.size} channels, n_x = {nx}), "
                         f"got dos {attacks.dos.shape}, xi {attacks.xi.shape}")
    return attacks


def run_networks(network, runs: int) -> tuple[SensorNetwork, list[SensorNetwork] | None]:
    """``network`` as the batches take it: one :class:`SensorNetwork` for every run, or one per run (the same
    graph, channels of different DoS/FDI probabilities, e.g. the settings of a sweep).  Returns the first
    network and the list of the runs' networks (None when one serves every run)."""
    if isinstance(network, SensorNetwork):
        return network, None
    try:
        nets = list(network)
    except TypeError:
        nets = []
    if len(nets) != runs or not all(isinstance(net, SensorNetwork) for net in nets):
        raise InputError(f"network must be a SensorNetwork or one per run ({runs}), got "
                         f"{len(nets) if nets else type(network).__name__}")
    if not all(np.array_equal(net.adjacency, nets[0].adjacency) for net in nets):
        raise InputError("network: the runs' networks must share one graph (only their channels' DoS and FDI "
                         "probabilities may differ)")
    return nets[0], nets


def per_run(value_of, network: SensorNetwork, nets: list | None) -> np.ndarray:
    """``value_of(net)`` of each run's network, stacked over the runs (one item when ``nets`` is None)."""
    return value_of(network)[None] if nets is None else np.stack([value_of(net) for net in nets])


# --------------------------------------------------------------------------- the result
class ConsensusResult(NamedTuple):
    """A run of the consensus filter over all nodes (:func:`filters.consensus.run_consensus`; a row of
    :class:`ConsensusBatchResult`, :meth:`ConsensusBatchResult.run`).

    Φ entries whose ``valid`` flag is False come from the fallback recursion and
    are *not* bounds.  ``violations`` lists ``{node, step, condition, margin}``:
    condition ``'(28)'`` is checked on ``Φ_{k|k}`` (reported at step k),
    ``'(29)'`` on ``Φ_{k+1|k}`` (step k+1), ``'theorem2'`` on ``Φ_{k|k}``; ``'diverged'``
    (with a ``reason``) when a node's estimate or covariance left finite numbers: the run
    stops there and every array is NaN from that step on.
    """

    x_post: np.ndarray  # (steps+1, N, n_x)
    x_pred: np.ndarray  # (steps, N, n_x)
    phi_post: np.ndarray  # (steps+1, N, n_x, n_x)
    phi_pred: np.ndarray  # (steps, N, n_x, n_x)
    K: np.ndarray  # (steps, N, n_x, max n_z_i): node i's gain in K[..., :n_z_i], zero beyond
    C: np.ndarray  # (steps, N, n_x, n_x)
    valid: np.ndarray  # (steps+1, N) bool: phi_post[k, i] is a bound
    margin28: np.ndarray  # (steps, N)
    margin29: np.ndarray  # (steps, N)
    theorem2: np.ndarray  # (steps+1, N)
    violations: list
    sigma: np.ndarray  # (steps, N) σ used in (26) at each node and step (NaN on the fallback)
    beta: np.ndarray  # (steps, N) β used in (27)
    predicted_mse: np.ndarray | None = None  # (steps+1, N) mode 'mse': tr P_ii of the joint error covariance
    gate_counts: np.ndarray | None = None  # (steps, 5) packets per step: GATE_COUNTS (received, rejected, ...)
    # (steps, N) mode 'mse': the condition number of the system each node's gains were solved from
    # (designer.joint.mse_gains); NaN where none was solved
    gain_condition: np.ndarray | None = None
    carried: np.ndarray | None = None  # (N, m) as ConsensusBatchResult's: the nodes' carried states (None: whole)

    @property
    def feasible(self) -> bool:
        return not any(v["condition"] in HARD_CONDITIONS for v in self.violations)

    @property
    def diverged(self) -> dict | None:
        """The ``'diverged'`` violation when the run stopped early (its arrays are NaN from that step)."""
        return next((v for v in self.violations if v["condition"] == "diverged"), None)


#: The fields of a :class:`ConsensusBatchResult` a run without its covariances' record keeps at their latest step
#: only (:class:`filters.engine.Latest`; None in the result): the bounds, the predictions' and the gains.
COVARIANCE_FIELDS = ("phi_post", "phi_pred", "K", "C")
#: Those a run without its predictions' record keeps so (``predictions=False``: Φ itself over the steps kept).
PREDICTION_FIELDS = ("phi_pred", "K", "C")


def result_arrays(runs: int, steps: int, n: int, nx: int, nz: int, *, latest: Sequence[str] = (),
                  variances: bool = False, **given: np.ndarray) -> dict:
    """The fields of an empty :class:`ConsensusBatchResult` (NaN, invalid, no violation, no packet) for ``runs``
    runs of ``steps`` steps of ``n`` nodes (``nz`` the widest measurement), with the optional ones; the fields in
    ``given`` are taken as they are, not allocated (at a hundred states each covariance field is a gigabyte), those
    in ``latest`` kept at their latest step only (:class:`filters.engine.Latest`); with ``variances`` Φ
    (``phi_post``) as its diagonals over the steps (:class:`filters.engine.Diagonal`: :func:`consensus_arrays`
    gives them as ``phi_variances``)."""
    def full(name, shape):
        if name in given:
            return given[name]
        if name == "phi_post" and variances and name not in latest:
            return Diagonal(shape)
        return Latest(shape[:1] + shape[2:]) if name in latest else np.full(shape, np.nan)

    return dict(x_post=full("x_post", (runs, steps + 1, n, nx)), x_pred=full("x_pred", (runs, steps, n, nx)),
                phi_post=full("phi_post", (runs, steps + 1, n, nx, nx)),
                phi_pred=full("phi_pred", (runs, steps, n, nx, nx)), K=full("K", (runs, steps, n, nx, nz)),
                C=full("C", (runs, steps, n, nx, nx)), valid=np.zeros((runs, steps + 1, n), dtype=bool),
                margin28=np.full((runs, steps, n), np.nan), margin29=np.full((runs, steps, n), np.nan),
                theorem2=np.full((runs, steps + 1, n), np.nan), violations=[[] for _ in range(runs)],
                sigma=np.full((runs, steps, n), np.nan), beta=np.full((runs, steps, n), np.nan),
                predicted_mse=np.full((runs, steps + 1, n), np.nan), gain_condition=np.full((runs, steps, n), np.nan),
                gate_counts=np.zeros((runs, steps, len(GATE_COUNTS)), dtype=np.int64))


class ConsensusBatchResult(NamedTuple):
    """Many runs of the consensus filter: the fields of :class:`ConsensusResult`
    with a leading runs axis, and ``violations`` one list per run; :data:`COVARIANCE_FIELDS` None for runs without
    their covariances' record."""

    x_post: np.ndarray  # (runs, steps+1, N, n_x)
    x_pred: np.ndarray  # (runs, steps, N, n_x)
    phi_post: np.ndarray  # (runs, steps+1, N, n_x, n_x)
    phi_pred: np.ndarray  # (runs, steps, N, n_x, n_x)
    K: np.ndarray  # (runs, steps, N, n_x, max n_z_i), zero beyond each node's n_z_i
    C: np.ndarray  # (runs, steps, N, n_x, n_x)
    valid: np.ndarray  # (runs, steps+1, N) bool
    margin28: np.ndarray  # (runs, steps, N)
    margin29: np.ndarray  # (runs, steps, N)
    theorem2: np.ndarray  # (runs, steps+1, N)
    violations: list  # one list of {node, step, condition, margin[, reason]} per run
    sigma: np.ndarray  # (runs, steps, N)
    beta: np.ndarray  # (runs, steps, N)
    predicted_mse: np.ndarray | None = None  # (runs, steps+1, N), mode 'mse'
    gate_counts: np.ndarray | None = None  # (runs, steps, 5) GATE_COUNTS
    gain_condition: np.ndarray | None = None  # (runs, steps, N), mode 'mse'
    # (N, m) each node's carried states (-1: unused) when the nodes carry their regions (designer.regions): phi_post,
    # phi_pred, K and C are then in those coordinates (m wide), x_post and x_pred NaN where a node does not carry
    carried: np.ndarray | None = None
    # (runs, steps+1, N, n_x): Φ's diagonal over the steps, where a run kept it alone (variances=True: phi_post None)
    phi_variances: np.ndarray | None = None

    @property
    def runs(self) -> int:
        return self.x_post.shape[0]

    def run(self, r: int) -> ConsensusResult:
        """Run ``r`` as the :class:`ConsensusResult` of :func:`run_consensus`."""
        optional = ("predicted_mse", "gate_counts", "gain_condition")
        fields = [self.violations[r] if f == "violations" else None if getattr(self, f) is None else getattr(self, f)[r]
                  for f in ConsensusResult._fields if f not in optional + ("carried", "phi_variances")]
        return ConsensusResult(*fields, *(None if getattr(self, f) is None else getattr(self, f)[r] for f in optional),
                               self.carried)

    @property
    def feasible(self) -> np.ndarray:
        """Per run: no hard violation ((28), (29) or divergence)."""
        return np.array([not any(v["condition"] in HARD_CONDITIONS for v in vs) for vs in self.violations])

    @property
    def diverged(self) -> list:
        """Per run, its ``'diverged'`` violation or None."""
        return [next((v for v in vs if v["condition"] == "diverged"), None) for vs in self.violations]


# --------------------------------------------------------------------------- gains and bounds per mode
class PredictionChoice(NamedTuple):
    """A mode's prediction at stacked items that run Theorem 1's recursion."""

    phi_pred: np.ndarray  # (m, n_x, n_x), NaN where (28) fails
    margin28: np.ndarray  # (m,)
    sigma: np.ndarray  # (m,), the σ of (26)


class UpdateChoice(NamedTuple):
    """A mode's update at stacked items whose prediction is a bound."""

    margin29: np.ndarray  # (m,); the items with margin <= 0 take the fallback
    beta: np.ndarray  # (m,)
    K: np.ndarray  # (m, n_x, n_z)
    C: np.ndarray  # (m, n_x, n_x)
    phi_post: np.ndarray  # (m, n_x, n_x)
    weights: np.ndarray | None = None  # (m, L) mode tuned: the weights of (27)'s groups (NaN: group absent)


class NodeRule(NamedTuple):
    """A gain rule that each node applies on its own over the bound recursion of Theorem 1, run by
    :func:`run_consensus_batch`'s loop: its prediction and update, both batched over stacked items (an update
    takes the items' Φ_pred as a Spectrum and a dict of their arrays: H, s, V, R, d, nt = the paper's neighbour
    terms, and with ``weighted`` the groups of (27), which are present and the warm-start weights w0)."""

    predict: Callable[..., PredictionChoice]
    update: Callable[..., UpdateChoice]
    weighted: bool = False  # the weighted (27): each node's weights per incoming channel, carried between steps


def _fallback_update(phi_pred, H, s, R, neighbour_terms, tau: float, K=None, C=None):
    """The fallback of a node off Theorem 1's recursion: β = 0, V = 0, no inflation ((1 + 2 d_i), 3 -> 1); the gains
    ``C = τ Φ_pred`` and the gain (30), or the given ``K``, ``C`` (a replayed schedule)."""
    M = shifted_inverse(phi_pred, 0.0)
    V = np.zeros(H.shape[:-1] + (H.shape[-2],))
    if K is None:
        C = tau * phi_pred
        K = optimal_gain_from(M, H, C, s, 0.0, V, R, 0)
    with np.errstate(over="ignore", invalid="ignore"):  # a bound beyond floats is caught as a divergence
        return K, C, update_bound_from(M, H, K, C, s, 0.0, V, R, 0, neighbour_terms / 3.0)


def _replay_gains(gains, steps: int, n: int, nx: int, nz: int) -> tuple[np.ndarray, np.ndarray]:
    """A replayed schedule ``(K, C)`` checked against the runs: K (steps' >= steps, N, n_x, >= n_z), C (steps', N,
    n_x, n_x)."""
    try:
        K, C = (np.asarray(g, dtype=float) for g in gains)
    except (TypeError, ValueError):
        raise InputError(f"gains must be a pair (K, C) of arrays, got {type(gains).__name__}") from None
    if K.ndim != 4 or K.shape[0] < steps or K.shape[1:3] != (n, nx) or K.shape[3] < nz \
            or C.shape != (K.shape[0], n, nx, nx):
        raise InputError(f"gains must be (K ({steps}+ steps, {n}, {nx}, {nz}+), C (the same steps, {n}, {nx}, {nx})) "
                         f"for {steps} steps of {n} nodes, got K {K.shape}, C {C.shape}")
    return K, C


def wrap_residuals(r: np.ndarray, angles: Sequence[int]) -> np.ndarray:
    """Residuals ``(..., n_z_i)`` with the angular components beyond ±π wrapped into (-π, π].

    Residuals already inside (-π, π] are left as they are (wrapping them would change their last bit).
    """
    if not angles:
        return r
    return np.where(np.isin(np.arange(r.shape[-1]), list(angles)) & (np.abs(r) > np.pi), wrap_angles(r, angles), r)


def _take(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``a[mask]`` (mask over the leading axes), a view when the mask is all True."""
    return a.reshape((mask.size,) + a.shape[mask.ndim:]) if mask.all() else a[mask]  # mask.size: -1 fails for 0 inputs


def _put(a: np.ndarray, mask: np.ndarray, values: np.ndarray) -> None:
    """``a[mask] = values``, without the mask when it is all True."""
    if mask.all():
        a[...] = values.reshape(a.shape)
    else:
        a[mask] = values


class _Group(NamedTuple):
    """Nodes whose sensors share a dimension (and, for the structured rule, a structure D)."""

    nodes: np.ndarray
    index: np.ndarray | slice  # the nodes as an index (a slice when they are all the nodes, in order)
    dim: int
    columns: np.ndarray  # (g, dim): each node's columns of the stacked measurement
    R: np.ndarray  # (g, dim, dim)
    V: np.ndarray  # (g, dim, dim)
    D: np.ndarray | None


def node_groups(model: Model, design: ConsensusDesign, node: int | None = None) -> list[_Group]:
    """The nodes grouped by sensor shape, each with its columns of the stacked measurement; ``node``: that node
    alone, as one group over a block of one node whose measurement is its own sensor's."""
    offsets = model.sensor_offsets
    keys: dict = {}
    for i, dim in enumerate(model.sensor_dims):
        cover = hessian_cover(model.casadi_h_hess[i]) if design.linearization == "structured" else ()
        keys.setdefault((dim, cover), []).append(i)
    out = []
    for (dim, cover), nodes in keys.items():
        if node is not None:
            if node not in nodes:
                continue
            nodes, offsets = [node], np.zeros_like(offsets)
        index = slice(None) if nodes == list(range(model.n_sensors)) or node is not None else np.array(nodes)
        columns = np.array([np.arange(offsets[i], offsets[i] + dim) for i in nodes])
        out.append(_Group(np.array(nodes), index, dim, columns,
                          np.stack([model.measurement_cov(i) for i in nodes]), np.stack([design.V[i] for i in nodes]),
                          selection(cover, model.n_x) if cover else None))
    return out


# --------------------------------------------------------------------------- the filter
def batch_inputs(model, z, inputs, x0, phi0, cov_name: str = "phi0"):
    z = check_finite("z", z)
    if z.ndim != 3 or z.shape[2] != model.n_z or z.shape[0] < 1 or z.shape[1] < 1:
        raise InputError(f"z must have shape (runs, steps, {model.n_z}) with runs, steps >= 1, got {z.shape}")
    runs, steps = z.shape[:2]
    u = np.zeros((steps, 0)) if inputs is None else check_finite("inputs", inputs)
    if not ((u.ndim == 2 and u.shape[0] == steps) or (u.ndim == 3 and u.shape[:2] == (runs, steps))):
        raise InputError(f"inputs must have shape ({steps}, n_u) or ({runs}, {steps}, n_u), one row per step, "
                         f"got {u.shape}")
    if u.shape[-1] != model.n_u:  # a model with known inputs run without them fails later, deep in f: here instead
        raise InputError(f"inputs must have shape ({steps}, {model.n_u}) or ({runs}, {steps}, {model.n_u}) (the "
                         f"model's known inputs), got {None if inputs is None else u.shape}")
    x0 = model.prior.mean if x0 is None else check_finite("x0", x0)
    if x0.shape not in ((model.n_x,), (runs, model.n_x)):
        raise InputError(f"x0 must have shape ({model.n_x},) or ({runs}, {model.n_x}), got {x0.shape}")
    phi0 = model.prior.cov if phi0 is None else np.asarray(phi0, dtype=float)
    if phi0.ndim == 3:
        if phi0.shape[0] != runs:
            raise InputError(f"{cov_name} must have shape ({model.n_x}, {model.n_x}) or ({runs}, {model.n_x}, "
                             f"{model.n_x}), got {phi0.shape}")
        phi0 = np.stack([check_covariance(f"{cov_name}[{r}]", p, model.n_x) for r, p in enumerate(phi0)])
    else:
        phi0 = check_covariance(cov_name, phi0, model.n_x)
    return z, u, np.broadcast_to(x0, (runs, model.n_x)), np.broadcast_to(phi0, (runs, model.n_x, model.n_x))


def first_step_error(r: int, v28, v29, phi0, phi_pred0, design: ConsensusDesign, nodes=None) -> InputError:
    """The InputError raised at the first step of run ``r`` in paper mode (σ or β beyond (28)/(29)); ``nodes``: the
    ids of the block's nodes (default: the network's, in order)."""
    if v28[r].any():
        lam = float(np.linalg.eigvalsh(phi0[r])[-1])
        return InputError(
            f"sigma must satisfy (28) at the first step: sigma < 1/((1+epsilon) lambda_max(Phi_0|0)) = "
            f"{1.0 / ((1.0 + design.epsilon) * lam):.6g}, got {design.sigma!r}")
    j = int(np.flatnonzero(v29[r])[0])
    lam = float(np.linalg.eigvalsh(phi_pred0[r, j])[-1])
    return InputError(f"beta must satisfy (29) at the first step: beta < 1/lambda_max(Phi_1|0) = {1.0 / lam:.6g} "
                      f"at node {j if nodes is None else int(nodes[j])}, got {design.beta!r}")


def predict_nodes(model: Model, design: ConsensusDesign, predict_rule, k: int, xk, Pk, prop, uk, d_max: int):
    """The prediction (3), (26), (28) of stacked nodes ``(a, n)`` (runs × nodes of a batch, or one node alone: the
    same numbers): ``xk``, ``Pk`` their posteriors, ``prop`` which are still on Theorem 1's recursion, ``uk`` the
    inputs.  Returns ``(x̂⁻, Φ⁻, margin (28), σ, which Φ⁻ are bounds, Theorem 2's margin, which reached the bound
    limit)``; a node off the recursion or failing (28) takes the fallback ``F Φ Fᵀ + Q``."""
    F = model.F_expected(xk, k, uk)
    xp = model.f_expected(xk, k, uk)
    a, n, nx = xk.shape
    limit = prop & ~(np.trace(Pk, axis1=-2, axis2=-1) < BOUND_LIMIT)
    bound = prop & ~limit
    margin28 = np.where(limit, -np.inf, np.nan)
    sigma = np.full((a, n), np.nan)
    pvalid = np.zeros((a, n), dtype=bool)
    Pp = np.empty((a, n, nx, nx))
    th2k = np.full((a, n), np.nan)
    if bound.any():
        ub = uk if uk.ndim == 1 else _take(np.broadcast_to(uk, (a, n, uk.shape[-1])), bound)
        Sk = spectrum(_take(Pk, bound))  # one eigh for (28), (26) and Theorem 2
        U, D = prediction_scaling(model, _take(xk, bound), Sk.phi, k, ub, design.linearization, design.radius,
                                  design.U)
        choice = predict_rule(Sk, _take(F, bound), U, model.process_cov, D, design)
        _put(margin28, bound, choice.margin28)
        good = choice.margin28 > 0
        _put(pvalid, bound, good)
        _put(Pp, pvalid, _take(choice.phi_pred, good))
        _put(sigma, pvalid, _take(choice.sigma, good))
        if good.any():
            _put(th2k, pvalid, theorem2_margin(Sk if good.all() else Sk.take(good), _take(choice.sigma, good),
                                               d_max))
    fb = ~pvalid
    if fb.any():  # the fallback: sigma = 0, U = 0, the EKF's F Phi F^T + Q
        Pp[fb] = prediction_recursion(Pk[fb], F[fb], np.zeros((nx, nx)), model.process_cov, 0.0, design.epsilon)
    return xp, Pp, margin28, sigma, pvalid, th2k, limit


def update_nodes(model: Model, design: ConsensusDesign, groups, update_rule, k: int, xp, Pp, pvalid, s, innovation,
                 neigh, zk, degrees, nz: int, extra=None):
    """The update (7), (27), (29) of stacked nodes ``(a, n)``, per group of nodes of one sensor shape (``groups``:
    :class:`_Group`, their ``index`` into the n nodes, ``nodes`` their ids in the network): ``xp``, ``Pp`` the
    predictions, ``pvalid`` which are bounds, ``s`` how many packets each kept, ``innovation`` ``Σ_j (x̃_j - x̂⁻_i)``
    over them, ``neigh`` the neighbour terms of (27), ``zk`` (a, Σ dims of the groups' columns) the measurements.
    ``extra(group)`` gives a group's further items (a replayed schedule, the tuned rule's).  Returns
    ``(x, Φ, K, C, margin (29), β, which updates held (29), which nodes diverged, {(run, node): why}, [(nodes,
    weights, which held)] of the tuned rule)``."""
    a, n, nx = xp.shape
    xn = np.empty((a, n, nx))
    Pn = np.empty((a, n, nx, nx))
    Kn = np.zeros((a, n, nx, nz))
    Cn = np.empty((a, n, nx, nx))
    margin29 = np.full((a, n), np.nan)
    beta = np.full((a, n), np.nan)
    uvalid = np.zeros((a, n), dtype=bool)
    failed = np.zeros((a, n), dtype=bool)
    reasons: dict = {}  # (run, node) -> why its update failed
    weights = []
    rule, radius = design.linearization, design.radius
    for grp in groups:
        ns, at_g, g, dim = grp.nodes, grp.index, grp.nodes.size, grp.dim
        xg, Pg = xp[:, at_g], Pp[:, at_g]
        H = np.stack([model.H(int(i), xg[:, j], k + 1) for j, i in enumerate(ns)], axis=1)  # (a, g, dim, nx)
        hz = np.stack([model.h(int(i), xg[:, j], k + 1) for j, i in enumerate(ns)], axis=1)
        res = zk[:, grp.columns] - hz
        for j, i in enumerate(ns):
            res[:, j] = wrap_residuals(res[:, j], model.sensors[i].angles)
        vin = pvalid[:, at_g]
        V = np.array(np.broadcast_to(grp.V, (a, g, dim, dim)))
        if rule != "fixed":
            for j, i in enumerate(ns):
                sel = vin[:, j]
                if sel.any():
                    V[sel, j] = update_scaling(model, int(i), xg[sel, j], Pg[sel, j], k + 1, rule, radius,
                                               grp.V[j])[0]
        flat = dict(P=Pg, H=H, s=s[:, at_g], V=V, R=np.broadcast_to(grp.R, (a, g, dim, dim)),
                    d=np.broadcast_to(degrees[ns], (a, g)), nt=neigh[:, at_g])
        if extra is not None:
            flat.update(extra(grp))
        flat = {key: v.reshape((a * g,) + v.shape[2:]) for key, v in flat.items()}
        *out, gW, breakdowns = _update_items(flat, vin.reshape(-1), update_rule, grp.D, design)
        gm29, gbeta, gok, gK, gC, gP = (v.reshape((a, g) + v.shape[1:]) for v in out)
        if gW is not None:
            weights.append((ns, gW.reshape(a, g, -1), gok))
        x_g = xg + (gK @ res[..., None])[..., 0] + (gC @ innovation[:, at_g][..., None])[..., 0]
        fine = ~diverged_nodes(x_g, gP)
        for j, why in breakdowns.items():
            reasons[j // g, int(ns[j % g])] = why
        for r, j in zip(*np.nonzero(~fine)):
            reasons.setdefault((r, int(ns[j])), DIVERGED_REASON)
        failed[:, at_g] = ~fine
        xn[:, at_g], Pn[:, at_g], Cn[:, at_g] = x_g, gP, gC
        Kn[:, at_g, :, :dim] = gK
        margin29[:, at_g], beta[:, at_g], uvalid[:, at_g] = gm29, gbeta, gok
    return xn, Pn, Kn, Cn, margin29, beta, uvalid, failed, reasons, weights


def run_consensus_batch(model: Model, network: SensorNetwork | Sequence[SensorNetwork], z: np.ndarray,
                        design: ConsensusDesign, *, inputs=None,
                        attacks: EdgeAttacks | Sequence[AttackPattern] | None = None, x0=None,
                        phi0=None, gains: tuple[np.ndarray, np.ndarray] | None = None, runtime: str | None = None,
                        cov_kind: str = "bound", messages: int | None = None, covariances: bool = True,
                        predictions: bool = True, variances: bool = False) -> FilterResult:
    """Run the consensus filter at every node over many runs of measurements ``z`` (runs, steps, n_z).

    Parameters
    ----------
    model : the model (one sensor per node).
    network : SensorNetwork, or a sequence of them (one per run)
        The communication graph; one network per run gives each run its own channel probabilities (the
        statistics of its bounds and tuned weights) on one shared graph, e.g. the settings of a sweep.
    z : ndarray, shape (runs, steps, n_z)
        Stacked measurements of every run; ``z[r, k]`` measures ``x_{k+1}`` of run ``r``.
    design : ConsensusDesign
        Any gain rule with a filter (``design.rule.batch_filter()``), with or without a gate: a
        :class:`NodeRule` runs here, a function is handed the design.
    inputs : ndarray, shape (steps, n_u) or (runs, steps, n_u), optional
        Known inputs, shared by every run or one sequence per run.
    attacks : EdgeAttacks or sequence of AttackPattern (one per run), optional
        Realised channel attacks (none when omitted).
    x0, phi0 : initial estimate (n_x,) or (runs, n_x) and ``Φ_{0|0}`` (n_x, n_x) or (runs, n_x, n_x)
        (default: the prior's mean and covariance).
    gains : (K, C), optional
        Replay a fixed gain schedule in every run instead of computing the gains (any mode): ``K`` (steps', N,
        n_x, n_z') with node ``i``'s gain in its first ``n_z_i`` columns, ``C`` (steps', N, n_x, n_x), steps' >=
        steps.  Every node then runs the fallback recursion (no bound claimed, ``valid`` False throughout).
    runtime : str, optional
        What the filter needs at run time (:data:`designer.rule.FILTER_RUNTIMES`): by default the gain rule's
        (:attr:`designer.rule.GainRule.runtime`), ``'scheduled'`` for a replayed gain schedule.
    cov_kind : {'bound', 'covariance'}
        What Φ is: the design's bound (default), or the filter's own covariance (the design reduced to the EKF,
        σ = β = 0 and U = V = 0).
    messages : int, optional
        Transmissions per step (default: one per directed link of the network and exchange round, ``2 |E| rounds``
        with the design's rounds, one round for a replay; lost ones included).
    covariances : bool
        False: Φ, the predictions' Φ and the gains are kept at their latest step only (:data:`COVARIANCE_FIELDS`;
        the result's ``cov`` None, the estimates' numbers the same), what a study that scores a reference filter's
        estimates asks.  A gain rule with its own batch filter keeps them.
    predictions : bool
        False: the predictions' Φ and the gains are kept at their latest step only (None in the ``detail``), Φ
        over the steps kept: what a study that scores a designed filter's estimates and bounds asks (the rules'
        own batch filters take it too, :meth:`designer.rule.GainRule.batch_filter`).
    variances : bool
        True: Φ over the steps kept as its diagonals alone (``phi_variances``; the result's ``cov`` None and its
        ``cov_diagonal`` them, ``valid`` and the estimates the same), what a study that judges a designed filter's
        bounds by their traces asks (a rule's own batch filter that takes no ``variances`` keeps Φ whole).

    Returns
    -------
    FilterResult
        ``x_post``, Φ (``phi_post``, trusted where ``valid``), the violations, ``messages`` per step and the
        packets received (``gate_counts``' first column); ``detail`` the :class:`ConsensusBatchResult` of the runs
        (:meth:`ConsensusBatchResult.run` gives run ``r`` as a ``ConsensusResult``; a run alone,
        :func:`filters.consensus.run_consensus`, is a batch of one).

    Raises
    ------
    InputError
        For bad input, and when σ or β of a paper design violates (28)/(29) at the first step (the
        message names the bound, for the first run in batch order that violates it).
    """
    z, u, x0, phi0 = batch_inputs(model, z, inputs, x0, phi0)
    runs, steps = z.shape[:2]
    network, nets = run_networks(network, runs)
    design = validate_design(design, model, network)
    res = _consensus_runs(model, network, nets, z, u, x0, phi0, design, inputs, attacks, gains, covariances,
                          predictions, variances)
    return consensus_result(res, network, design, runtime=runtime, cov_kind=cov_kind, messages=messages,
                            replay=gains is not None)


def consensus_arrays(out: Mapping) -> ConsensusBatchResult:
    """The :class:`ConsensusBatchResult` of a run's records (:func:`result_arrays`): a record kept at its latest step
    only None (:func:`filters.engine.history`), Φ kept as its diagonals given as ``phi_variances``."""
    fields = {name: history(value) for name, value in out.items()}
    return ConsensusBatchResult(**{"phi_variances": None if fields.get("phi_post") is not None
                                   else diagonals(out["phi_post"]), **fields})


def consensus_result(detail: ConsensusBatchResult, network: SensorNetwork, design: ConsensusDesign, *,
                     runtime: str | None = None, cov_kind: str = "bound", messages: int | None = None,
                     replay: bool = False) -> FilterResult:
    """The :class:`filters.result.FilterResult` a consensus-family filter returns (:func:`run_consensus_batch`, a
    gain rule's own batch filter): ``x_post``, Φ (``phi_post``, trusted where ``valid``), the violations,
    ``messages`` per step (default: ``2 |E| rounds`` on ``network`` with the design's rounds, one for a ``replay``)
    and the packets received (``gate_counts``' first column); ``runtime`` by default the gain rule's
    (``'scheduled'`` for a replay); ``detail`` the runs' :class:`ConsensusBatchResult`."""
    runs, steps = detail.x_pred.shape[:2]
    if messages is None:
        messages = network.messages_per_step(1 if replay else design.rounds)
    if runtime is None:
        runtime = "scheduled" if replay else design.rule.runtime
    return FilterResult(detail.x_post, detail.phi_post, cov_kind, detail.valid, detail.violations,
                        constant_messages(runs, steps, messages), runtime,
                        delivered=None if detail.gate_counts is None else detail.gate_counts[..., 0],
                        detail=detail, carried=detail.carried, cov_diagonal=detail.phi_variances).check()


def _consensus_runs(model: Model, network: SensorNetwork, nets: list | None, z, u, x0, phi0, design: ConsensusDesign,
                    inputs, attacks, gains, covariances: bool = True,
                    predictions: bool = True, variances: bool = False) -> ConsensusBatchResult:
    """The runs of :func:`run_consensus_batch` (its inputs checked), as the family's arrays."""
    runs, steps = z.shape[:2]
    ex = Exchange(network)
    attacks = edge_attacks(network, attacks, runs, steps, model.n_x)
    filt = None if gains is not None else design.rule.batch_filter()
    if filt is not None and not isinstance(filt, NodeRule):
        # a rule's own filter may take no `predictions` (one written before it, outside the repository): it keeps them
        takes = inspect.signature(filt).parameters
        lean = {} if predictions or "predictions" not in takes else {"predictions": False}
        if variances and "variances" in takes:
            lean["variances"] = True
        return filt(model, network if nets is None else nets, z, design, inputs=inputs, attacks=attacks, x0=x0,
                    phi0=phi0, **lean).detail
    n, nx = network.n_nodes, model.n_x
    nz = max(model.sensor_dims)
    replay = gains is not None
    if replay:
        gains = _replay_gains(gains, steps, n, nx, nz)
    predict_rule, update_rule = (None, None) if replay else filt[:2]
    fixed = design.rule.fixed_multipliers  # the user's σ, β: wrong for the model if (28)/(29) fail at once
    degrees = network.degrees
    d_max = network.d_max
    eye = np.eye(nx)
    groups = node_groups(model, design)
    # Weights of the neighbour terms in (27), per channel: 3 (1 - phibar_ij); and 3 delta^2 sum_j gammabar_ij;
    # per run (1 item when every run has the same network)
    w_phi = per_run(lambda net: 3.0 * (1.0 - net.dos_prob[ex.receiver, ex.sender]), network, nets)
    w_xi = per_run(lambda net: 3.0 * design.delta**2 * (net.fdi_prob * net.adjacency).sum(axis=1), network, nets)
    weighted = not replay and filt.weighted
    if weighted:  # the weighted (27): one group slot per incoming channel (padded to d_max), then the FDI group
        slots = _channel_slots(ex, d_max)
        q_chan = per_run(lambda net: net.falsified_prob[ex.receiver, ex.sender], network, nets)
        W = np.full((runs, n, d_max + 2), np.nan)  # each node's weights at its last weighted update, by slot

    out = result_arrays(runs, steps, n, nx, nz, latest=(COVARIANCE_FIELDS if not covariances else
                                                        () if predictions else PREDICTION_FIELDS),
                        variances=variances)
    del out["predicted_mse"], out["gain_condition"]  # modes mse and scheduled only
    violations = out["violations"]
    proper = np.full((runs, n), not replay)  # a node still on Theorem 1's recursion (a replay claims no bound)
    out["x_post"][:, 0] = x0[:, None]
    out["phi_post"][:, 0] = phi0[:, None]
    out["valid"][:, 0] = not replay
    valid = out["valid"]

    def step(k, act, at):
        a = act.size
        xk, Pk, prop = out["x_post"][at, k], out["phi_post"][at, k], proper[at]
        uk = u[k] if u.ndim == 2 else u[at, k][:, None, :]
        xp, Pp, margin28, sigma, pvalid, th2k, limit = predict_nodes(model, design, predict_rule, k, xk, Pk, prop, uk,
                                                                     d_max)
        v28 = prop & ~pvalid
        pred_ok = pvalid & valid[at, k]
        # ---- the gate (design.gate > 0: x̃_j - x̂_i against 2 (Φ_i + Φ_j) >= its covariance) and the exchange
        if attacks is None:
            received, fdi, xi = np.ones((a, ex.receiver.size), dtype=bool), None, None
        else:
            received, fdi, xi = ~attacks.dos[at, k], attacks.fdi[at, k], attacks.xi[at, k]
        cov_diff = 2.0 * (Pp[:, ex.receiver] + Pp[:, ex.sender]) if design.gate else None
        recv, counts = gate_channels(xp, ex.receiver, ex.sender, received, fdi, xi, cov_diff, design.gate)
        s = ex.sum(recv.astype(float))
        innovation = ex.sum(recv[..., None] * channel_packets(xp[:, ex.sender], fdi, xi)) - s[..., None] * xp
        each = slice(None) if nets is None else at  # the runs' channel statistics
        neigh = ex.weighted_sum(w_phi[each], Pp) + w_xi[each][..., None, None] * eye

        def extra(grp):  # a group's items beyond the update's own: a replayed schedule's gains, the weighted weights'
            ns = grp.nodes
            if replay:
                return dict(Kr=np.broadcast_to(gains[0][k, ns, :, :grp.dim], (a, ns.size, nx, grp.dim)),
                            Cr=np.broadcast_to(gains[1][k, ns], (a, ns.size, nx, nx)))
            if weighted:
                return weighted_items(slots[ns], recv, Pp, ex.sender, q_chan[each], W[act[:, None], ns], design)
            return {}

        xn, Pn, Kn, Cn, margin29, beta, uvalid, failed, reasons, tuned_weights = update_nodes(
            model, design, groups, update_rule, k, xp, Pp, pvalid, s, innovation, neigh, z[at, k], degrees, nz, extra)
        for ns, gW, gok in tuned_weights:
            rr, jj = np.nonzero(gok)
            W[act[rr], ns[jj]] = gW[rr, jj]
        v29 = pvalid & ~uvalid
        # ---- divergence: a run stops at its first failing node (in node order)
        first = np.where(failed.any(axis=1), failed.argmax(axis=1), n)
        before = np.arange(n)[None, :] < first[:, None]
        v29 &= before
        margin29[~before], beta[~before] = np.nan, np.nan
        if k == 0 and fixed:  # sigma or beta is wrong for this model at the first step
            raising = np.flatnonzero(v28.any(axis=1) | v29.any(axis=1))
            if raising.size:
                r = int(raising[0])
                raise first_step_error(r, v28, v29, phi0[at], Pp, design)
        nb_bad = ex.sum((~pred_ok)[:, ex.sender].astype(float)) > 0
        proper[at] = prop & ~v28 & ~v29
        # ---- violations: theorem2 and (28) node by node, then (29) (the loop adds divergence)
        rr, ii = np.nonzero((th2k < 0) | v28)
        for r, i, t2, c28, mg, lim in zip(act[rr].tolist(), ii.tolist(), th2k[rr, ii].tolist(), v28[rr, ii].tolist(),
                                          margin28[rr, ii].tolist(), limit[rr, ii].tolist()):
            vs = violations[r]
            if t2 < 0:
                vs.append({"node": i, "step": k, "condition": "theorem2", "margin": t2})
            if c28:
                vs.append({"node": i, "step": k, "condition": "(28)", "margin": mg, **({"reason": LIMIT_REASON}
                                                                                     if lim else {})})
        rr, ii = np.nonzero(v29)
        for r, i, mg in zip(act[rr].tolist(), ii.tolist(), margin29[rr, ii].tolist()):
            violations[r].append({"node": i, "step": k + 1, "condition": "(29)", "margin": mg})
        return Step(dict(x_pred=xp, phi_pred=Pp, margin28=margin28, sigma=sigma, theorem2=th2k, K=Kn, C=Cn,
                         margin29=margin29, beta=beta, gate_counts=counts),
                    dict(x_post=xn, phi_post=Pn, valid=uvalid & pred_ok & ~nb_bad), failed,
                    lambda r, node: reasons[r, node])

    act = run_batch(step, out, violations, steps, nan_from=("x_post", "phi_post"), nan_before=("K", "C"),
                    invalid_from=("valid",))
    # Phi_{K|K} against the last sigma each node used
    at = slice(None) if act.size == runs else act
    last = valid[at, steps]
    if last.any():
        th = np.full(last.shape, np.nan)
        th[last] = theorem2_margin(out["phi_post"][at, steps][last], out["sigma"][at, steps - 1][last], d_max)
        out["theorem2"][at, steps] = th
        rr, ii = np.nonzero(th < 0)
        for r, i, mg in zip(act[rr].tolist(), ii.tolist(), th[rr, ii].tolist()):
            violations[r].append({"node": i, "step": steps, "condition": "theorem2", "margin": mg})
    return consensus_arrays(out)


def _channel_slots(ex: Exchange, d_max: int) -> np.ndarray:
    """``(N, d_max)``: node i's incoming channels in sender order, -1 beyond."""
    deg = np.bincount(ex.receiver, minlength=ex.n)
    first = np.cumsum(deg) - deg
    j = np.arange(d_max)
    return np.where(j[None] < deg[:, None], first[:, None] + j[None], -1)


def weighted_items(slots, recv, Pp, sender, q_chan, previous, design: ConsensusDesign) -> dict:
    """The tuned rule's items for nodes with channel ``slots`` (g, d_max), all runs (a; ``q_chan`` (a or 1, E) the
    channels' probabilities that a received packet is falsified): the groups of the weighted
    (27) from the received neighbours' Φ_pred (:func:`designer.tuning.neighbour_group_stack`), which are present,
    and the warm start from each node's ``previous`` weights (a, g, d_max + 2) by slot."""
    a, g = recv.shape[0], slots.shape[0]
    chan = np.maximum(slots, 0)
    present = recv[:, chan] & (slots >= 0)  # (a, g, d_max)
    nb = Pp[:, sender[chan]]  # (a, g, d_max, n, n)
    flat = (a * g,)
    groups, mask = neighbour_group_stack(nb.reshape(flat + nb.shape[2:]), np.broadcast_to(q_chan[:, chan], present.shape)
                                         .reshape(flat + present.shape[2:]), present.reshape(flat + present.shape[2:]),
                                         design.delta, span=design.fdi_span)
    full = np.concatenate([np.ones(flat + (1,), dtype=bool), mask], axis=1)
    w0 = warm_start_weights(previous.reshape(flat + previous.shape[2:]), full)
    return {"groups": groups.reshape((a, g) + groups.shape[1:]), "present": mask.reshape(a, g, -1),
            "w0": w0.reshape(a, g, -1)}


def _update_items(it: dict, vin: np.ndarray, update_rule, D, design: ConsensusDesign):
    """The update of stacked items (one run and node each): the mode's rule where the prediction is a
    bound and (29) holds, the fallback elsewhere (and, mode tuned, the weights of the items whose rule
    held; NaN elsewhere: they keep their previous weights).  A numerical breakdown (``LinAlgError``) is searched
    item by item; those items get NaN outputs and a reason (``{item: reason}``)."""
    m, nx = it["P"].shape[:2]
    dim = it["H"].shape[-2]
    margin = np.full(m, np.nan)
    beta = np.full(m, np.nan)
    ok = np.zeros(m, dtype=bool)
    K = np.full((m, nx, dim), np.nan)
    C = np.full((m, nx, nx), np.nan)
    P = np.full((m, nx, nx), np.nan)
    weights = np.full((m,) + it["w0"].shape[1:], np.nan) if "w0" in it else None
    breakdowns: dict[int, str] = {}

    def compute(idx):
        rows = idx[vin[idx]]
        if rows.size:
            every = rows.size == m  # no copies when every item is inside
            sub = {key: v if every else v[rows] for key, v in it.items() if key != "P"}
            ch = update_rule(spectrum(it["P"] if every else it["P"][rows]), sub, D, design)
            good = ch.margin29 > 0
            margin[rows] = ch.margin29
            rows = rows[good]
            ok[rows], beta[rows] = True, ch.beta[good]
            K[rows], C[rows], P[rows] = ch.K[good], ch.C[good], ch.phi_post[good]
            if ch.weights is not None:
                weights[rows] = ch.weights[good]
        rest = idx[~ok[idx]]
        if rest.size:
            K[rest], C[rest], P[rest] = _fallback_update(*(it[key][rest] for key in ("P", "H", "s", "R", "nt")),
                                                         design.tau, *((it["Kr"][rest], it["Cr"][rest])
                                                                       if "Kr" in it else ()))

    try:
        compute(np.arange(m))
    except np.linalg.LinAlgError:
        for j in range(m):
            try:
                compute(np.array([j]))
            except np.linalg.LinAlgError as exc:
                breakdowns[j] = f"numerical breakdown: {exc}"
                K[j], C[j], P[j] = np.nan, np.nan, np.nan
    return margin, beta, ok, K, C, P, weights, breakdowns
