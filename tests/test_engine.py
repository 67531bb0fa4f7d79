"""The consensus family's one batched time loop (filters.engine.run_batch; issue 39, item 5).

A toy filter (a scalar Kalman filter per node of a random walk, a step of a few lines) run on the engine against the
same filter written as a plain loop over one run: the records where the step puts them, a run that diverges stops
alone at its first failing node (a 'diverged' violation after the step's own, NaN from that step on in the
posteriors, at the step before in the gains, invalid from then), the family's state follows the runs that go on,
the step reads views while no run has stopped, and a run alone is a batch of one, bit for bit.
"""
from __future__ import annotations

import numpy as np
import pytest

from filters.engine import Diagonal, Latest, Step, diagonals, estimate_arrays, history, run_batch
from filters.result import DIVERGED_REASON, diverged_nodes

Q, R = 0.1, 0.5
STEPS, NODES = 8, 3


def reference(z, x0, P0):
    """One run of the toy filter as a plain loop: ``(x_post, P_post, gain, violations)``; NaN after a divergence."""
    x_post = np.full((STEPS + 1, NODES, 1), np.nan)
    P_post = np.full((STEPS + 1, NODES, 1, 1), np.nan)
    gain = np.full((STEPS, NODES), np.nan)
    x_post[0], P_post[0] = x0, P0
    x, P = np.full((NODES, 1), x0), np.full((NODES, 1, 1), P0)
    for k in range(STEPS):
        Pp = P + Q
        K = Pp[:, 0, 0] / (Pp[:, 0, 0] + R)
        x = x + K[:, None] * (z[k][:, None] - x)
        P = (1.0 - K)[:, None, None] * Pp
        gain[k] = K
        x_post[k + 1], P_post[k + 1] = x, P
        bad = ~(np.isfinite(x).all(-1) & (np.abs(x).max(-1) < 1e12))
        if bad.any():
            x_post[k + 1:] = P_post[k + 1:] = np.nan
            gain[k] = np.nan
            return x_post, P_post, gain, [{"node": int(np.argmax(bad)), "step": k + 1, "condition": "diverged",
                                           "margin": -np.inf, "reason": DIVERGED_REASON}]
    return x_post, P_post, gain, []


def run_toy(z, x0, P0, seen=None, covariances=True, variances=False):
    """The toy filter on the engine over the runs of ``z`` (runs, steps, nodes)."""
    runs = z.shape[0]
    out = estimate_arrays(runs, STEPS, NODES, 1, np.full((runs, 1), x0), np.full((runs, 1, 1), P0), 2,
                          covariances=covariances, variances=variances)
    out["gain"] = np.full((runs, STEPS, NODES), np.nan)
    out["valid"] = np.zeros((runs, STEPS + 1, NODES), dtype=bool)
    out["valid"][:, 0] = True
    violations = [[] for _ in range(runs)]
    state = {"ids": np.arange(runs)}  # a family's own state of the runs going on

    def step(k, act, at):
        np.testing.assert_array_equal(state["ids"], act)
        if seen is not None:
            seen.append((k, act.copy(), isinstance(at, slice)))
        x, P = out["x_post"][at, k], out["P_post"][at, k]
        Pp = P + Q
        K = Pp[..., 0, 0] / (Pp[..., 0, 0] + R)
        xn = x + K[..., None] * (z[at, k][..., None] - x)
        for r in act[(K < 0.5).all(axis=1)].tolist():  # a condition of the family's own, recorded before a stop
            violations[r].append({"node": 0, "step": k, "condition": "small gain", "margin": 0.0})
        return Step(dict(gain=K, delivered=np.full(act.size, 7)),
                    dict(x_post=xn, P_post=(1.0 - K)[..., None, None] * Pp, valid=np.ones((act.size, NODES), bool)),
                    diverged_nodes(xn, Pp))

    def stopped(going):
        state["ids"] = state["ids"][going]

    left = run_batch(step, out, violations, STEPS, nan_from=("x_post", "P_post"), nan_before=("gain",),
                     invalid_from=("valid",), stopped=stopped)
    return out, violations, left


@pytest.fixture(scope="module")
def measurements():
    z = np.random.default_rng(5).standard_normal((4, STEPS, NODES))
    z[1, 3, 2] = 1e300  # run 1 leaves finite numbers at node 2 after step 3 ...
    z[3, 5, 1] = np.inf  # ... run 3 at node 1 after step 5
    return z


