"""Each built-in study's headline numbers, recomputed independently from the library primitives.

The six studies are configurations of one pipeline (:mod:`studies.pipeline`); their numbers
for a given seed must not change with a refactoring.  Every test here runs one study at a
small size through :func:`studies.pipeline.run_study` and recomputes one or two of its
headline numbers a second way: from the scenario (``load_scenario``), the simulators
(:mod:`designer.simulate`, :mod:`filters.attacks`, :mod:`filters.encryption`), the filters
(``run_consensus``, ``run_ekf``, the NumPy engine ``run_sir``, ``run_sis``) and the
likelihood builders, following each study's *documented* random-stream layout (run ``r``
draws from ``SeedSequence(seed, spawn_key=(r,))`` and the ``.spawn(n)`` layout its module
docstring states) and its *documented* metric definition.  Nothing calls a study's private
task functions, and no number is copied from a run: a change of streams, seeds, chunking
or metric definitions in a study makes its test fail.

Tolerances.  Where a study filters with the same code path as the recomputation
(``run_consensus``, ``run_ekf``, ``run_sir``) the numbers agree to 1e-12.
Where the study uses the fused numba kernels (``engine="fast"``) and the recomputation the
NumPy engine ``run_sir`` or ``run_sis`` with the same Generator, the two agree per run to about 1e-10
(tests/test_fastsir.py, tests/test_fast_edpf.py, tests/test_fused_sis.py: same draws, different order of
floating-point operations), so the metrics are compared with a relative tolerance of 1e-8.

The runs are simulated and filtered one at a time here (every study gives each run its own
Generators, so a run's numbers must not depend on the other runs of its chunk), which also
checks that the study's batching of a chunk's runs does not leak into its numbers.
"""
from __future__ import annotations

import numpy as np

import rules
from designer.design import DesignOptions, make_design
from designer.simulate import simulate, simulate_runs
from filters.attacks import (attack_pattern, bias_attack, binary_sensor_channel, channel_draws, deception_attack,
                             receive, round_robin_schedule, simulate_attacks, uplink_attacks)
from filters.binary import binary_loglik
from filters.consensus import run_consensus
from filters.distributed import run_hcmci, run_kcf
from filters.edpf import interval_loglik, received
from filters.ekf import run_ekf
from filters.encryption import transmit
from filters.fdi import run_sis
from filters.particle import run_sir
from filters.rrp import rrp_loglik, wrap_angles
from filters.uplink import fdi_covariances, split_received, uplink_loglik
from studies.pipeline import run_study
from studies.scenarios import load_scenario

SAME_PATH = 1e-12  # the study and the recomputation run the same code
FUSED_VS_NUMPY = 1e-8  # fused numba kernels vs run_sir: ~1e-10 per run (operation order), see the module docstring


def run_ss(seed: int, r: int) -> np.random.SeedSequence:
    """Run ``r``'s seed, as every study documents it."""
    return np.random.SeedSequence(seed, spawn_key=(r,))


def rng(ss: np.random.SeedSequence) -> np.random.Generator:
    return np.random.default_rng(ss)


def curve_average(e2: np.ndarray) -> float:
    """``studies.results.error_metrics``' "average RMSE": the mean over steps of sqrt(mean over runs of e2)."""
    return float(np.mean(np.sqrt(np.mean(e2, axis=0))))


def simulate_scenario(sc, ss: np.random.SeedSequence, steps: int):
    """One run of the scenario (the paper's fixed x0 when it has one) from a fresh Generator on ``ss``."""
    return simulate(sc.model, steps, rng(ss), x0=sc.x0, inputs=sc.inputs(steps))


