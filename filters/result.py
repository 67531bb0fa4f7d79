"""One result type for every filter family: :class:`FilterResult`, batched over Monte Carlo runs.

Every batched filter returns it; what is its family's alone is the one field ``detail``:

* the consensus EKF (every gain rule, a replayed gain schedule, the design reduced to the EKF at a fusion
  centre): :func:`filters.consensus_batch.run_consensus_batch` — ``cov`` is the bound Φ (``cov_kind = "bound"``;
  ``"covariance"`` for the design reduced to the EKF), ``valid`` where it is one; ``detail`` a
  :class:`filters.consensus_batch.ConsensusBatchResult` (the predictions, the gains K and C, σ, β, the margins of
  (28), (29) and Theorem 2, the gate counts; mse's predicted MSE and gain condition; ``detail.run(r)`` a run alone);
* the literature's distributed filters (KCF, HCMCI), the local EKFs (every node alone) and the relay filter:
  :func:`filters.distributed.run_kcf_batch`, :func:`~filters.distributed.run_hcmci_batch`,
  :func:`~filters.distributed.run_local_batch`, :func:`rules.relay.filter.run_relay_batch` (each through
  :func:`filters.distributed.distributed_result`) — ``cov`` is each node's own covariance P (``"covariance"``),
  ``messages`` and ``delivered`` as the filter counted them (the local EKFs none); ``detail`` a
  :class:`filters.distributed.DistributedBatchResult` (the predictions, the rounds, HCMCI's ω; ``detail.run(r)`` a
  run alone);
* the centralized EKF, :func:`filters.ekf.run_ekf_batch`, and the particle filters,
  :func:`filters.particle.run_sir` — one estimate, so ``nodes = 1`` (the fusion centre,
  :func:`centralized_result`), ``cov`` the filter's covariance (the particles' weighted one); ``detail`` a
  :class:`filters.ekf.EKFResult` (x, P) or a :class:`filters.particle.SIRResult` (ESS, log-likelihood, the
  steps resampled, collapsed or skipped);
* the fused particle filters, :func:`filters.fused.sir_packets`, :func:`~filters.fused.sir_binary` and
  :func:`~filters.fused.sir_edpf` — a fusion centre as well, but ``cov`` is None unless they were asked for it
  (``covariance=True``: the kernels compute no covariance by default, and none is made up); ``valid`` then says
  where the estimate is finite; ``detail`` a :class:`filters.fused.FastSIRResult` (their own arrays).

``cov`` is None only where a family computes no covariance: a consumer that needs one (a bound's verdict, a
trace, the energy ratio) checks for it; :attr:`FilterResult.trace` is then None.

A filter takes what its result must say and its family cannot know itself (e.g. the runtime of a consensus
filter run for the centralized EKF, the uplinks of a fusion centre) as parameters.

Messages are counted as the studies' contract counts them (``messages_per_step`` /
``communications``): transmissions attempted per step, a packet lost to DoS included; one per
directed link and consensus round for the networked filters (``2 |E| L``), one uplink per sensor
for a fusion centre, none for isolated nodes.

A run that stopped (``diverged``) carries a ``'diverged'`` violation ``{node, step, condition,
margin, reason}`` and its arrays are NaN from that step on: :func:`stop_diverged` is that bookkeeping
for the batched filters (the consensus EKF of every mode), :func:`diverged_nodes` the test they
share, :data:`DIVERGED` the estimate beyond which a run stops (every filter) and :data:`HARD_CONDITIONS` the
violations that make a design infeasible.  The centralized filters report a run as diverged at the
first step whose estimate is not finite (:func:`nonfinite_violations`).
"""
from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import numpy as np

from designer.rule import FILTER_RUNTIMES
from designer.validation import InputError

__all__ = ["FilterResult", "COV_KINDS", "nonfinite_violations", "constant_messages", "centralized_result",
           "diverged_nodes", "stop_diverged", "DIVERGED", "DIVERGED_REASON", "HARD_CONDITIONS"]

DIVERGED = 1e12  # an estimate this large has left any physical meaning: stop, do not propagate (every filter)
HARD_CONDITIONS = ("(28)", "(29)", "diverged")  # violations of these conditions make a design infeasible

COV_KINDS = ("bound", "covariance")  # what ``FilterResult.cov`` is: a designed bound Φ, or the filter's own P
DIVERGED_REASON = f"estimate or covariance beyond {DIVERGED:g} or not finite"