def test_each_run_of_the_batch_is_the_plain_loop_and_a_diverged_run_stops_alone(measurements):
    seen = []
    out, violations, left = run_toy(measurements, 0.2, 1.0, seen)
    np.testing.assert_array_equal(left, [0, 2])
    for r in range(measurements.shape[0]):
        x, P, gain, diverged = reference(measurements[r], 0.2, 1.0)
        np.testing.assert_array_equal(out["x_post"][r], x)
        np.testing.assert_array_equal(out["P_post"][r], P)
        np.testing.assert_array_equal(out["gain"][r], gain)
        assert [v for v in violations[r] if v["condition"] == "diverged"] == diverged
        assert violations[r][-1]["condition"] == ("diverged" if diverged else "small gain")
        stop = diverged[0]["step"] if diverged else STEPS + 1
        assert out["valid"][r, :stop].all() and not out["valid"][r, stop:].any()
        np.testing.assert_array_equal(out["delivered"][r], np.where(np.arange(STEPS) < stop, 7, 0))
    assert [v["node"] for v in violations[1] + violations[3] if v["condition"] == "diverged"] == [2, 1]
    np.testing.assert_array_equal(out["sent"], np.full((4, STEPS), 2))
    # the step reads views (a slice) while every run goes on, the runs' indices once one stopped
    assert [s for k, act, s in seen] == [k < 4 for k in range(STEPS)]
    np.testing.assert_array_equal(seen[5][1], [0, 2, 3])
    np.testing.assert_array_equal(seen[6][1], [0, 2])


def test_a_run_alone_is_a_batch_of_one(measurements):
    full, violations, _ = run_toy(measurements, 0.2, 1.0)
    for r in range(measurements.shape[0]):
        alone, v, _ = run_toy(measurements[r:r + 1], 0.2, 1.0)
        for name, a in alone.items():
            np.testing.assert_array_equal(a[0], full[name][r], err_msg=name)
        assert v[0] == violations[r]


def test_covariances_kept_at_their_latest_step_give_the_same_estimates(measurements):
    """Without covariances the records P_post and P_pred are kept at their latest step only (filters.engine.Latest):
    the step reads and writes them as full records, and every other record (estimates, gains, violations, a run's
    stop, validity) has the same bits; the result holds None in their place (history)."""
    full, v_full, left_full = run_toy(measurements, 0.2, 1.0)
    lean, v_lean, left_lean = run_toy(measurements, 0.2, 1.0, covariances=False)
    assert isinstance(lean["P_post"], Latest) and history(lean["P_post"]) is None and history(lean["P_pred"]) is None
    assert lean["P_post"].value.shape == (4, NODES, 1, 1)
    np.testing.assert_array_equal(left_lean, left_full)
    assert v_lean == v_full
    for name in ("x_post", "gain", "valid", "delivered", "sent"):
        np.testing.assert_array_equal(lean[name], full[name], err_msg=name)
    # each run's latest: its last posterior, NaN for the runs that stopped
    np.testing.assert_array_equal(lean["P_post"].value, full["P_post"][:, -1])
    assert np.isnan(lean["P_post"].value[[1, 3]]).all() and np.isfinite(lean["P_post"].value[[0, 2]]).all()


def test_covariances_kept_as_their_diagonals_give_the_same_estimates_and_diagonals(measurements):
    """With variances P_post is kept whole at its latest step and as its diagonals and finiteness over the steps
    (filters.engine.Diagonal): the same estimates and stops, the full record's diagonals bit for bit (NaN from a
    stopped run's step, not finite there), and the result holds None for the matrices (history)."""
    full, v_full, _ = run_toy(measurements, 0.2, 1.0)
    lean, v_lean, _ = run_toy(measurements, 0.2, 1.0, variances=True)
    assert isinstance(lean["P_post"], Diagonal) and history(lean["P_post"]) is None
    assert v_lean == v_full
    np.testing.assert_array_equal(lean["x_post"], full["x_post"])
    np.testing.assert_array_equal(diagonals(lean["P_post"]), diagonals(full["P_post"]))
    np.testing.assert_array_equal(lean["P_post"].finite, np.isfinite(full["P_post"]).all(axis=(-2, -1)))
    assert not lean["P_post"].finite[1, 4:].any() and lean["P_post"].finite[0].all()
    np.testing.assert_array_equal(lean["P_post"].value, full["P_post"][:, -1])
    assert diagonals(Latest((2, 1, 1))) is None


def test_a_batch_whose_every_run_stops_ends_there():
    z = np.zeros((2, STEPS, NODES))
    z[:, 1, 0] = 1e300
    seen = []
    out, violations, left = run_toy(z, 0.0, 1.0, seen)
    assert left.size == 0 and [k for k, *_ in seen] == [0, 1]
    assert [vs[-1]["step"] for vs in violations] == [2, 2]
    assert np.isnan(out["x_post"][:, 2:]).all() and np.isfinite(out["x_post"][:, :2]).all()
