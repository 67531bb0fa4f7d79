"""Our bootstrap filter against an independent one from the peer SMC library ``particles`` (issue 5).

With attacks off, on ``target-range-bearing``, our SIR filter
(:func:`filters.particle.run_sir` with the :mod:`filters.rrp` likelihoods) and the
peer's bootstrap filter run on the *same* simulated data: every sensor every step
(the paper's geometry, and one with a sensor behind the target so that bearings
cross ±π), and the Round-Robin single packet per step.  Per-run time-averaged RMSEs
are compared paired by run (``|mean difference| < 4 SE``, and a Wilcoxon signed-rank
test against run-level shifts); so are the log marginal likelihood estimates.
Negative controls show the statistics detect real modelling faults.

The peer's side is a second implementation written here from the scenario's
parameters only: its own constant-velocity matrices, its own range-bearing glint
likelihood (scipy.stats densities, bearing residuals wrapped through the complex
exponential), the peer's samplers and resampling.  Nothing of ``designer.noise``, of
the CasADi model or of ``filters`` enters it.

Time alignment: our ``z[k]`` measures ``x_{k+1}`` and our prior is on ``x_0``; the
peer's ``PY(t, ...)`` at ``t = 0`` already weights ``X_0`` by ``data[0]``.  So the peer's
``X_t`` is our ``x_{t+1}``: its ``PX0`` is our prior pushed through one transition,
``N(F m0, F P0 Fᵀ + Q)``, and its data are ``z[0 .. K-1]``.
:func:`test_alignment_on_a_linear_gaussian_model` checks that reading against the
peer's exact Kalman filter.

The peer draws from NumPy's global random state: it is seeded here and the state is
restored afterwards.  Our filter only ever sees its own Generator.
"""
from __future__ import annotations

import functools

import casadi as ca
import numpy as np
import pytest
from scipy import stats

particles = pytest.importorskip("particles")
from particles import distributions as dists  # noqa: E402
from particles import kalman  # noqa: E402
from particles import state_space_models as ssms  # noqa: E402
from particles.collectors import Moments  # noqa: E402

from designer import Gaussian, Model, Sensor, simulate  # noqa: E402
from filters.attacks import round_robin_schedule  # noqa: E402
from filters.particle import run_sir  # noqa: E402
from filters.rrp import all_sensors_loglik, rrp_loglik, wrap_angles  # noqa: E402
from studies.scenarios import load_scenario  # noqa: E402

RUNS, STEPS, PARTICLES = 36, 100, 400
N_SIGMA = 4.0
WILCOXON_LEVEL = 1e-3
LOGLIK_STEPS = 30
# Sensor 4 behind the target's path: about a third of its bearings lie within 0.15 rad of ±π.
BEHIND = [[0.0, 0.0], [0.0, 30.0], [0.0, 60.0], [80.0, 35.0]]
CASES = {
    # name: (scenario overrides, Round-Robin single packet per step?)
    "all-sensors": ({}, False),
    "all-sensors-wrapping": ({"sensor_positions": BEHIND}, False),
    "round-robin": ({}, True),
}
SEEDS = {"all-sensors": 101, "all-sensors-wrapping": 102, "round-robin": 103}


# --------------------------------------------------------------- the peer's model
def _cv_matrices(period: float, accel_std: float):
    """Constant-velocity F and white-noise-acceleration Q for ``[px, vx, py, vy]``, from scratch."""
    T = period
    F1 = np.array([[1.0, T], [0.0, 1.0]])
    Q1 = accel_std**2 * np.array([[T**3 / 3.0, T**2 / 2.0], [T**2 / 2.0, T]])
    F, Q = np.zeros((4, 4)), np.zeros((4, 4))
    for s in (slice(0, 2), slice(2, 4)):
        F[s, s], Q[s, s] = F1, Q1
    return F, Q


def _pushed_prior(F, Q, m0, P0):
    """Law of ``x_1`` when ``x_0 ~ N(m0, P0)``: the peer's ``X_0`` (its ``data[0]`` is our ``z[0]``)."""
    return F @ m0, F @ P0 @ F.T + Q


