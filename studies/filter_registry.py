"""The filters a study compares, as a registry: one entry per filter, each returning a
:class:`filters.result.FilterResult`.

An entry (:class:`FilterEntry`) names the filter as the report labels it (the key of ``results.json``'s
``filters``: a contract), its family, what it needs at run time (``runtime``, of
:data:`designer.rule.FILTER_RUNTIMES`; a designed consensus filter takes its gain rule's), a
description, what it needs from the study (a design of a gain rule, particles) and ``run(batch, settings,
design)``, which runs it on every run of a :class:`Batch` at the given settings at once.  A study iterates
over a :class:`FilterRegistry`: a new filter is one entry (``registry.register(entry)``), nothing else.

Every filter returns its :class:`filters.result.FilterResult` itself (its family's arrays in ``detail``), so an
entry's ``run`` is a call of its filter on the batch's rows and nothing else: no conversion happens here.  The
entries of the project's filter families are made by the factories below: :func:`designed_consensus` (the
consensus EKF with a design of a gain rule), :func:`local_ekfs` (every node alone: an EKF on its sensor),
:func:`replayed_schedule` (a gain schedule replayed), :func:`kcf` and :func:`hcmci` (the literature's distributed
filters), :func:`centralized_consensus_ekf`, :func:`centralized_ekf` and :func:`particle_filters` (a fusion centre
receiving every uplink).  The registry lives in ``studies`` (not in
``filters``) because a designed entry needs a design made by :mod:`studies.consensus_design`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Iterator, NamedTuple, Sequence

import numpy as np

import rules
from designer.design import ConsensusDesign
from designer.rule import FILTER_RUNTIMES
from designer.network import SensorNetwork
from designer.validation import InputError
from filters.consensus_batch import EdgeAttacks, run_consensus_batch
from filters.distributed import (HCMCINetwork, KCFNetwork, LocalEKFNetwork, hcmci_payload, kcf_payload, run_hcmci_batch,
                                 run_kcf_batch, run_local_batch)
from filters.ekf import run_ekf_batch
from filters.node import node_network
from filters.particle import run_sir
from filters.result import FilterResult
from filters.uplink import fdi_covariances, split_received, uplink_loglik

from .pipeline import naming_filter

__all__ = ["Batch", "FilterEntry", "FilterRegistry", "designed_consensus", "local_ekfs", "kcf", "hcmci",
           "centralized_ekf", "particle_filters", "centralized_consensus_ekf", "replayed_schedule", "local_ekf_design",
           "FAMILIES"]

FAMILIES = ("consensus", "local", "EKF", "particle", "centralized")  # the families a study reports


@dataclass(frozen=True, eq=False)
class Batch:
    """Every filter's input on a chunk of Monte Carlo runs at a study's settings (common random numbers).

    ``scenarios``: one per setting (the same model and graph; the channels' and uplinks' probabilities
    of that setting), the main setting first.  ``z`` (runs, K, n_z) and ``inputs`` (runs, K, n_u) or
    None: each run's measurements and known inputs (the same at every setting).  ``attacks[j][a]``:
    run ``a``'s realised channel attacks at setting ``j`` (:class:`filters.attacks.AttackPattern`), or
    ``attacks[j]`` the runs' :class:`filters.consensus_batch.EdgeAttacks` (on the channels alone: a dense pattern is
    0.8 GB a run on a 118-node grid);
    ``received[j][a]`` (K, n_z): what run ``a``'s uplinks delivered to a fusion centre at setting ``j``
    (NaN where lost; None when the study has no uplinks).  ``particle_seeds[a]``: the SeedSequence of
    run ``a``'s particle filters; ``particles`` their number; ``iterations``: consensus rounds per step
    of the filters that take them (HCMCI's L); ``per_row_networks``: a designed filter gets one network per row
(its setting's channel probabilities), or the main one for all rows (False); ``covariances``: False where the study
scores the estimates of the filters that are not designed and nothing else of them (KCF, HCMCI, the local and the
centralized EKF then keep no covariance over the steps: ``cov`` None, the same estimates), and of a designed filter
its estimates and bounds (it keeps Φ, not its predictions' Φ nor its gains); ``variances``: a designed filter keeps
Φ's diagonals over the steps alone (``cov_diagonal``, ``cov`` None), where the study judges its bounds by their
traces (the comparison), not by the errors they whiten.  A filter run on settings
``js`` returns rows in
    setting-major order, row ``i R + a`` for setting ``js[i]`` and run ``a``.  ``cache`` holds results
    that several entries share (the particle filters run as one batch).
    """

    scenarios: tuple
    z: np.ndarray
    inputs: np.ndarray | None
    attacks: tuple
    received: tuple | None = None
    particle_seeds: tuple | None = None
    particles: int | None = None
    iterations: int = 1
    run_ids: tuple = ()
    per_row_networks: bool = True
    covariances: bool = True
    variances: bool = False
    cache: dict = field(default_factory=dict)

    @property
    def runs(self) -> int:
        return int(self.z.shape[0])

    @property
    def model(self):
        return self.scenarios[0].model

    @property
    def network(self) -> SensorNetwork:
        return self.scenarios[0].network

    def z_rows(self, js: Sequence[int]) -> np.ndarray:
        return np.concatenate([self.z] * len(js))

    def input_rows(self, js: Sequence[int]) -> np.ndarray | None:
        return None if self.inputs is None else np.concatenate([self.inputs] * len(js))

    def attack_rows(self, js: Sequence[int]) -> list | EdgeAttacks:
        """The rows' attacks: one AttackPattern per row, or where ``attacks[j]`` is the runs'
        :class:`filters.consensus_batch.EdgeAttacks` (on the channels alone) theirs, setting after setting."""
        if isinstance(self.attacks[js[0]], EdgeAttacks):
            parts = [self.attacks[j] for j in js]
            return parts[0] if len(parts) == 1 else parts[0]._replace(
                **{f: np.concatenate([getattr(p, f) for p in parts]) for f in ("dos", "fdi", "xi")})
        return [self.attacks[j][a] for j in js for a in range(self.runs)]

    def network_rows(self, js: Sequence[int]) -> SensorNetwork | list[SensorNetwork]:
        if not self.per_row_networks:
            return self.network
        return [self.scenarios[j].network for j in js for _ in range(self.runs)]


class FilterEntry(NamedTuple):
    """A filter of a study: its label, family, run time, description, needs and how to run it.

    ``run(batch, js, design)`` runs the filter on every run of ``batch`` at the settings ``js`` and
    returns their :class:`FilterResult` (rows setting-major); ``design`` is the design it runs with, for an
    entry with a ``mode``: :meth:`design_for` of the design of gain rule ``mode`` at that setting (None for
    an entry without).  ``messages(network,
    iterations)``: transmissions per step as the contract counts them (known before any run, also for a
    filter that is not run).  ``designed``: it reports a design's conditions and bound verdicts;
    ``start_check``: its fixed σ, β may break (28)/(29) at the first step, where it is reported as not
    run (:func:`studies.consensus_design.check_first_step`); ``attacked``: False for a filter that uses no
    channel (the same numbers at every setting: run once, at the main one); ``counts_delivered``: the study
    reports the packets it received; ``rounds``: it runs ``iterations`` consensus rounds per step;
    ``particles``: it needs the study's particles; ``node_filters(model, network, design, iterations)``: its node
    filters, every node of the network to drive a step at a time (:mod:`filters.node`; None: it has none);
    ``payload(model, network, iterations)``: the numbers it sends per step (what its messages carry; None: not
    counted here: a designed filter's is its gain rule's, :meth:`designer.rule.GainRule.payload`).
    """

    name: str
    family: str
    runtime: str
    description: str
    run: Callable[[Batch, Sequence[int], ConsensusDesign | None], FilterResult]
    messages: Callable[[SensorNetwork, int], int]
    mode: str | None = None
    designed: bool = False
    start_check: bool = False
    attacked: bool = True
    counts_delivered: bool = False
    rounds: bool = False
    particles: bool = False
    derive: Callable | None = None
    node_filters: Callable | None = None
    payload: Callable | None = None  # (model, network, iterations) -> numbers sent per step (None: not counted)

    def design_for(self, design: ConsensusDesign, model) -> ConsensusDesign:
        """The design it runs with, from the design of its gain rule ``mode`` (``derive(design, model)``: e.g. the
        paper design reduced to the EKF; the design itself when it derives none)."""
        return design if self.derive is None else self.derive(design, model)

    def messages_per_step(self, network: SensorNetwork, iterations: int, options=None) -> int:
        """Transmissions per step on ``network``: ``messages(network, L)`` with ``L`` the study's consensus rounds
        ``iterations`` (HCMCI), or for a designed filter its design's exchange rounds (``rounds`` of the study's
        design ``options``, :class:`designer.design.DesignOptions`, as its gain rule takes them)."""
        if self.designed and options is not None:
            from .design_options import as_mode

            return int(self.messages(network, rules.get(self.mode).rounds(network, as_mode(options, self.mode).rounds)))
        return int(self.messages(network, iterations))

    def nodes(self, network: SensorNetwork) -> int:
        """How many estimates it keeps on ``network``: one at a fusion centre, one per node otherwise."""
        return 1 if self.runtime == "centralized" else int(network.n_nodes)

    def check(self) -> "FilterEntry":
        if not self.name:
            raise InputError("a filter's name must not be empty")
        if self.family not in FAMILIES:
            raise InputError(f"family must be one of {', '.join(FAMILIES)}, got {self.family!r}")
        if self.runtime not in FILTER_RUNTIMES:
            raise InputError(f"runtime must be one of {', '.join(FILTER_RUNTIMES)}, got {self.runtime!r}")
        if (self.designed or self.start_check) and self.mode is None:
            raise InputError(f"filter {self.name!r}: a designed filter needs the gain rule (mode) of its design")
        if self.mode is not None:
            rules.get(self.mode)
        return self


class FilterRegistry:
    """An ordered registry of :class:`FilterEntry` by name (the order of a study's arrays and tables)."""

    def __init__(self, entries: Sequence[FilterEntry] = ()):
        self._entries: dict[str, FilterEntry] = {}
        for e in entries:
            self.register(e)

    def register(self, entry: FilterEntry) -> FilterEntry:
        """Add ``entry`` (its name must be new); returns it."""
        entry.check()
        if entry.name in self._entries:
            raise InputError(f"a filter named {entry.name!r} is registered already")
        self._entries[entry.name] = entry
        return entry

    def unregister(self, name: str) -> FilterEntry:
        if name not in self._entries:
            raise InputError(f"no filter named {name!r}; registered: {', '.join(self._entries)}")
        return self._entries.pop(name)

    def __getitem__(self, name: str) -> FilterEntry:
        return self._entries[name]

    def __contains__(self, name: str) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[FilterEntry]:
        return iter(list(self._entries.values()))

    def __len__(self) -> int:
        return len(self._entries)

    def names(self) -> tuple[str, ...]:
        return tuple(self._entries)


def local_ekf_design(design):
    """The consensus design reduced to the EKF: σ = β = τ = 0, U = V = 0 (used with an isolated network)."""
    return design._replace(sigma=0.0, beta=0.0, tau=0.0, U=np.zeros_like(design.U),
                           V=tuple(np.zeros_like(v) for v in design.V), epsilon=0.5, rule=rules.get(rules.PUBLISHED),
                           linearization="fixed")


def _links(network: SensorNetwork, iterations: int) -> int:
    return network.messages_per_step()


def _links_per_round(network: SensorNetwork, rounds: int) -> int:
    return network.messages_per_step(rounds)


def _uplinks(network: SensorNetwork, iterations: int) -> int:
    return int(network.n_nodes)


def designed_consensus(name: str, mode: str, description: str, *, start_check: bool = False) -> FilterEntry:
    """The consensus EKF with the design of gain rule ``mode`` at each setting, on the network's attacked
    channels (each row with its setting's network: the channels' probabilities its design and gains use)."""

    def run(batch: Batch, js: Sequence[int], design: ConsensusDesign | None) -> FilterResult:
        return run_consensus_batch(batch.model, batch.network_rows(js), batch.z_rows(js), design,
                                   attacks=batch.attack_rows(js), inputs=batch.input_rows(js),
                                   predictions=batch.covariances, variances=batch.variances)

    return FilterEntry(name, "consensus", rules.get(mode).runtime, description, run,
                       _links_per_round, mode=mode, designed=True,
                       start_check=start_check,
                       node_filters=lambda model, network, design, iterations: node_network(model, network, design))


def local_ekfs(name: str, description: str) -> FilterEntry:
    """An EKF at every node on its own sensor (:func:`filters.distributed.run_local_batch`: every node alone); nothing
    to attack, no message, no design."""

    def run(batch: Batch, js: Sequence[int], design) -> FilterResult:
        return run_local_batch(batch.model, batch.z_rows(js), inputs=batch.input_rows(js),
                               covariances=batch.covariances)

    return FilterEntry(name, "local", "local", description, run, lambda net, L: 0, attacked=False,
                       node_filters=lambda model, network, design, iterations: LocalEKFNetwork(model),
                       payload=lambda model, network, iterations: 0)


def kcf(name: str, description: str) -> FilterEntry:
    """Olfati-Saber's Kalman consensus filter (:func:`filters.distributed.run_kcf_batch`) on the attacked channels
    (the realised attacks only: the channels' probabilities are not its to know)."""

    def run(batch: Batch, js: Sequence[int], design) -> FilterResult:
        return run_kcf_batch(batch.model, batch.network, batch.z_rows(js), inputs=batch.input_rows(js),
                             attacks=batch.attack_rows(js), covariances=batch.covariances)

    return FilterEntry(name, "consensus", "local", description, run, _links, counts_delivered=True,
                       node_filters=lambda model, network, design, iterations: KCFNetwork(model, network),
                       payload=lambda model, network, iterations: kcf_payload(model.n_x, network, model.sensor_dims))


def hcmci(name: str, description: str) -> FilterEntry:
    """Battistelli et al.'s HCMCI (:func:`filters.distributed.run_hcmci_batch`) with ``batch.iterations`` rounds
    per step on the attacked channels; ``2 |E| L`` messages per step."""

    def run(batch: Batch, js: Sequence[int], design) -> FilterResult:
        return run_hcmci_batch(batch.model, batch.network, batch.z_rows(js), inputs=batch.input_rows(js),
                               attacks=batch.attack_rows(js), iterations=batch.iterations,
                               covariances=batch.covariances)

    return FilterEntry(name, "consensus", "local", description, run, _links_per_round, counts_delivered=True,
                       rounds=True,
                       node_filters=lambda model, network, design, iterations: HCMCINetwork(model, network,
                                                                                           iterations=iterations),
                       payload=lambda model, network, iterations: hcmci_payload(model.n_x, network, iterations))


def centralized_consensus_ekf(name: str, description: str) -> FilterEntry:
    """One filter at a fusion centre receiving every sensor's measurement (unattacked): the consensus filter of the
    paper design reduced to the EKF (:func:`local_ekf_design`) on the model with its sensors stacked
    (:meth:`designer.model.Model.with_stacked_sensors`, Gaussian sensor noises only) as one node; one uplink per
    sensor and step."""

    def run(batch: Batch, js: Sequence[int], design: ConsensusDesign | None) -> FilterResult:
        centre = SensorNetwork(1, np.zeros((1, 1), int))
        return run_consensus_batch(batch.model.with_stacked_sensors(), centre, batch.z_rows(js), design,
                                   attacks=None, inputs=batch.input_rows(js), runtime="centralized",
                                   cov_kind="covariance", messages=batch.model.n_sensors,
                                   covariances=batch.covariances)

    def derive(design: ConsensusDesign, model) -> ConsensusDesign:
        n_z = model.with_stacked_sensors().n_z
        return local_ekf_design(design)._replace(V=(np.zeros((n_z, n_z)),))

    return FilterEntry(name, "centralized", "centralized", description, run, _uplinks, mode=rules.PUBLISHED,
                       attacked=False, derive=derive,
                       payload=lambda model, network, iterations: int(sum(model.sensor_dims)))


def replayed_schedule(name: str, description: str, gains: tuple) -> FilterEntry:
    """A gain schedule's ``gains`` = (K (steps, nodes, n_x, n_z), C (steps, nodes, n_x, n_x)) looked up by the step
    and applied at each node (:func:`filters.consensus_batch.run_consensus_batch` replaying ``gains`` in every run,
    with the paper design's τ): runtime ``scheduled``, no bound it can claim (not ``designed``)."""

    def run(batch: Batch, js: Sequence[int], design: ConsensusDesign | None) -> FilterResult:
        return run_consensus_batch(batch.model, batch.network, batch.z_rows(js), design, inputs=batch.input_rows(js),
                                   attacks=batch.attack_rows(js), gains=gains)

    return FilterEntry(name, "consensus", "scheduled", description, run, _links, mode=rules.PUBLISHED)


def centralized_ekf(name: str, description: str) -> FilterEntry:
    """An EKF at a fusion centre on what the attacked uplinks delivered, trusting every received packet."""

    def run(batch: Batch, js: Sequence[int], design) -> FilterResult:
        m = batch.model
        values, avail = split_received(m, np.stack([batch.received[j][a] for j in js for a in range(batch.runs)]))
        return run_ekf_batch(m, values, available=avail, inputs=batch.input_rows(js))

    return FilterEntry(name, "EKF", "centralized", description, run, _uplinks)


def particle_filters(aware: tuple[str, str], plain: tuple[str, str]) -> tuple[FilterEntry, FilterEntry]:
    """The fusion centre's bootstrap particle filters: ``aware`` = (name, description) of the one whose likelihood
    knows the uplinks' attack law (a mixture with the falsified packets' moment-matched density), ``plain`` the one
    trusting every received packet.

    Both run as one NumPy batch over every run and setting (:func:`filters.particle.run_sir`'s blocks): run
    ``a``'s two filters at the main setting draw from the first two streams of ``batch.particle_seeds[a].spawn(3)``,
    alone, and both at every other setting from the third, together; each filter's time is the batch's per row.
    """
    names = (aware[0], plain[0])

    def pair(batch: Batch):
        scs, R, m = batch.scenarios, batch.runs, batch.model
        S, n = len(scs), batch.network.n_nodes
        qs = []  # per (setting, filter) row: the probability that a received packet is falsified; 0 = trust all
        for s in scs:
            up_d, up_f = s.resolved_attacks.uplink_dos, s.resolved_attacks.uplink_fdi
            q = np.where(up_d < 1, up_f / np.where(up_d < 1, 1.0 - up_d, 1.0), 0.0)
            qs += [float(q[0]) if np.all(q == q[0]) else q, 0.0 if np.all(q == q[0]) else np.zeros(n)]
        per_sensor = any(np.ndim(q) for q in qs)
        covs = fdi_covariances(m, m.prior.mean, scs[0].resolved_attacks.signal)
        t0 = time.perf_counter()
        streams = [np.random.default_rng(seq) for fs in batch.particle_seeds for seq in fs.spawn(3)]
        blocks = [1, 1, 2 * (S - 1)] * R
        if S == 1:
            streams, blocks = [g for i, g in enumerate(streams) if i % 3 < 2], [1, 1] * R
        q_rows = np.array([np.broadcast_to(q, (n,)) if per_sensor else q for q in qs] * R)
        with naming_filter([names[c] for _ in range(R * S) for c in range(2)],
                           [batch.run_ids[a] for a in range(R) for _ in range(2 * S)]):
            out = run_sir(m, np.stack([batch.received[j][a] for a in range(R) for j in range(S) for _ in range(2)]),
                          streams, blocks=blocks, particles=batch.particles,
                          inputs=None if batch.inputs is None else np.repeat(batch.inputs, 2 * S, axis=0),
                          loglik=uplink_loglik(m, fdi_prob=q_rows, fdi_covs=covs))
        return out._replace(seconds=np.full(out.runs, (time.perf_counter() - t0) / (2 * S * R)))

    def entry(c: int, name: str, description: str) -> FilterEntry:
        def run(batch: Batch, js: Sequence[int], design) -> FilterResult:
            if "particle filters" not in batch.cache:  # both filters' rows, run a-major: 2 S a + 2 j + c
                batch.cache["particle filters"] = pair(batch)
            S = len(batch.scenarios)
            return batch.cache["particle filters"].row([2 * S * a + 2 * j + c for j in js for a in range(batch.runs)])

        return FilterEntry(name, "particle", "centralized", description, run, _uplinks, particles=True)

    return entry(0, *aware), entry(1, *plain)
