"""The scheduled node's C export: the home of :class:`ScheduledExport` (the scheduled rule's
:meth:`designer.rule.GainRule.c_export`), :func:`write_scheduled_c` (the node filter of a ``scheduled`` design:
:class:`rules.scheduled.filter.ScheduledNode` in C99, its tables as data, the per-link gains solved online) and of
its replay, :func:`scheduled_replay_text`.

The node's C is in this package's ``c/`` (``cfd_node.h.in``, ``cfd_node.c.in``, ``driver_main.c``), filled by
:func:`designer.export_c.template`; the frame (the model's code, the common C and the linear algebra, the replay
driver's head, the Makefile) is :mod:`designer.export_c`'s.
"""
from __future__ import annotations

import hashlib
from importlib.resources import files
from pathlib import Path
from typing import Sequence

import numpy as np

from designer.export_c import (NodeExport, arrival_flag, c_array, common_code, described, linalg_code, model_code,
                               replay_file, template, work_code, write_node)
from designer.validation import InputError

__all__ = ["ScheduledExport", "write_scheduled_c", "scheduled_replay_text"]

_C = files(__package__) / "c"


class ScheduledExport(NodeExport):
    """The C export of the scheduled rule's node: a step's replay record is the inputs and, per exported node, its
    measurement, the packets that reached it in the first round, the estimates of rounds 2..L, and its estimate and
    own covariance after the step (:func:`scheduled_replay_text`)."""

    def replay_step(self, net, k, u, z, nodes):
        _, rounds = net.last  # what each node sent and, round by round, what reached it
        hit = net.falsified()
        return u, [(z_i, rounds[0][i], hit[i], [r[i] for r in rounds[1:]], net.nodes[i].x, net.nodes[i].P)
                   for i, z_i in zip(nodes, z)]

    def write(self, model, network, design, net, steps, out, *, nodes, tolerances, verdict=None):
        return write_scheduled_c(model, network, design, out, nodes=nodes, verdict=verdict,
                                 replay=scheduled_replay_text(nodes, [net.nodes[i].senders.tolist() for i in nodes],
                                                              model.n_u, max(model.sensor_dims),
                                                              design.tables.exchange, steps, tolerances))