class GlintRangeBearing(dists.ProbDist):
    """Packets ``[range, bearing]`` of the given sensors for states ``x`` (N, 4); product of glint mixtures.

    Each packet's noise is ``(1 - κ) N(0, Σ1) + κ N(0, Σ2)`` with diagonal Σ (the scenario's
    parameters are the diagonals), so each component factorises into two scalar normals.
    """

    def __init__(self, x, positions, kappa, sd1, sd2):
        self.x, self.positions = x, np.atleast_2d(positions)
        self.kappa, self.sd1, self.sd2 = kappa, sd1, sd2
        self.dim = 2 * len(self.positions)

    def logpdf(self, y):
        y = np.asarray(y, dtype=float).reshape(len(self.positions), 2)
        dx = self.x[:, None, 0] - self.positions[None, :, 0]  # (N, sensors)
        dy = self.x[:, None, 2] - self.positions[None, :, 1]
        res_range = y[None, :, 0] - np.hypot(dx, dy)
        res_bearing = np.angle(np.exp(1j * (y[None, :, 1] - np.arctan2(dy, dx))))  # in (-π, π]
        comp = [
            log_w + stats.norm.logpdf(res_range, scale=sd[0]) + stats.norm.logpdf(res_bearing, scale=sd[1])
            for log_w, sd in ((np.log1p(-self.kappa), self.sd1), (np.log(self.kappa), self.sd2))
        ]
        return np.logaddexp(comp[0], comp[1]).sum(axis=1)


class PeerRangeBearing(ssms.StateSpaceModel):
    """target-range-bearing for ``particles``; ``X_t`` is the scenario's ``x_{t+1}``.

    ``schedule`` (or None for every sensor at every step) gives the sensor whose packet ``data[t]`` is.
    """

    def PX0(self):
        mean, cov = _pushed_prior(self.F, self.Q, self.m0, self.P0)
        return dists.MvNormal(loc=mean, cov=cov)

    def PX(self, t, xp):
        return dists.MvNormal(loc=xp @ self.F.T, cov=self.Q)

    def PY(self, t, xp, x):
        pos = self.positions if self.schedule is None else self.positions[[self.schedule[t]]]
        return GlintRangeBearing(x, pos, self.kappa, self.sd1, self.sd2)


def _peer_model(params: dict, schedule=None) -> PeerRangeBearing:
    F, Q = _cv_matrices(params["period"], params["accel_std"])
    return PeerRangeBearing(
        F=F, Q=Q, m0=np.asarray(params["x0"], float), P0=np.diag(params["prior_var"]),
        positions=np.asarray(params["sensor_positions"], float), kappa=float(params["glint_prob"]),
        sd1=np.sqrt(params["glint_cov1"]), sd2=np.sqrt(params["glint_cov2"]), schedule=schedule,
    )


def _run_peer(model, z, M, seed):
    """The peer's bootstrap filter on every run: weighted means (runs, K, n_x) and log-likelihoods (runs,)."""
    saved = np.random.get_state()
    try:
        np.random.seed(seed)
        means, loglik = [], []
        # ESSrmin = 1: resample whenever ESS < N, i.e. at every step, as ours with ess_threshold = 1.
        for data in z:
            pf = particles.SMC(fk=ssms.Bootstrap(ssm=model, data=data), N=M, resampling="systematic",
                               ESSrmin=1.0, store_history=False, collect=[Moments()])
            pf.run()
            means.append([m["mean"] for m in pf.summaries.moments])
            loglik.append(pf.logLt)
    finally:
        np.random.set_state(saved)
    return np.asarray(means), np.asarray(loglik)


# ------------------------------------------------------------------- statistics
def _rmse_per_run(est, truth, idx):
    """Time-averaged RMSE of components ``idx`` for each run (runs,)."""
    e = est[..., idx] - truth[..., idx]
    return np.sqrt((e**2).sum(-1).mean(-1))


def _paired(a, b):
    """Mean and standard error of the run-paired difference ``a - b``."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    return d.mean(), d.std(ddof=1) / np.sqrt(d.size)


# ----------------------------------------------------------------------- fixtures
def _run_case(name: str, seed: int) -> dict:
    """Simulated runs (attacks off), and our filter and the peer's on the same received packets."""
    overrides, rr = CASES[name]
    sc = load_scenario("target-range-bearing", overrides)
    m = sc.model
    tr = sc.simulate(np.random.default_rng(seed), STEPS, batch=RUNS)
    y = tr.per_sensor(m)  # (runs, K, sensors, 2)
    y[..., 1] = wrap_angles(y, [1])[..., 1]  # received bearings in (-π, π], as the channel delivers them
    if rr:
        schedule = round_robin_schedule(STEPS, m.n_sensors, sc.params["rr_start"])
        z = y[:, np.arange(STEPS), schedule]  # (runs, K, 2): the scheduled sensor's packet
        loglik = rrp_loglik(m, schedule, angles=[1])
        loglik_nowrap = rrp_loglik(m, schedule)
    else:
        schedule = None
        z = y.reshape(RUNS, STEPS, -1)
        loglik = all_sensors_loglik(m, angles=[1])
        loglik_nowrap = all_sensors_loglik(m)
    ours = run_sir(m, z, np.random.default_rng(seed + 1000), particles=PARTICLES, runs=RUNS, loglik=loglik).detail
    peer = _peer_model(sc.params, schedule)
    peer_mean, _ = _run_peer(peer, z, PARTICLES, seed=seed + 2000)
    return dict(name=name, sc=sc, truth=tr.x[:, 1:], z=z, loglik=loglik, loglik_nowrap=loglik_nowrap,
                ours=ours, peer_model=peer, peer_mean=peer_mean)


