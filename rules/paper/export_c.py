"""The consensus node's C export: the home of :class:`PaperExport` (the paper rule's
:meth:`designer.rule.GainRule.c_export`), :func:`write_consensus_c`
(the node filter of a ``paper`` design: :class:`filters.consensus_node.ConsensusNode` in C99, two phases a step) and
of its replay, :func:`consensus_replay_text`.

The node's C is in this package's ``c/`` (``cfd_node.h.in``, ``cfd_node.c.in``, ``driver_main.c``), filled by
:func:`designer.export_c.template`; the frame (the model's code, the common C and the linear algebra, the replay
driver's head, the Makefile) is :mod:`designer.export_c`'s.
"""
from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Sequence

import numpy as np

from designer.export_c import (NodeExport, arrival_flag, c_array, common_code, described, linalg_code, model_code,
                               replay_file, template, work_code, write_node)
from designer.validation import InputError

__all__ = ["PaperExport", "write_consensus_c", "consensus_replay_text"]

_C = files(__package__) / "c"


class PaperExport(NodeExport):
    """The C export of the paper rule's two-phase consensus node: a design of the ``fixed`` linearization only; a
    step's replay record is the inputs and, per exported node, its measurement, what reached it, the packet it sent
    and its estimate and covariance after the update (:func:`consensus_replay_text`)."""

    def check(self, design) -> None:
        if design.linearization != "fixed":
            raise InputError(f"linearization must be 'fixed' to export a paper design to C (the "
                             f"{design.linearization!r} scalings come from the model's Hessians at every step, which "
                             "the export does not generate)")

    def replay_step(self, net, k, u, z, nodes):
        sent, rounds = net.last  # what each node sent and, round by round, what reached it
        hit = net.falsified()
        return u, [(z_i, rounds[0][i][0], hit[i], rounds[0][i][1], sent[i], net.nodes[i].x, net.nodes[i].P)
                   for i, z_i in zip(nodes, z)]

    def write(self, model, network, design, net, steps, out, *, nodes, tolerances, verdict=None):
        return write_consensus_c(model, network, design, out, nodes=nodes, verdict=verdict,
                                 replay=consensus_replay_text(nodes, [net.nodes[i].senders.tolist() for i in nodes],
                                                              model.n_u, steps, tolerances))


