"""One batched time loop for the consensus-family filters: the home of the loop over steps, its records and the stop.

A batched filter is a step function run over time (the shape of dynamax's filters, a step scanned over the
steps): :func:`run_batch` owns what every family's loop shares, each family (the consensus EKF of every mode,
the relay rule, KCF and HCMCI) supplies its step, the part that differs: prediction, exchange and update of the
runs still going.  The loop

* runs the steps in order over the runs still going (``act``, indices into the batch; ``at`` the same runs as an
  index, a whole-axis slice while none has stopped so that the step reads views, not copies);
* writes what the step returns into the result arrays: :attr:`Step.now` at ``[run, k]`` (predictions, gains,
  margins, packet counts), :attr:`Step.after` at ``[run, k + 1]`` (posteriors);
* stops a run whose estimate or covariance left finite numbers (:attr:`Step.bad`, e.g.
  :func:`filters.result.diverged_nodes`) at its first such node: a ``'diverged'`` violation and NaN from that
  step on (:func:`filters.result.stop_diverged`), while the other runs go on; the family's own state of the
  stopped runs goes with them (``stopped``);
* returns the runs that went on to the end (a family's last records, e.g. Theorem 2 on ``Φ_{K|K}``).

A run alone is a batch of one, and a run's numbers do not depend on the other runs of its batch: the loop adds no
arithmetic of its own.  :func:`estimate_arrays` allocates the records of the filters that carry an estimate and a
covariance per node (the relay rule, KCF, HCMCI) with their messages count; the consensus EKF's are
:func:`filters.consensus_batch.result_arrays`.

A record may be kept at its latest step only (:class:`Latest`): the filter's state, not its history.  A study that
scores a reference filter's estimates needs none of its covariances, which at a hundred states and nodes are a
gigabyte and more a run; the step reads and writes such a record as it does a full one, and the result has None
in its place (:func:`history`).  A covariance record may also be kept as its diagonals over the steps
(:class:`Diagonal`, :func:`diagonals`): what a study that judges a designed filter's bounds by their traces needs.
"""
from __future__ import annotations

from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from designer.progress import line

from .result import DIVERGED_REASON, stop_diverged

__all__ = ["Step", "run_batch", "estimate_arrays", "Latest", "Diagonal", "history", "diagonals"]


class Step(NamedTuple):
    """What a family's step returns for the ``a`` runs going on at step ``k``."""

    now: Mapping[str, np.ndarray]  # record name -> (a, ...) values at [run, k]
    after: Mapping[str, np.ndarray]  # record name -> (a, ...) values at [run, k + 1]
    bad: np.ndarray  # (a, N) which nodes of the runs left finite numbers at k + 1 (the run stops at the first)
    reason: str | Callable[[int, int], str] = DIVERGED_REASON  # or reason(j, node) for position j of the runs


def run_batch(step: Callable[[int, np.ndarray, slice | np.ndarray], Step], records: Mapping[str, np.ndarray],
              violations: list, steps: int, *, nan_from: Sequence[str] = (), nan_before: Sequence[str] = (),
              invalid_from: Sequence[str] = (), stopped: Callable[[np.ndarray], None] | None = None) -> np.ndarray:
    """Run ``step(k, act, at)`` over ``steps`` steps of the ``len(violations)`` runs of a batch; returns the runs
    still going at the end.

    ``records`` the result arrays by name (runs first, then steps), written where the step's :class:`Step` says;
    ``violations`` one list per run (the step appends its conditions' violations, the loop a ``'diverged'`` one
    after them).  A run that stops at step ``k + 1`` gets NaN in the records ``nan_from`` from ``k + 1`` on
    (posteriors), in ``nan_before`` at ``k`` (what its last update used: gains, predictions) and False in
    ``invalid_from`` from ``k + 1`` on; ``stopped(going)`` (the (a,) mask of the runs that go on) lets the family
    drop its own state of the others.
    """
    runs = len(violations)
    act = np.arange(runs)
    pick = (lambda names: tuple(records[name] for name in names))  # noqa: E731
    for k in range(steps):
        if not act.size:
            break
        line("step", k, steps)
        at = slice(None) if act.size == runs else act
        out = step(k, act, at)
        for name, value in out.now.items():
            records[name][at, k] = value
        for name, value in out.after.items():
            records[name][at, k + 1] = value
        going = stop_diverged(violations, act, out.bad, k + 1, out.reason, nan_from=pick(nan_from),
                              nan_before=pick(nan_before), invalid_from=pick(invalid_from))
        if not going.all():
            if stopped is not None:
                stopped(going)
            act = act[going]
    return act