# ----------------------------------------------------------------------------- consensus-robot (seed 003)
def test_consensus_robot_paper_design_rmse():
    """consensus-robot, paper mode: "consensus-EKF (paper, tau=0.01)", "KCF" and "HCMCI" rmse_position.

    Run r: ``SeedSequence(seed, spawn_key=(r,)).spawn(2)`` = (truth and measurements, channel
    attacks); the paper design (the scenario's design defaults in mode "paper") on every node,
    and the literature's filters (``run_kcf``, ``run_hcmci`` with the default L = 1) on the same attacks;
    RMSE_position = sqrt(mean over runs, nodes and steps 1..K of the squared position error).
    """
    seed, runs, steps = 11, 3, 8
    res = run_study("consensus-robot", runs=runs, seed=seed, quiet=True, overrides={"steps": steps},
                    options=DesignOptions(mode="paper")).results
    sc = load_scenario("indoor-robot", {"steps": steps})
    m, net = sc.model, sc.network
    x0, u0 = sc.operating_point
    opts = (sc.design or DesignOptions()).merged(DesignOptions(mode="paper"))
    design = make_design(m, net, rule=rules.get("paper"), delta=sc.resolved_attacks.delta, options=opts, x0=x0, u0=u0)
    assert design.tau == 0.01
    pos = list(m.position_index)
    e2 = {"paper": [], "KCF": [], "HCMCI": []}  # KCF, HCMCI (filters.distributed, L = 1) on the same attacks
    for r in range(runs):
        traj_ss, att_ss = run_ss(seed, r).spawn(2)
        traj = simulate_scenario(sc, traj_ss, steps)
        att = simulate_attacks(net, steps, m.n_x, rng(att_ss), sc.resolved_attacks.signal)
        for key, out in (("paper", run_consensus(m, net, traj.z, design, inputs=traj.inputs, attacks=att)),
                         ("KCF", run_kcf(m, net, traj.z, inputs=traj.inputs, attacks=att)),
                         ("HCMCI", run_hcmci(m, net, traj.z, iterations=1, inputs=traj.inputs, attacks=att))):
            assert out.diverged is None
            err = traj.x[1:, None, :] - out.x_post[1:]  # (K, nodes, n_x)
            e2[key].append((err[..., pos] ** 2).sum(-1))
    for name, key in (("consensus-EKF (paper, tau=0.01)", "paper"), ("KCF", "KCF"), ("HCMCI", "HCMCI")):
        f = res["filters"][name]
        assert f["diverged_runs"] == []
        np.testing.assert_allclose(f["rmse_position"], float(np.sqrt(np.mean(e2[key]))), rtol=SAME_PATH, err_msg=name)


# ----------------------------------------------------------------------------- comparison
def test_comparison_centralized_filters_rmse():
    """comparison on indoor-robot, sweeps off: the centralized PFs', the EKF's, KCF's and HCMCI's rmse_position.

    Run r: ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` = (truth, channel draws, particle
    filters); the uplinks use the diagonal of the channel draws and KCF, HCMCI (``hcmci_iterations=2``)
    the node-to-node channels of the same draws (mean over nodes too); the particle filters at the
    main setting draw from ``spawn(3)[2].spawn(3)`` = (attack-aware PF, PF trusting every
    packet, sweep batch).  RMSE = sqrt(mean over runs and steps of the squared position error).
    """
    seed, runs, steps, M = 5, 2, 6, 40
    res = run_study("comparison", ["indoor-robot"], runs=runs, particles=M, seed=seed, quiet=True,
                    sweep_values=(), overrides={"steps": steps}, hcmci_iterations=2).results
    sc = load_scenario("indoor-robot", {"steps": steps})
    m, n = sc.model, sc.network.n_nodes
    att = sc.resolved_attacks
    signal = att.signal
    covs = fdi_covariances(m, m.prior.mean, signal)
    # the probability that a received packet was falsified (uniform uplinks on this scenario)
    dos, fdi = float(att.uplink_dos[0]), float(att.uplink_fdi[0])
    assert np.all(att.uplink_dos == dos) and np.all(att.uplink_fdi == fdi)
    q = fdi / (1.0 - dos)
    pos = list(m.position_index)
    e2 = {"aware": [], "plain": [], "ekf": [], "kcf": [], "hcmci": []}
    for r in range(runs):
        ts, cs, fs = run_ss(seed, r).spawn(3)
        traj = simulate_scenario(sc, ts, steps)
        u, s = channel_draws(steps, n, rng(cs))
        # KCF and HCMCI (L = 2) on the node-to-node channels of the same draws, every node's estimate scored
        att_net = attack_pattern(sc.network, u, s, m.n_x, signal)
        for key, out in (("kcf", run_kcf(m, sc.network, traj.z, inputs=traj.inputs, attacks=att_net)),
                         ("hcmci", run_hcmci(m, sc.network, traj.z, iterations=2, inputs=traj.inputs,
                                             attacks=att_net))):
            e2[key].append(((traj.x[1:, None, pos] - out.x_post[1:][..., pos]) ** 2).sum(-1))
        y = receive(m, traj.x, traj.z, uplink_attacks(u, s, m.n_x, dos_prob=att.uplink_dos,
                                                      fdi_prob=att.uplink_fdi, signal=signal))
        pf_ss = fs.spawn(3)
        for key, c, prob in (("aware", 0, q), ("plain", 1, 0.0)):
            out = run_sir(m, y[None], rng(pf_ss[c]), particles=M, runs=1, inputs=traj.inputs,
                          loglik=uplink_loglik(m, fdi_prob=prob, fdi_covs=covs)).detail
            e2[key].append(((traj.x[1:, pos] - out.mean[0][1:, pos]) ** 2).sum(-1))
        values, avail = split_received(m, y)
        xs = run_ekf(m, values, available=avail, inputs=traj.inputs).x
        e2["ekf"].append(((traj.x[1:, pos] - xs[1:, pos]) ** 2).sum(-1))
    f = res["filters"]
    for name, key in (("centralized PF (attack-aware)", "aware"), ("centralized PF (trusts every packet)", "plain"),
                      ("centralized EKF (trusts every packet)", "ekf"), ("KCF", "kcf"), ("HCMCI", "hcmci")):
        assert f[name]["diverged_runs"] == 0
        np.testing.assert_allclose(f[name]["rmse_position"], float(np.sqrt(np.mean(e2[key]))), rtol=SAME_PATH,
                                   err_msg=name)