class FilterResult(NamedTuple):
    """Runs of one filter, whatever its family.

    ``x`` (runs, steps + 1, nodes, n_x): every node's estimate, ``x[:, 0]`` the initial one (a
    centralized filter has one node: the fusion centre).  ``cov`` (runs, steps + 1, nodes, n_x, n_x):
    the covariance the filter believes (``cov_kind == "covariance"``) or the bound it certifies
    (``"bound"``), trusted where ``valid`` (runs, steps + 1, nodes); None for a filter run without one (the
    fused particle filters by default; ``valid`` then marks the finite estimates).  ``violations``: per run, the list
    of ``{node, step, condition, margin[, reason]}`` (design conditions of the consensus filters, and
    ``'diverged'`` where the run stopped).  ``messages`` (runs, steps): transmissions attempted per
    step; ``delivered`` (runs, steps): those that arrived, where the family counts them (else None).
    ``runtime``: what the filter needs at run time (:data:`designer.rule.FILTER_RUNTIMES`).
    ``detail``: the family's own result (gains, margins, packet counts), for what is the family's
    alone.  ``seconds`` (runs,): wall time per run, where the caller measured it.  ``ess`` (runs, steps): a particle
    filter's effective sample size after each step's weighting (None for a filter without weights).
    ``cov_diagonal`` (runs, steps + 1, nodes, m): ``cov``'s diagonal, where the filter kept that alone (``cov`` then
    None: :meth:`variance`).  ``carried``
    (nodes, m): when each node carries only some states (:mod:`designer.regions`, a regional rule's design), their
    indices (``-1``: a place not used); ``cov`` is then (runs, steps + 1, nodes, m, m) in those coordinates (zero in
    the unused places) and ``x`` NaN at the states a node does not carry.
    """

    x: np.ndarray
    cov: np.ndarray | None
    cov_kind: str
    valid: np.ndarray
    violations: list
    messages: np.ndarray
    runtime: str
    delivered: np.ndarray | None = None
    detail: Any = None
    seconds: np.ndarray | None = None
    carried: np.ndarray | None = None
    ess: np.ndarray | None = None
    cov_diagonal: np.ndarray | None = None

    def variance(self) -> np.ndarray | None:
        """(runs, steps + 1, nodes, m): the diagonal of ``cov`` over the steps, or the filter's own record of it
        where it kept its covariance's diagonal alone (``cov_diagonal``, ``cov`` None: what a study that judges a
        bound by its trace asks); None without either."""
        if self.cov_diagonal is not None:
            return self.cov_diagonal
        return None if self.cov is None else np.diagonal(self.cov, axis1=-2, axis2=-1)

    def check(self) -> "FilterResult":
        """This result, its shapes and kinds checked (``InputError`` naming the field)."""
        if self.x.ndim != 4:
            raise InputError(f"x must have shape (runs, steps + 1, nodes, n_x), got {self.x.shape}")
        runs, k1, nodes, nx = self.x.shape
        m = nx
        if self.carried is not None:
            if self.carried.ndim != 2 or self.carried.shape[0] != nodes or not np.all(self.carried < nx):
                raise InputError(f"carried must have shape ({nodes}, m) with state indices below {nx} (-1: unused), "
                                 f"got {self.carried.shape}")
            m = self.carried.shape[1]
        if self.cov is not None and self.cov.shape != (runs, k1, nodes, m, m):
            raise InputError(f"cov must have shape {(runs, k1, nodes, m, m)}, got {self.cov.shape}")
        if self.cov_diagonal is not None and self.cov_diagonal.shape != (runs, k1, nodes, m):
            raise InputError(f"cov_diagonal must have shape {(runs, k1, nodes, m)}, got {self.cov_diagonal.shape}")
        if self.cov_kind not in COV_KINDS:
            raise InputError(f"cov_kind must be one of {', '.join(COV_KINDS)}, got {self.cov_kind!r}")
        if self.valid.shape != (runs, k1, nodes):
            raise InputError(f"valid must have shape {(runs, k1, nodes)}, got {self.valid.shape}")
        if len(self.violations) != runs:
            raise InputError(f"violations must hold one list per run ({runs}), got {len(self.violations)}")
        for name in ("messages", "delivered", "ess"):
            a = getattr(self, name)
            if a is not None and a.shape != (runs, k1 - 1):
                raise InputError(f"{name} must have shape {(runs, k1 - 1)}, got {a.shape}")
        if self.runtime not in FILTER_RUNTIMES:
            raise InputError(f"runtime must be one of {', '.join(FILTER_RUNTIMES)}, got {self.runtime!r}")
        return self

    @property
    def runs(self) -> int:
        return self.x.shape[0]

    @property
    def steps(self) -> int:
        return self.x.shape[1] - 1

    @property
    def nodes(self) -> int:
        return self.x.shape[2]

    @property
    def trace(self) -> np.ndarray | None:
        """(runs, steps + 1, nodes): tr of ``cov`` (the bound's or the covariance's, as ``cov_kind`` says); None
        without ``cov``."""
        return None if self.cov is None else np.trace(self.cov, axis1=-2, axis2=-1)

    @property
    def diverged(self) -> list:
        """Per run, its ``'diverged'`` violation (``node``, ``step``, ``reason``) or None."""
        return [next((v for v in vs if v["condition"] == "diverged"), None) for vs in self.violations]

    @property
    def diverged_step(self) -> np.ndarray:
        """(runs,) the step where each run stopped, -1 for a run that did not."""
        return np.array([-1 if d is None else int(d["step"]) for d in self.diverged], dtype=np.int64)

    def row(self, r: int | Sequence[int] | slice) -> "FilterResult":
        """The runs ``r`` (an index, indices or a slice) as a result of their own."""
        idx = np.atleast_1d(np.arange(self.runs)[r])
        pick = (lambda a: None if a is None else a[idx])  # noqa: E731
        return self._replace(x=self.x[idx], cov=pick(self.cov), valid=self.valid[idx],
                             violations=[self.violations[i] for i in idx], messages=self.messages[idx],
                             delivered=pick(self.delivered), seconds=pick(self.seconds), ess=pick(self.ess))