@functools.lru_cache(maxsize=None)
def _case(name: str) -> dict:
    return _run_case(name, SEEDS[name])


@pytest.fixture(params=list(CASES))
def case(request):
    return _case(request.param)


def _rmse_pair(c, idx, ours_mean=None):
    ours_mean = c["ours"].mean[:, 1:] if ours_mean is None else ours_mean
    return _rmse_per_run(ours_mean, c["truth"], idx), _rmse_per_run(c["peer_mean"], c["truth"], idx)


# -------------------------------------------------------------------------- tests
def test_peer_model_is_the_scenario_model():
    """Preconditions: the peer's hand-written F, Q and packet density are the scenario's, point by point
    (bearings crossing ±π included), so any difference below is the filters', not the models'."""
    sc = load_scenario("target-range-bearing", {"sensor_positions": BEHIND})
    m = sc.model
    F, Q = _cv_matrices(sc.params["period"], sc.params["accel_std"])
    rng = np.random.default_rng(0)
    x = rng.normal([40.0, 0.3, 35.0, 0.3], [25.0, 1.0, 25.0, 1.0], size=(200, 4))
    np.testing.assert_allclose(m.f(x), x @ F.T, atol=1e-12)
    np.testing.assert_allclose(m.process_cov, Q, rtol=1e-12)
    peer = _peer_model(sc.params)
    y = wrap_angles(sc.simulate(rng, 20).per_sensor(m)[-1], [1])  # a packet of each sensor, (4, 2)
    y[3, 1] = np.pi - 0.01  # sensor 4 sees the target just past ±π
    np.testing.assert_allclose(peer.PY(0, None, x).logpdf(y.ravel()),
                               all_sensors_loglik(m, angles=[1])(x[None], 1, y.ravel()[None])[0], rtol=1e-10)


@pytest.mark.parametrize("what", ["position", "velocity"])
@pytest.mark.slow
def test_rmse_matches_peer_bootstrap_filter(case, what):
    """Paired over runs on the same data: |mean RMSE_ours - mean RMSE_peer| < 4 SE of the difference."""
    m = case["sc"].model
    ours, peer = _rmse_pair(case, list(m.position_index if what == "position" else m.velocity_index))
    diff, se = _paired(ours, peer)
    assert abs(diff) < N_SIGMA * se, (case["name"], what, ours.mean(), peer.mean(), diff, se)


@pytest.mark.slow
def test_no_run_level_shift_against_the_peer(case):
    """Wilcoxon signed-rank test on the paired position RMSEs.

    Two implementations of one algorithm on the same data give exchangeable pairs, so the
    run differences are symmetric about 0 whatever their tails.  This complements the mean
    test: a filter that loses the track in a few runs inflates the SE of the mean difference
    as much as the difference itself, while the ranks still see it (see the wrap control).
    """
    ours, peer = _rmse_pair(case, list(case["sc"].model.position_index))
    p = stats.wilcoxon(ours, peer).pvalue
    assert p > WILCOXON_LEVEL, (case["name"], p)


@pytest.mark.slow
def test_log_likelihood_matches_peer(case):
    """Log marginal likelihood estimates log p(z_1:k) of the same short series agree within Monte Carlo error.

    A short series keeps the estimates' left tail (a run where a filter nearly loses the track
    costs hundreds of nats) from dominating the paired differences.
    """
    m, k = case["sc"].model, LOGLIK_STEPS
    z = np.ascontiguousarray(case["z"][:, :k])
    ours = run_sir(m, z, np.random.default_rng(21), particles=PARTICLES, runs=RUNS, loglik=case["loglik"]).detail.loglik
    _, peer = _run_peer(case["peer_model"], z, PARTICLES, seed=22)
    diff, se = _paired(ours, peer)
    assert abs(diff) < N_SIGMA * se, (case["name"], ours.mean(), peer.mean(), diff, se)


def _faulty_filter(fault: str, case: dict):
    """Our filter with a deliberate modelling fault, on the same data as the peer's."""
    m, ll = case["sc"].model, case["loglik"]
    if fault == "glint-5x-wide":  # likelihood tempered by 1/25: about a measurement noise 5x too wide
        return run_sir(m, case["z"], np.random.default_rng(8), particles=PARTICLES, runs=RUNS,
                       loglik=lambda x, k1, z: ll(x, k1, z) / 25.0).detail
    assert fault == "process-noise-x10"
    m10 = load_scenario("target-range-bearing", {"accel_std": case["sc"].params["accel_std"] * np.sqrt(10.0)}).model
    return run_sir(m10, case["z"], np.random.default_rng(8), particles=PARTICLES, runs=RUNS,
                   loglik=all_sensors_loglik(m10, angles=[1])).detail


