"""The relay node's C export: the home of :class:`RelayExport` (the relay rule's
:meth:`designer.rule.GainRule.c_export`, the ``flood`` rule's too), :func:`write_relay_c` (the node filter of a design
whose gain rule relays: :class:`rules.relay.filter.RelayNode` in C99) and of its replay, :func:`replay_text`.

The node's C is in this package's ``c/`` (``cfd_node.h.in``, ``cfd_node.c.in``, ``driver_main.c``), filled by
:func:`designer.export_c.template`; the frame (the model's code, the common C, the replay driver's head, the
Makefile) is :mod:`designer.export_c`'s.
"""
from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Sequence

import numpy as np

from designer.bounds import sqrtm_psd
from designer.export_c import (REPLAY_TOLERANCES, NodeExport, c_array, common_code, described, model_code,
                               replay_file, template, work_code, write_node)
from designer.validation import InputError

from .design import FLOAT_RTOL, RTOL, relay_carried, relay_moments, relay_routes

__all__ = ["RelayExport", "write_relay_c", "replay_text"]

_C = files(__package__) / "c"


class RelayExport(NodeExport):
    """The C export of a relaying rule's node filter: a step's replay record is the inputs and, per exported node,
    what reached it and its estimate and bound after the step (:func:`replay_text`), in the coordinates of the states
    it carries (the first :func:`carried_width` places of :attr:`rules.relay.filter.RelayNode.states`)."""

    def __init__(self, rule):
        self.rule = rule  # the relaying gain rule exported (its default hops and its routing)

    def replay_numbers(self, model, network, options, regions, nodes):
        """Per exported node and step: its measurement, one flag and the measurement of each other sensor of its
        ball, the inputs, its estimate and bound (``CFD_NC`` wide: the most an exported node carries), the
        tolerances; its data: its ball's rows' moments (A, F1, F2: rows x rows each), the rows' layout and its
        states."""
        routes = relay_routes(network, self.rule.rounds(network, options.rounds), self.rule.routing)
        dims = np.asarray(model.sensor_dims)
        nodes = [int(i) for i in nodes]
        widths = (np.full(network.n_nodes, model.n_x) if regions is None else
                  np.count_nonzero(relay_carried(model, routes, regions).index >= 0, axis=1))
        w = int(widths[nodes].max())
        record = data = 0
        for i in nodes:
            ball = routes.ball(i)
            rows = int(dims[ball].sum())
            record += rows + ball.size - 1 + REPLAY_TOLERANCES + model.n_u + w + w * w
            data += 3 * rows * rows + 2 * rows + 2 * ball.size + int(widths[i])
        return record, data

    def float_twin(self, net, rng):
        """The base class's twin at float's rounding, its nodes' pseudo-inverses cut where the float node cuts them
        (:data:`rules.relay.design.FLOAT_RTOL`: float does not resolve an eigenvalue below; the double keeps it
        down to :data:`rules.relay.design.RTOL`), so that the float tolerance covers what the float node leaves
        out."""
        twin = super().float_twin(net, rng)
        for node in twin.nodes:
            node.rtol = FLOAT_RTOL
        return twin

    def replay_step(self, net, k, u, z, nodes):
        _, rounds = net.last  # what each node sent and, round by round, what reached it
        w = carried_width([net.nodes[i] for i in nodes])
        return u, [(*rounds[0][i], net.nodes[i].x[:w], net.nodes[i].P[:w, :w]) for i in nodes]

    def write(self, model, network, design, net, steps, out, *, nodes, tolerances, verdict=None):
        routes = relay_routes(network, design.rounds, design.rule.routing)
        return write_relay_c(model, network, design, routes, relay_moments(routes, network, model.sensor_dims), out,
                             nodes=nodes, states=[net.nodes[i].states for i in nodes],
                             replay=replay_text(nodes, [net.nodes[i].ball for i in nodes], model.sensor_dims, steps,
                                                model.n_u, tolerances),
                             verdict=verdict)


def carried_width(nodes: Sequence) -> int:
    """``CFD_NC``: the most states one of the relay nodes ``nodes`` (:class:`rules.relay.filter.RelayNode`) carries
    (its ``states`` that are not ``-1``; the model's state count when they carry the whole state)."""
    return max(int(np.count_nonzero(nd.states >= 0)) for nd in nodes)


