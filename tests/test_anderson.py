"""designer.anderson: the safeguarded Anderson acceleration the design's fixed-point recursions share.

References: a linear fixed point solved in closed form, NumPy's lstsq, the plain iteration of the same map, and
the items of a batch taken alone."""
from __future__ import annotations

import numpy as np
import pytest

from designer.anderson import Anderson, least_squares, positive_definite


def _linear_maps(k: int, n: int, seed: int, radius: float = 0.97):
    """k maps x -> A x + b on vectors of n entries, A with spectral radius ``radius`` (a slow plain iteration),
    and their fixed points solved directly."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(k, n, n))
    A *= radius / np.abs(np.linalg.eigvals(A)).max(axis=1)[:, None, None]
    b = rng.normal(size=(k, n))
    fixed = np.linalg.solve(np.eye(n) - A, b[..., None])[..., 0]
    return A, b, fixed


def _iterate(A, b, memory, tol=1e-12, max_iter=5000):
    k, n = b.shape
    acc = Anderson(k, memory, admissible=lambda c: np.isfinite(c).all(axis=1))
    x = np.zeros((k, n))
    act = np.arange(k)
    its = np.zeros(k, dtype=int)
    for it in range(1, max_iter + 1):
        g = (A[act] @ x[act, :, None])[..., 0] + b[act]
        done = np.linalg.norm(g - x[act], axis=1) <= tol * np.linalg.norm(g, axis=1)
        x[act[done]] = g[done]
        its[act[done]] = it
        if (~done).any():
            x[act[~done]] = acc.step(act[~done], x[act[~done]], g[~done])
        act = act[~done]
        if not act.size:
            break
    return x, its


def test_least_squares_is_lstsq_and_drops_a_dependent_column():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 30, 3))
    b = rng.normal(size=(4, 30))
    got = least_squares(np.swapaxes(A, 1, 2) @ A, (np.swapaxes(A, 1, 2) @ b[..., None])[..., 0], 30)
    for i in range(4):
        assert np.allclose(got[i], np.linalg.lstsq(A[i], b[i], rcond=None)[0], rtol=1e-10, atol=1e-12)
    # a repeated column and a zero one: their coefficients are 0, the others those of the reduced problem
    D = np.concatenate([A[:1, :, :2], A[:1, :, :1], np.zeros((1, 30, 1))], axis=2)
    gamma = least_squares(np.swapaxes(D, 1, 2) @ D, (np.swapaxes(D, 1, 2) @ b[:1, :, None])[..., 0], 30)[0]
    assert gamma[2] == 0.0 and gamma[3] == 0.0
    assert np.allclose(gamma[:2], np.linalg.lstsq(D[0, :, :2], b[0], rcond=None)[0], rtol=1e-10)


def test_accelerated_iteration_reaches_the_closed_form_fixed_point_in_far_fewer_steps():
    A, b, fixed = _linear_maps(5, 12, seed=1)
    plain, plain_its = _iterate(A, b, memory=0)
    fast, fast_its = _iterate(A, b, memory=5)
    assert np.allclose(plain, fixed, rtol=0, atol=1e-9 * np.abs(fixed).max())
    assert np.allclose(fast, fixed, rtol=0, atol=1e-9 * np.abs(fixed).max())
    assert plain_its.min() > 300  # the plain iteration's tail: 0.97 an iteration
    assert fast_its.max() * 5 < plain_its.min()


def test_each_item_of_a_batch_takes_the_steps_it_takes_alone():
    A, b, _ = _linear_maps(6, 9, seed=2)
    together, its = _iterate(A, b, memory=5)
    for i in range(6):
        alone, its_i = _iterate(A[i:i + 1], b[i:i + 1], memory=5)
        assert its_i[0] == its[i] and np.array_equal(alone[0], together[i])


def test_the_safeguard_takes_the_plain_step_when_no_extrapolated_point_is_admissible():
    A, b, _ = _linear_maps(1, 6, seed=3)
    acc = Anderson(1, 5, admissible=lambda c: np.zeros(len(c), dtype=bool))  # nothing admissible
    x = np.zeros((1, 6))
    for _ in range(8):
        g = (A @ x[..., None])[..., 0] + b
        nxt = acc.step([0], x, g)
        assert np.array_equal(nxt, g) and not acc.extrapolated[0]
        x = nxt
    # admissible: the extrapolated point is taken, and retreat gives back the plain step it replaced
    acc = Anderson(1, 5, admissible=lambda c: np.ones(len(c), dtype=bool))
    x = np.zeros((1, 6))
    for _ in range(3):
        g = (A @ x[..., None])[..., 0] + b
        x = acc.step([0], x, g)
    assert acc.extrapolated[0] and not np.array_equal(x, g)
    assert np.array_equal(acc.retreat([0]), g) and acc.count[0] == 0 and not acc.extrapolated[0]
    with pytest.raises(ValueError):
        acc.retreat([0])


def test_positive_definite_checks_every_matrix_of_an_item():
    good = np.stack([np.eye(3), 2 * np.eye(3)])
    bad = good.copy()
    bad[1, 2, 2] = -1e-3
    nan = good.copy()
    nan[0, 0, 1] = np.nan
    assert positive_definite(np.stack([good, good])).tolist() == [True, True]
    assert positive_definite(np.stack([good, bad, nan])).tolist() == [True, False, False]
    assert positive_definite(np.eye(2)[None]).tolist() == [True]


def test_out_of_reach_never_stops_a_linear_iteration_that_settles_within_its_budget():
    """A linear iteration's relative change shrinks by ρ an iteration: where ρ^k r0 reaches the tolerance within the
    budget, no prefix is called out of reach (the rate it extrapolates is exact, the iterations it needs are those
    left at most); where it would need far more, it stops at its first judgment, two windows in, and its count of
    the iterations needed is the closed form's."""
    from designer.anderson import REACH_WINDOW, out_of_reach

    tol, budget = 1e-9, 1000
    for rho in (0.5, 0.9, 0.97, 0.975, 0.979):
        r = 0.8 * rho ** np.arange(budget)
        settles = int(np.argmax(r <= tol)) if (r <= tol).any() else None
        assert settles is not None and settles < budget, rho
        assert all(out_of_reach(r[:k], tol, budget) is None for k in range(1, settles + 1)), rho
    r = 0.8 * 0.999 ** np.arange(budget)  # needs about 20 700 iterations: out of reach at once
    assert all(out_of_reach(r[:k], tol, budget) is None for k in range(1, 2 * REACH_WINDOW))
    why = out_of_reach(r[:2 * REACH_WINDOW], tol, budget)
    need = np.log(tol / r[2 * REACH_WINDOW - 1]) / np.log(0.999)
    assert why is not None and f"about {need:.3g} more" in why and "beyond the 1000 allowed" in why


def test_out_of_reach_calls_a_stalled_or_growing_change_out_of_reach_and_not_a_settled_one():
    from designer.anderson import REACH_WINDOW, out_of_reach

    k = 2 * REACH_WINDOW
    stalled = np.full(k, 4e-3)
    growing = 4e-3 * 1.001 ** np.arange(k)
    assert "stopped shrinking" in out_of_reach(stalled, 1e-9, 1000)
    assert "stopped shrinking" in out_of_reach(growing, 1e-9, 1000)
    assert out_of_reach(np.r_[stalled[:-1], 1e-10], 1e-9, 1000) is None  # at the tolerance: the caller's to stop
    assert out_of_reach(np.r_[stalled[:-1], np.nan], 1e-9, 1000) is None  # not finite: the caller's to judge
    jumpy = 0.8 * 0.97 ** np.arange(k) * np.where(np.arange(k) % 7 == 0, 5.0, 1.0)  # accelerated jumps on a rate
    assert out_of_reach(jumpy, 1e-9, 1000) is None