def write_consensus_c(model, network, design, out: Path, *, nodes: Sequence[int], replay: str | None = None,
                      verdict: str = "unknown") -> list[Path]:
    """Write the C sources of the node filter of the ``paper`` consensus design ``design``
    (:class:`filters.consensus_node.ConsensusNode`: ``cfd_predict`` gives the packet a node sends, ``cfd_update``
    takes what arrived) for the nodes ``nodes`` into ``out``; ``replay``: the text of ``replay.txt``
    (:func:`consensus_replay_text`); ``verdict``: the design's, stated in the header.  Returns the files written.

    The rule's σ, β, τ, ε, U, V_i and δ are the design's numbers; its linearisation must be ``fixed`` (the Hessian
    scalings of ``hessian`` and ``structured`` are not exported) and its rule ``paper`` (``tuned`` solves a convex
    problem online at every step: not exported)."""
    from scipy.special import chdtri

    from designer.bounds import BOUND_LIMIT

    if not design.rule.fixed_multipliers:
        raise InputError(f"mode must be a rule of fixed multipliers (paper) for the consensus node's C export, got "
                         f"{design.mode!r}")
    if design.linearization != "fixed":
        raise InputError(f"linearization must be 'fixed' for the C export (the {design.linearization!r} scalings "
                         "come from the model's Hessians at every step, which the export does not generate)")
    out = Path(out)
    n = model.n_x
    sizes, dims, layout = model_code(model, out)
    sigma, beta, eps = float(design.sigma), float(design.beta), float(design.epsilon)
    U = np.asarray(design.U, dtype=float)
    UU = U @ U.T / (eps * sigma) if np.any(U) else np.zeros((n, n))
    w_xi = 3.0 * design.delta**2 * (network.fdi_prob * network.adjacency).sum(axis=1)
    nodes = [int(i) for i in nodes]
    nb_start, nb, wphi, mat_start, R, VV = [0], [], [], [0], [], []
    for i in nodes:
        senders = np.flatnonzero(network.adjacency[i])
        nb += senders.tolist()
        wphi += (3.0 * (1.0 - network.dos_prob[i, senders])).tolist()
        nb_start.append(len(nb))
        Vi = np.asarray(design.V[i], dtype=float)
        R += model.measurement_cov(i).reshape(-1).tolist()
        VV += (Vi @ Vi.T / beta if np.any(Vi) else np.zeros_like(Vi)).reshape(-1).tolist()
        mat_start.append(len(R))
    d_max = max(nb_start[j + 1] - nb_start[j] for j in range(len(nodes)))
    header = template(_C / "cfd_node.h.in", NX=n, NU=model.n_u, NZ=int(dims.sum()), SENSORS=model.n_sensors,
                      NODES=len(nodes), D_MAX=max(d_max, 1), SIGMA=sigma, BETA=beta, TAU=float(design.tau),
                      GATE=float(design.gate), NZMAX=int(dims.max()), WORK=work_code(sizes, "CFD_NX"),
                      **described(model, nodes, verdict))
    data = "".join([
        c_array("cfd_node_id", nodes, "int"), c_array("cfd_nb_start", nb_start, "int"), c_array("cfd_nb", nb, "int"),
        c_array("cfd_wphi", wphi), c_array("cfd_wxi", w_xi[nodes]),
        c_array("cfd_deg", network.degrees[nodes], "int"), c_array("cfd_mat_start", mat_start, "int"),
        c_array("cfd_R", R), c_array("cfd_VV", VV), c_array("cfd_UU", UU), layout,
        c_array("cfd_Q", model.process_cov), c_array("cfd_x0", model.prior.mean), c_array("cfd_P0", model.prior.cov),
    ])
    source = template(
        _C / "cfd_node.c.in", COMMON=common_code(model), LINALG=linalg_code(), DATA=data, SIGMA=repr(sigma),
        BETA=repr(beta),
        TAU=repr(float(design.tau)), EPS=repr(eps), FIXED=int(design.rule.fixed_multipliers),
        GATE=repr(float(design.gate)), CHI2=repr(float(chdtri(n, design.gate))) if design.gate else "0.0",
        BOUND_LIMIT=repr(float(BOUND_LIMIT)), RCOND=repr(1e-13), DIVERGED=repr(1e12))
    return write_node(out, header, source, template(_C / "driver_main.c"), replay)


def consensus_replay_text(nodes: Sequence[int], senders: Sequence[Sequence[int]], n_u: int, steps: list,
                          tolerances) -> str:
    """``replay.txt`` of a consensus design: ``steps nodes n_u``, then per step and node (in ``nodes`` order) its
    tolerances (``tolerances``: :func:`designer.export_c.replay_file`), the step's inputs, the node's
    measurement, one arrival flag per in-neighbour (``senders`` order; :func:`designer.export_c.arrival_flag`: 0
    lost, 1 arrived as sent, 2 arrived falsified), the estimates that arrived (zeros where not), every
    in-neighbour's packet (its bound row by row, then 1 if it is a bound), then the Python node filter's packet
    (prediction, its covariance, its flag) and its estimate and covariance after the update. ``steps``: per step,
    ``(u, [(z, received {j: x̃}, falsified {j}, bounds {j: Packet}, packet, x, P) per node])``."""
    def rows():
        for u, per_node in steps:
            for j, (z, got, hit, bounds, packet, x, P) in enumerate(per_node):
                vals = list(np.asarray(u, float).reshape(-1)) + list(np.asarray(z, float).reshape(-1))
                vals += [arrival_flag(s, got, hit) for s in senders[j]]
                n = np.asarray(x).size
                for s in senders[j]:
                    vals += list(np.asarray(got[s], float).reshape(-1)) if s in got else [0.0] * n
                for s in senders[j]:
                    vals += list(np.asarray(bounds[s].P, float).reshape(-1)) + [float(bool(bounds[s].ok))]
                vals += list(np.asarray(packet.x, float)) + list(np.asarray(packet.P, float).reshape(-1))
                vals += [float(bool(packet.ok))] + list(np.asarray(x, float)) + list(np.asarray(P, float).reshape(-1))
                yield vals

    return replay_file(len(steps), len(nodes), n_u, rows(), tolerances)