class Latest:
    """A record of a batch kept at its latest step only: indexed as the full record is, ``a[runs, step]`` (runs
    first, then the step, a single one), it holds each run's value at the step written last, whatever the step
    named (a step reads a record at the step the step before wrote, never earlier).  ``a[run, step:] = NaN`` (a run
    that stops) sets that run's value.  ``shape``: (runs, ...) without the steps' axis."""

    def __init__(self, shape: tuple, fill=np.nan):
        self.value = np.full(shape, fill)

    def __getitem__(self, key):
        return self.value[key[0]]

    def __setitem__(self, key, value) -> None:
        self.value[key[0]] = value


class Diagonal(Latest):
    """A covariance record kept whole at its latest step only (:class:`Latest`: what the next step reads) and, over
    the steps, as its diagonal and whether each matrix is finite: ``diagonal`` (runs, steps, ..., m) and ``finite``
    (runs, steps, ...), what judging a bound by its trace (on the whole state or a region's) needs.  ``shape``: the
    full record's, (runs, steps, ..., m, m).  A 64-node field's bounds over a comparison's 2 runs and 10 settings:
    2.6 GB whole, 40 MB so."""

    def __init__(self, shape: tuple, fill=np.nan):
        super().__init__(shape[:1] + shape[2:], fill)
        self.diagonal = np.full(shape[:-1], fill)
        self.finite = np.zeros(shape[:-2], dtype=bool)

    def __setitem__(self, key, value) -> None:
        super().__setitem__(key, value)
        if np.ndim(value) < 2:  # a run that stops: NaN from its step
            self.diagonal[key], self.finite[key] = value, np.isfinite(value)
            return
        self.diagonal[key] = np.diagonal(value, axis1=-2, axis2=-1)
        self.finite[key] = np.isfinite(value).all(axis=(-2, -1))


def history(record) -> np.ndarray | None:
    """A record as a result holds it: its array over the steps, or None for one kept at its latest step only
    (:class:`Latest`, :class:`Diagonal`)."""
    return None if isinstance(record, Latest) else record


def diagonals(record) -> np.ndarray | None:
    """A covariance record's diagonals over the steps (..., m): a :class:`Diagonal`'s own, a full record's, None for
    a :class:`Latest`."""
    if isinstance(record, Diagonal):
        return record.diagonal
    return None if isinstance(record, Latest) else np.diagonal(record, axis1=-2, axis2=-1)


def estimate_arrays(runs: int, steps: int, n: int, nx: int, x0: np.ndarray, P0: np.ndarray, per_step: int, *,
                    covariances: bool = True, predictions: bool = True, variances: bool = False) -> dict:
    """The records of a filter whose nodes carry an estimate and a covariance: ``x_post``, ``P_post`` (runs, steps
    + 1, n, ...) from every node's ``x0`` (runs, nx), ``P0`` (runs, nx, nx), ``x_pred``, ``P_pred`` (runs, steps,
    n, ...) NaN, and the messages: ``sent`` (runs, steps) ``per_step`` transmissions at every step (attempted,
    lost ones included), ``delivered`` (runs, steps) zero until the steps count them.  Without ``covariances``,
    ``P_post`` and ``P_pred`` are kept at their latest step only (:class:`Latest`); without ``predictions``,
    ``P_pred``; with ``variances`` (and ``covariances``), ``P_post`` as its diagonals (:class:`Diagonal`)."""
    def cov(shape, keep: bool, diagonal: bool = False):
        if keep and diagonal:
            return Diagonal(shape)
        return np.full(shape, np.nan) if keep else Latest(shape[:1] + shape[2:])

    out = dict(x_post=np.full((runs, steps + 1, n, nx), np.nan),
               P_post=cov((runs, steps + 1, n, nx, nx), covariances, variances),
               x_pred=np.full((runs, steps, n, nx), np.nan),
               P_pred=cov((runs, steps, n, nx, nx), covariances and predictions),
               sent=np.full((runs, steps), per_step), delivered=np.zeros((runs, steps), int))
    out["x_post"][:, 0], out["P_post"][:, 0] = x0[:, None], P0[:, None]
    return out