# ----------------------------------------------------------------------------- rrp-deception (seed 000)
def test_rrp_deception_table1_rmse():
    """rrp-deception (fast engine), sweep off: RRP-PF-DA's, RRP-SPF-NM's and the linear-domain row's rmse_position
    and collapses.

    Run r: ``SeedSequence(seed, spawn_key=(r,)).spawn(4)`` = (truth, Round-Robin attacks,
    all-sensor attacks, filters); the truth by ``simulate_runs`` (its per-run draws first); filter configuration
    c draws from ``spawn(4)[3].spawn(n)[c]`` (RRP-PF-DA is c = 0, RRP-SPF-NM c = 2, the linear row c = 4 of
    n = 5).  The scheduled sensor's packet, bearings wrapped;
    RRP-PF-DA filters the deceived packets with the attack-aware likelihood (14), RRP-SPF-NM
    the clean ones with the standard likelihood, the linear row the deceived ones with the standard likelihood
    and linear-domain weights (``run_sir(linear_weights=True)``, the reference).  The metric is error_metrics'
    average RMSE.
    """
    seed, runs, steps, M = 3, 3, 25, 60
    res = run_study("rrp-deception", runs=runs, particles=M, seed=seed, quiet=True, sweep=(),
                    overrides={"steps": steps}).results
    assert res["engine"] == "fast"
    sc = load_scenario("target-range-bearing", {"steps": steps})
    m, ch = sc.model, sc.channel
    angles = sorted({j for _, j in m.angle_components})
    sched = round_robin_schedule(steps, m.n_sensors, ch.start)
    eta = ch.deception_prob
    lin = "RRP-SPF-DA (linear-domain weights)"
    ll = {"RRP-PF-DA": rrp_loglik(m, sched, attack_prob=eta, signal=ch.deception, angles=angles),
          "RRP-SPF-NM": rrp_loglik(m, sched, attack_prob=0.0, angles=angles)}
    ll[lin] = ll["RRP-SPF-NM"]
    pos = list(m.position_index)
    e2 = {"RRP-PF-DA": [], "RRP-SPF-NM": [], lin: []}
    collapsed = 0
    for r in range(runs):
        s_truth, s_rr, _s_all, s_filters = run_ss(seed, r).spawn(4)
        tr = simulate_runs(m, steps, [rng(s_truth)], x0=sc.x0, inputs=sc.inputs(steps))
        y_rr = wrap_angles(tr.per_sensor(m)[0], angles)[np.arange(steps), sched]  # (K, n_y): the scheduled packets
        attacked = deception_attack(y_rr, eta, ch.deception, rng(s_rr)).y
        data = {"RRP-PF-DA": attacked, "RRP-SPF-NM": y_rr, lin: attacked}
        streams = s_filters.spawn(5)
        for name, c in (("RRP-PF-DA", 0), ("RRP-SPF-NM", 2), (lin, 4)):
            out = run_sir(m, data[name][None], rng(streams[c]), particles=M, runs=1, loglik=ll[name],
                          linear_weights=name == lin).detail
            e2[name].append(((tr.x[0][1:, pos] - out.mean[0][1:, pos]) ** 2).sum(-1))
            collapsed += int(out.collapsed.sum()) if name == lin else 0
    for name in e2:
        np.testing.assert_allclose(res["filters"][name]["rmse_position"], curve_average(np.array(e2[name])),
                                   rtol=FUSED_VS_NUMPY, err_msg=name)
    assert res["filters"][lin]["engine"] == "fast" and res["filters"][lin]["collapsed_steps"] == collapsed > 0