def constant_messages(runs: int, steps: int, per_step: int) -> np.ndarray:
    """(runs, steps) ``per_step`` transmissions at every step (attempted, whether or not they arrive)."""
    return np.full((runs, steps), int(per_step), dtype=np.int64)


def nonfinite_violations(x: np.ndarray) -> list:
    """Per run of ``x`` (runs, steps + 1, ...): ``[]``, or the ``'diverged'`` violation at the first step whose
    estimate is not finite (a centralized filter: node 0)."""
    bad = ~np.isfinite(x.reshape(x.shape[0], x.shape[1], -1)).all(axis=-1)  # (runs, steps + 1)
    return [[] if not b.any() else [{"node": 0, "step": int(np.argmax(b)), "condition": "diverged",
                                     "margin": -np.inf, "reason": "the estimate left finite numbers"}]
            for b in bad]



def centralized_result(x: np.ndarray, cov: np.ndarray | None, uplinks: int, detail: Any = None) -> FilterResult:
    """A fusion centre's runs, ``x`` (runs, steps + 1, n_x) and its covariance ``cov`` (runs, steps + 1, n_x, n_x)
    or None (a filter run without one), as a :class:`FilterResult` of one node: ``uplinks`` messages per step (one
    per sensor), valid where the covariance (without one: the estimate) is finite, diverged at the first step whose
    estimate is not finite, runtime ``centralized``."""
    runs, k1 = x.shape[:2]
    valid = np.isfinite(x).all(axis=-1) if cov is None else np.isfinite(cov).all(axis=(-2, -1))
    return FilterResult(x[:, :, None], None if cov is None else cov[:, :, None], "covariance", valid[:, :, None],
                        nonfinite_violations(x), constant_messages(runs, k1 - 1, uplinks), "centralized",
                        detail=detail).check()


def diverged_nodes(x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``(..., N)`` True where a node's estimate ``x`` (..., N, n_x) or covariance ``P`` (..., N, n_x, n_x) left
    finite numbers or an estimate reached :data:`DIVERGED` (the run must stop there)."""
    return ~(np.isfinite(x).all(axis=-1) & np.isfinite(P).all(axis=(-2, -1)) & (np.abs(x).max(axis=-1) < DIVERGED))


def stop_diverged(violations: list, active: np.ndarray, bad: np.ndarray, step: int, reason=DIVERGED_REASON, *,
                  nan_from: Sequence[np.ndarray] = (), nan_before: Sequence[np.ndarray] = (),
                  invalid_from: Sequence[np.ndarray] = ()) -> np.ndarray:
    """Stop the runs of a batch that diverged at ``step``, as :func:`filters.consensus.run_consensus` stops a run.

    ``active`` (a,): the batch's run indices still going; ``bad`` (a, N): which of their nodes failed at ``step``
    (e.g. :func:`diverged_nodes`).  A run with a failed node stops at its first one (in node order): appends to
    ``violations[run]`` ``{node, step, condition: 'diverged', margin: -inf, reason}`` (``reason`` a string, or
    ``reason(j, node)`` for position ``j`` of ``active``), sets ``a[run, step:]`` to NaN for every array of
    ``nan_from`` (indexed by the step of a posterior, 0..K), ``a[run, step - 1]`` to NaN for every array of
    ``nan_before`` (indexed by the step of the update, 0..K-1: gains) and ``b[run, step:]`` to False for every
    array of ``invalid_from``.  Returns the (a,) mask of the runs that go on.
    """
    dead = np.flatnonzero(bad.any(axis=-1))
    for j in dead.tolist():
        g, node = int(active[j]), int(np.argmax(bad[j]))
        violations[g].append({"node": node, "step": step, "condition": "diverged", "margin": -np.inf,
                              "reason": reason if isinstance(reason, str) else reason(j, node)})
        for a in nan_from:
            a[g, step:] = np.nan
        for a in nan_before:
            a[g, step - 1] = np.nan
        for b in invalid_from:
            b[g, step:] = False
    going = np.ones(bad.shape[0], dtype=bool)
    going[dead] = False
    return going