@pytest.mark.parametrize("fault", ["glint-5x-wide", "process-noise-x10"])
def test_negative_control_wrong_model_is_detected(fault):
    """The mean test can fail: a filter with a wrong noise model differs from the peer beyond 4 SE."""
    case = _case("all-sensors")
    est = _faulty_filter(fault, case).mean[:, 1:]
    m = case["sc"].model
    for idx in (m.position_index, m.velocity_index):
        diff, se = _paired(*_rmse_pair(case, list(idx), est))
        assert diff > N_SIGMA * se, (fault, idx, diff, se)


def test_negative_control_unwrapped_bearings_are_detected():
    """With a sensor behind the target, dropping the bearing wrap loses the track in some runs: the rank
    test flags it (the mean test alone does not: the few huge differences also inflate its SE)."""
    case = _case("all-sensors-wrapping")
    bad = run_sir(case["sc"].model, case["z"], np.random.default_rng(9), particles=PARTICLES, runs=RUNS,
                  loglik=case["loglik_nowrap"]).detail
    ours, peer = _rmse_pair(case, list(case["sc"].model.position_index), bad.mean[:, 1:])
    assert stats.wilcoxon(ours, peer).pvalue < WILCOXON_LEVEL


@pytest.mark.slow
def test_alignment_on_a_linear_gaussian_model():
    """On a linear-Gaussian CV model our filter and the peer's both follow the peer's exact Kalman filter
    with the prior pushed one step, and not the one read without the shift."""
    T, K, M, runs = 1.0, 30, 500, 20
    F, Q = _cv_matrices(T, 0.5)
    G = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    Rm = np.eye(2)
    # A tight prior and a fast target, so that mistaking the prior on x_0 for one on x_1 shows.
    m0, P0 = np.array([0.0, 3.0, 0.0, -2.0]), np.diag([0.04, 0.01, 0.04, 0.01])
    x = ca.SX.sym("x", 4)
    model = Model("cv-linear", x, ca.mtimes(ca.DM(F), x), [Sensor("p", ca.mtimes(ca.DM(G), x), Gaussian.zero_mean(Rm))],
                  Gaussian.zero_mean(Q), Gaussian(m0, P0))
    tr = simulate(model, K, np.random.default_rng(3), batch=runs)
    ours = run_sir(model, tr.z, np.random.default_rng(4), particles=M, runs=runs).detail
    mu1, cov1 = _pushed_prior(F, Q, m0, P0)  # the same shift as PeerRangeBearing.PX0
    pushed = kalman.MVLinearGauss(F=F, G=G, covX=Q, covY=Rm, mu0=mu1, cov0=cov1)
    unshifted = kalman.MVLinearGauss(F=F, G=G, covX=Q, covY=Rm, mu0=m0, cov0=P0)
    peer_mean, peer_loglik = _run_peer(pushed, tr.z, M, seed=5)

    def kf(ssm, data):
        k = kalman.Kalman(ssm=ssm, data=data)
        k.filter()
        return (np.array([f.mean for f in k.filt]), np.sqrt(np.array([np.diag(f.cov) for f in k.filt])),
                float(np.sum(k.logpyt)))

    dev_ours, dev_peer, dev_unshifted, exact, exact_unshifted = [], [], [], [], []
    for r in range(runs):
        mean, sd, ll = kf(pushed, tr.z[r])
        mean_u, _, ll_u = kf(unshifted, tr.z[r])
        dev = lambda est: np.sqrt(np.mean(((est - mean) / sd) ** 2))  # noqa: E731  RMS in posterior sds
        dev_ours.append(dev(ours.mean[r, 1:]))
        dev_peer.append(dev(peer_mean[r]))
        dev_unshifted.append(dev(mean_u))
        exact.append(ll)
        exact_unshifted.append(ll_u)
    exact, exact_unshifted = np.array(exact), np.array(exact_unshifted)
    # Both particle filters sit a small fraction of a posterior sd from the exact filter ...
    assert np.median(dev_ours) < 0.4 and np.median(dev_peer) < 0.4, (np.median(dev_ours), np.median(dev_peer))
    # ... where the unshifted reading is about one sd away at every run.
    assert min(dev_unshifted) > 0.8, min(dev_unshifted)
    # Log-likelihoods: ours and the peer's agree, and ours is that of the pushed prior, not the unshifted one.
    diff, se = _paired(ours.loglik, peer_loglik)
    assert abs(diff) < N_SIGMA * se, (diff, se)
    assert np.median(np.abs(ours.loglik - exact)) < np.median(np.abs(ours.loglik - exact_unshifted)) / 3