# ----------------------------------------------------------------------------- binary-multi-attack (seed 002)
def test_binary_multi_attack_rmse():
    """binary-multi-attack (fast engine), sweeps and Table II off: Sta-PF's and Sec-PF's rmse_position.

    Run r: ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` = (truth, channel, filters); the
    channel's draws replayed from a fresh Generator on the channel stream for every setting
    (Sta-PF: every attack probability 0); configuration c draws from ``spawn(3)[2].spawn(n)[c]``
    (Sec-PF c = 0, Sta-PF c = 2).  Sec-PF's likelihood knows the attack probabilities, Sta-PF's
    sets them to 0.  The metric is error_metrics' average RMSE.
    """
    seed, runs, steps, M = 8, 3, 20, 60
    res = run_study("binary-multi-attack", runs=runs, particles=M, seed=seed, quiet=True, sweep=(),
                    table2_particles=(), overrides={"steps": steps}).results
    assert res["engine"] == "fast"
    sc = load_scenario("target-binary-energy", {"steps": steps})
    m, ch = sc.model, sc.channel
    law = dict(threshold=ch.threshold, gain=ch.gain, channel_noise=ch.channel_noise, deception=ch.deception)
    probs = {"Sec-PF": dict(dos_prob=ch.dos_prob, deception_prob=ch.deception_prob, flip_prob=ch.flip_prob),
             "Sta-PF": dict(dos_prob=0.0, deception_prob=0.0, flip_prob=0.0)}
    ll = {name: binary_loglik(m, **law, **p) for name, p in probs.items()}
    pos = list(m.position_index)
    e2 = {"Sec-PF": [], "Sta-PF": []}
    for r in range(runs):
        s_truth, s_channel, s_filters = run_ss(seed, r).spawn(3)
        tr = simulate_scenario(sc, s_truth, steps)
        streams = s_filters.spawn(3)
        for name, c in (("Sec-PF", 0), ("Sta-PF", 2)):
            y = binary_sensor_channel(tr.z, **probs[name], **law, rng=rng(s_channel)).y
            out = run_sir(m, y[None], rng(streams[c]), particles=M, runs=1, loglik=ll[name]).detail
            e2[name].append(((tr.x[1:, pos] - out.mean[0][1:, pos]) ** 2).sum(-1))
    for name in e2:
        np.testing.assert_allclose(res["filters"][name]["rmse_position"], curve_average(np.array(e2[name])),
                                   rtol=FUSED_VS_NUMPY, err_msg=name)