def write_scheduled_c(model, network, design, out: Path, *, nodes: Sequence[int], replay: str | None = None,
                      verdict: str = "unknown") -> list[Path]:
    """Write the C sources of the node filter of the ``scheduled`` design ``design``
    (:class:`rules.scheduled.filter.ScheduledNode`: ``cfd_predict`` with the node's measurement gives the packet it
    sends, ``cfd_update`` the first round with what arrived, ``cfd_round`` the exchange rounds 2..L) for the nodes
    ``nodes`` into ``out``: each exported node's tables (the whitened factors of its links per step and round, the
    stationary ones beyond the horizon, the bank's), its certificate per step, and the per-link gains'
    solve (:func:`rules.scheduled.design.link_gains`, :func:`designer.joint.solve_gains`) online.  ``replay``: the text of
    ``replay.txt`` (:func:`scheduled_replay_text`).  Returns the files written."""
    from designer.joint import GAIN_RCOND

    tables = design.tables
    if design.mode != "scheduled" or tables is None:
        raise InputError(f"mode must be 'scheduled' with its tables for this export, got {design.mode!r}")
    out = Path(out)
    n = model.n_x
    sizes, dims, layout = model_code(model, out)
    nz = int(dims.max())
    ch = tables.channels
    chan, mask = ch.slots
    L = int(tables.rounds)
    T = tables.steps
    B = len(tables.bank_points) if tables.has_bank else 0
    nodes = [int(i) for i in nodes]
    R_pad = np.stack([np.pad(model.measurement_cov(i), ((0, nz - dims[i]), (0, nz - dims[i])))
                      + np.diag(np.r_[np.zeros(dims[i]), np.ones(nz - dims[i])]) for i in range(model.n_sensors)])
    nb_start, nb, p, q, tab_start = [0], [], [], [], [0]
    gam, sig = _Entries(), _Entries()  # per node: [step (T, then inf) and per bank point][round] -> its slots' tables
    upper = [np.triu_indices(d) for d in range(ch.d_max + 1)]  # Sigma's blocks (j, l), l >= j: (l, j) is (j, l)ᵀ
    for i in nodes:
        sl = chan[i][mask[i]]
        d = sl.size
        nb += ch.sender[sl].tolist()
        p += ch.p[sl].tolist()
        q += ch.q[sl].tolist()
        nb_start.append(len(nb))
        for k in range(T + 1):  # the step's own tables, k = T: beyond the horizon
            for r in range(1, L + 1):
                G, S = tables.tables(k) if r == 1 else tables.round_tables(k, r)
                gam.add(G[sl])
                sig.add(S[i][upper[d]])
        for b in range(B):
            for r in range(1, L + 1):
                G = tables.bank_Gamma[b] if r == 1 else tables.bank_round_Gamma[b, r - 2]
                S = tables.bank_Sigma[b] if r == 1 else tables.bank_round_Sigma[b, r - 2]
                gam.add(G[sl])
                sig.add(S[i][upper[d]])
        tab_start.append(len(gam.offsets))
    d_max = max(nb_start[j + 1] - nb_start[j] for j in range(len(nodes)))
    # the certificate's diagonal per step and exported node (T + 1, nodes, n): NaN where it is no bound
    cert = np.where(tables.valid[:, None, None], np.diagonal(tables.Phi, axis1=-2, axis2=-1), np.nan)[:, nodes]
    M = np.zeros((n, n)) if design.fdi_moment is None else np.asarray(design.fdi_moment, dtype=float)
    mu = np.zeros(n) if design.fdi_mean is None else np.asarray(design.fdi_mean, dtype=float)
    nominal = tables.nominal[np.minimum(np.arange(T + 1) + 1, T)]  # the step's own candidate point, k = 0..T
    header = template(_C / "cfd_node.h.in", NX=n, NU=model.n_u, NZ=int(dims.sum()), SENSORS=model.n_sensors,
                      NODES=len(nodes), D_MAX=max(d_max, 1), ROUNDS=L, STEPS=int(T), NZMAX=nz,
                      WORK=work_code(sizes, "CFD_WMAX"),
                      EXCH=int(bool(tables.exchange)), EXCHANGE="exchanged" if tables.exchange else "not exchanged",
                      **described(model, nodes, verdict))
    table_code = c_array("cfd_gam", gam.data()) + c_array("cfd_sig", sig.data())
    _say_large_tables(len(table_code), gam.size + sig.size, tables, design.table_kind, len(nodes))
    data = "".join([
        c_array("cfd_node_id", nodes, "int"), c_array("cfd_nb_start", nb_start, "int"), c_array("cfd_nb", nb, "int"),
        c_array("cfd_p", p), c_array("cfd_q", q), c_array("cfd_tab_start", tab_start, "int"),
        c_array("cfd_gam_off", gam.offsets, "int"), c_array("cfd_sig_off", sig.offsets, "int"), table_code,
        c_array("cfd_cert", cert), c_array("cfd_Rpad", R_pad), c_array("cfd_M", M), c_array("cfd_mu", mu),
        c_array("cfd_nominal", nominal), c_array("cfd_bank_points", tables.bank_points if B else []),
        c_array("cfd_bank_metric", tables.bank_metric if B else []), layout,
        c_array("cfd_Q", model.process_cov), c_array("cfd_x0", model.prior.mean), c_array("cfd_P0", model.prior.cov),
    ])
    source = template(
        _C / "cfd_node.c.in", COMMON=common_code(model), LINALG=linalg_code(), DATA=data, T=T, B=B,
        A=0 if not B else int(tables.bank_metric.shape[0]),
        MARGIN=repr(float(tables.robustness)), GAIN_RCOND=repr(float(GAIN_RCOND)), DIVERGED=repr(1e12))
    return write_node(out, header, source, template(_C / "driver_main.c"), replay)


#: Tables' C beyond this many bytes is said (a RuntimeWarning, which ``cfdesign export`` prints): what makes it large
#: and what would not be.  An assumption: a few MB is what issue 41 asks of 30 nodes.
LARGE_TABLES_BYTES = 16 * 2**20