def write_relay_c(model, network, design, routes, moments: Sequence, out: Path, *, nodes: Sequence[int],
                  states: Sequence[np.ndarray] | None = None, replay: str | None = None,
                  verdict: str = "unknown") -> list[Path]:
    """Write the C sources of the node filter of the relay design ``design`` (``routes``, ``moments``: its
    :func:`rules.relay.design.relay_routes` and :func:`rules.relay.design.relay_moments`) for the nodes ``nodes`` into
    ``out``; ``states``: the states each of them carries (:attr:`rules.relay.filter.RelayNode.states`, ``-1`` at an
    unused place; None: the whole state); ``replay``: the text of ``replay.txt`` (see :func:`replay_text`);
    ``verdict``: the design's (:mod:`designer.verdict`), stated in the header.  Returns the files written."""
    rule = design.rule
    if not rule.relays:
        raise InputError(f"mode must be a relaying gain rule for the relay node's C export, got {rule.name!r}")
    out = Path(out)
    n, nz_max = model.n_x, max(model.sensor_dims)
    signal = design.fdi_signal
    M = np.zeros((n, n)) if signal is None else signal.moment(n)
    mu = np.zeros(n) if signal is None else signal.mean(n)
    if not np.any(network.fdi_prob > 0):
        M, mu = np.zeros((n, n)), np.zeros(n)
    G = routes.hops + 1
    sizes, dims, layout = model_code(model, out)
    rinv = [sqrtm_psd(model.measurement_cov(s), inverse=True) for s in range(model.n_sensors)]
    rinv_start = np.concatenate([[0], np.cumsum(dims ** 2)])
    nodes = [int(i) for i in nodes]
    if states is None:
        states = [np.arange(n)] * len(nodes)
    states = [np.asarray(s, dtype=int)[np.asarray(s) >= 0] for s in states]
    nc = max(s.size for s in states)
    state_start = np.concatenate([[0], np.cumsum([s.size for s in states])])
    ball_start, ball, row_start, row_group, p, rr_start, A, F1, F2 = [0], [], [0], [], [], [0], [], [], []
    for i in nodes:
        mom = moments[i]
        ball += mom.sensors.tolist()
        ball_start.append(len(ball))
        r = mom.rows.size
        row_group += mom.groups.argmax(-1).tolist()
        p += mom.p.tolist()
        row_start.append(row_start[-1] + r)
        A += mom.A.reshape(-1).tolist()
        F1 += (mom.F1 if np.any(M) else np.zeros((r, r))).reshape(-1).tolist()
        F2 += (mom.F2 if np.any(mu) else np.zeros((r, r))).reshape(-1).tolist()
        rr_start.append(len(A))
    r_max = max(row_start[j + 1] - row_start[j] for j in range(len(nodes)))
    ball_max = max(ball_start[j + 1] - ball_start[j] for j in range(len(nodes)))
    header = template(_C / "cfd_node.h.in", NX=n, NC=nc, NU=model.n_u, NZ=int(dims.sum()), SENSORS=model.n_sensors,
                      NODES=len(nodes), BALL_MAX=ball_max, ROWS_MAX=r_max, ROUNDS=int(routes.hops), MODE=rule.name,
                      NZMAX=nz_max, GROUPS=G, KMAX=min(r_max, G * nc), WORK=work_code(sizes, "CFD_ROWS_MAX"),
                      **described(model, nodes, verdict))
    data = "".join([
        c_array("cfd_node_id", nodes, "int"), c_array("cfd_state_start", state_start, "int"),
        c_array("cfd_state", np.concatenate(states), "int"), c_array("cfd_ball_start", ball_start, "int"),
        c_array("cfd_ball_sensor", ball, "int"), c_array("cfd_row_start", row_start, "int"),
        c_array("cfd_row_group", row_group, "int"), c_array("cfd_p", p), c_array("cfd_rr_start", rr_start, "int"),
        c_array("cfd_A", A), c_array("cfd_F1", F1), c_array("cfd_F2", F2),
        layout, c_array("cfd_rinv_start", rinv_start, "int"),
        c_array("cfd_rinv", np.concatenate([r.reshape(-1) for r in rinv])),
        c_array("cfd_Q", model.process_cov), c_array("cfd_M", M), c_array("cfd_mu", mu),
        c_array("cfd_x0", model.prior.mean), c_array("cfd_P0", model.prior.cov),
    ])
    whole = all(np.array_equal(s, np.arange(n)) for s in states)  # the C's sizes then fixed at compile time
    source = template(_C / "cfd_node.c.in", COMMON=common_code(model), DATA=data,
                      USE_F1=int(bool(np.any(M))), USE_F2=int(bool(np.any(mu))), WHOLE=int(whole),
                      RTOL=repr(RTOL), FLOAT_RTOL=repr(FLOAT_RTOL))
    return write_node(out, header, source, template(_C / "driver_main.c"), replay)


def replay_text(nodes: Sequence[int], balls: Sequence[Sequence[int]], dims: Sequence[int], steps: list,
                n_u: int, tolerances) -> str:
    """``replay.txt``: ``steps nodes n_u``, then per step and node (in ``nodes`` order) its tolerances
    (``tolerances``: :func:`designer.export_c.replay_file`), the node's measurement,
    one arrived flag per sensor of its ball after its own, the received measurements (zeros where not arrived), the
    step's inputs, the Python node filter's estimate and bound (row by row); numbers as Python's ``repr`` (exact).
    ``steps``: per step, ``(u, [(z_own, received {sensor: value}, x, P) per node])``."""
    def rows():
        for u, per_node in steps:
            for j, (own, got, x, P) in enumerate(per_node):
                vals = list(np.asarray(own, float))
                flags, rec = [], []
                for s in balls[j][1:]:
                    v = got.get(int(s))
                    flags.append(0 if v is None else 1)
                    rec += [0.0] * dims[s] if v is None else list(np.asarray(v, float))
                yield vals + flags + rec + list(np.asarray(u, float).reshape(-1)) + list(np.asarray(x).reshape(-1)) \
                    + list(np.asarray(P).reshape(-1))

    return replay_file(len(steps), len(nodes), n_u, rows(), tolerances)