# ----------------------------------------------------------------------------- encrypted-switching (seed 001)
def test_encrypted_switching_ppf_rmse_state():
    """encrypted-switching (fast engine), mean-dynamics row off: PPF's rmse_state (both states).

    Run r: ``SeedSequence(seed, spawn_key=(r,)).spawn(3)`` = (truth, channel, filters); the
    truth by ``simulate_runs`` (its per-run draws first), the channel by ``transmit`` of the
    run on its own Generator (what ``transmit_runs`` does per run), PPF = the mixture proposal
    (the model's transition) with the interval likelihood, systematic resampling at ESS < M/2,
    from a Generator on the run's filter stream.  rmse_state[i] = the mean over t of
    sqrt(mean over runs of (x_i - xhat_i)^2).
    """
    seed, runs, steps, M = 4, 3, 25, 60
    res = run_study("encrypted-switching", runs=runs, particles=M, seed=seed, quiet=True,
                    mean_dynamics_row=False, overrides={"steps": steps}).results
    assert res["engine"] == "fast"
    sc = load_scenario("switching-2d", {"steps": steps})
    m, ch = sc.model, sc.channel
    ll = interval_loglik(m, ch.codec)
    err = []
    for r in range(runs):
        s_truth, s_channel, s_filter = run_ss(seed, r).spawn(3)
        tr = simulate_runs(m, steps, [rng(s_truth)], x0=sc.x0, inputs=sc.inputs(steps))
        tx = transmit(tr.z[0], ch.codec, rng(s_channel), bit_error_prob=ch.bit_error_prob,
                      dropout_prob=ch.dropout_prob)
        out = run_sir(m, received(tx)[None], rng(s_filter), particles=M, runs=1, loglik=ll,
                      resampler="systematic", ess_threshold=0.5).detail
        err.append(tr.x[0, 1:] - out.mean[0, 1:])
    err = np.array(err)  # (runs, T, n_x)
    ours = [curve_average(err[..., i] ** 2) for i in range(m.n_x)]
    np.testing.assert_allclose(res["filters"]["PPF"]["rmse_state"], ours, rtol=FUSED_VS_NUMPY)


# ----------------------------------------------------------------------------- fdi-four-tank (seed 004)
def test_fdi_four_tank_normal_pf_rmse():
    """fdi-four-tank: the normal PF without attack (rmse_truth) and under attack (rmse against it).

    Run r: ``SeedSequence(seed, spawn_key=(r,)).spawn(5)`` = (plant and measurement noise,
    attack occurrences, particles, attack-estimate error, sampled correction); both filters
    draw their particles from a fresh Generator on stream 2 (SIS, no resampling; their
    estimates do not depend on the detector, which only flags attacks).  rmse_truth = mean
    over k of sqrt(mean over runs of ||xhat_k - x_k||^2); the paper's rmse of the normal PF
    under attack is the same against the no-attack normal PF's estimate.
    """
    seed, runs, steps, M = 6, 3, 30, 50
    res = run_study("fdi-four-tank", runs=runs, particles=M, seed=seed, quiet=True,
                    overrides={"steps": steps}).results
    sc = load_scenario("four-tank", {"steps": steps})
    m, ch = sc.model, sc.channel
    truth, clean, attacked = [], [], []
    for r in range(runs):
        streams = run_ss(seed, r).spawn(5)
        # the simulated plant is deterministic by default (plant_noise=False): sc.plant, with the model's draw order
        tr = simulate(sc.plant, steps, rng(streams[0]), x0=sc.x0, inputs=sc.inputs(steps))
        y_att = bias_attack(tr.z, bias=ch.bias, tau=ch.tau, prob=ch.prob, rng=rng(streams[1])).y
        for z, store in ((tr.z, clean), (y_att, attacked)):
            store.append(run_sis(m, z[None], [rng(streams[2])], particles=M, inputs=sc.inputs(steps)).mean[0])
        truth.append(tr.x)
    truth, clean, attacked = np.array(truth), np.array(clean), np.array(attacked)
    f = res["filters"]
    noatt = curve_average(((clean[:, 1:] - truth[:, 1:]) ** 2).sum(-1))
    normal = curve_average(((attacked[:, 1:] - clean[:, 1:]) ** 2).sum(-1))
    # the study's default engine is the fused one (filters.fused.sis_fdi); the recomputation is run_sis
    np.testing.assert_allclose(f["normal PF (no attack)"]["rmse_truth"], noatt, rtol=FUSED_VS_NUMPY)
    np.testing.assert_allclose(f["normal PF (under attack)"]["rmse"], normal, rtol=FUSED_VS_NUMPY)