def _say_large_tables(code_bytes: int, numbers: int, tables, asked: str | None, exported: int) -> None:
    """Warn when the exported tables' C passes :data:`LARGE_TABLES_BYTES`: why (each step's own tables, asked for or
    kept by default where the nominal's linearisation moves with the step; else the nodes' count) and the smaller
    exports.  ``asked``: the design's ``--table-kind`` (None: its default)."""
    if code_bytes <= LARGE_TABLES_BYTES:
        return
    import warnings

    from .design import PER_STEP_KIND, STATIONARY_KIND

    own = tables.steps if tables.kind == PER_STEP_KIND else (tables.own_steps or 0)
    if not own:
        why = ""
    elif asked == PER_STEP_KIND:
        why = f"each of the {own} steps' own tables (--table-kind {PER_STEP_KIND}), "
    else:
        why = (f"each of the first {own} steps' own tables (the default keeps them where the design's nominal leaves "
               f"its operating point's linearisation, which the stationary tables are of), ")
    warnings.warn(f"the {exported} nodes' tables are {numbers} numbers, {code_bytes / 2**20:.0f} MB of C: {why}"
                  f"a C compiler takes long over them; smaller: a design with --table-kind {STATIONARY_KIND} (its "
                  f"operating point's tables at every step, one step's size), or fewer nodes (--node)",
                  RuntimeWarning, stacklevel=2)


class _Entries:
    """The table entries of an export, each written once: an entry equal to one already written (the stationary
    tables at every step, a step's tables beyond the horizon) takes that one's offset."""

    def __init__(self):
        self.offsets: list[int] = []
        self._parts: list[np.ndarray] = []
        self._size = 0
        self._seen: dict[bytes, int] = {}

    def add(self, a: np.ndarray) -> None:
        a = np.ascontiguousarray(a, dtype=float).reshape(-1)
        key = hashlib.sha256(a.tobytes()).digest()
        if key not in self._seen:
            self._seen[key] = self._size
            self._parts.append(a)
            self._size += a.size
        self.offsets.append(self._seen[key])

    @property
    def size(self) -> int:
        """The numbers written (each distinct entry once)."""
        return self._size

    def data(self) -> np.ndarray:
        return np.concatenate(self._parts) if self._parts else np.zeros(0)


def scheduled_replay_text(nodes: Sequence[int], senders: Sequence[Sequence[int]], n_u: int, nz: int,
                          exchange: bool, steps: list, tolerances) -> str:
    """``replay.txt`` of a scheduled design: ``steps nodes n_u``, then per step and node (in ``nodes`` order) its
    tolerances (``tolerances``: :func:`designer.export_c.replay_file`), the step's inputs, the node's
    measurement, one arrival flag per in-neighbour (:func:`designer.export_c.arrival_flag`: 0 lost, 1 arrived as
    sent, 2 arrived falsified), the predictions that arrived (zeros where not), with exchange the measurements that
    arrived (``nz`` each, zero-padded), for rounds 2..L the estimates that arrived, then the Python node filter's
    estimate and own covariance after the step. ``steps``: per step, ``(u, [(z, received {j: ScheduledPacket},
    falsified {j}, [{j: x̃} per round 2..L], x, P) per node])``."""
    def rows():
        for u, per_node in steps:
            for j, (z, got, hit, later, x, P) in enumerate(per_node):
                n = np.asarray(x).size
                vals = list(np.asarray(u, float).reshape(-1)) + list(np.asarray(z, float).reshape(-1))
                vals += [arrival_flag(s, got, hit) for s in senders[j]]
                for s in senders[j]:
                    vals += list(np.asarray(got[s].x, float)) if s in got else [0.0] * n
                for s in senders[j] if exchange else ():
                    zz = np.asarray(got[s].z, float).reshape(-1) if s in got else np.zeros(0)
                    vals += list(zz) + [0.0] * (nz - zz.size)
                for rnd in later:
                    for s in senders[j]:
                        vals += list(np.asarray(rnd[s], float)) if s in rnd else [0.0] * n
                vals += list(np.asarray(x, float)) + list(np.asarray(P, float).reshape(-1))
                yield vals

    return replay_file(len(steps), len(nodes), n_u, rows(), tolerances)
