"""cfdesign export --target c: a design's node filter as C99 sources, compiled with the system's C compiler and
replayed against the Python node filter (make test), on the indoor robot and on a user's model file."""
from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest

import studies
from designer.validation import InputError
from studies.cli import main
from test_recorded import USER_MODEL  # noqa: E402 (tests/ is on the path: the user's cart with posts)

CC = shutil.which("cc") or shutil.which("gcc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler")  # a fresh machine has gcc: CI always runs these


def make_test(directory) -> subprocess.CompletedProcess:
    """``make test`` in ``directory`` (or, without make, the Makefile's two commands with the C compiler)."""
    if shutil.which("make"):
        return subprocess.run(["make", "-s", "test"], cwd=directory, capture_output=True, text=True, timeout=300)
    build = subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-o", "cfd_test", "cfd_test.c", "cfd_node.c",
                            "cfd_model.c", "-lm"], cwd=directory, capture_output=True, text=True, timeout=300)
    if build.returncode:
        return build
    return subprocess.run(["./cfd_test", "replay.txt"], cwd=directory, capture_output=True, text=True, timeout=300)


def float_test(directory) -> subprocess.CompletedProcess:
    """The export built with ``-DCFD_REAL=float`` (every file, under the Makefile's warnings) and its replay run: the
    node in float, checked at float's tolerance (the driver scales it by FLT_EPSILON / DBL_EPSILON)."""
    build = subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-DCFD_REAL=float", "-o",
                            "cfd_test_float", "cfd_test.c", "cfd_node.c", "cfd_model.c", "-lm"], cwd=directory,
                           capture_output=True, text=True, timeout=300)
    assert build.returncode == 0 and "warning" not in build.stderr, build.stderr
    return subprocess.run(["./cfd_test_float", "replay.txt"], cwd=directory, capture_output=True, text=True,
                          timeout=300)


def mutable_static_data(directory) -> list[str]:
    """The symbols of ``cfd_node.c`` and ``cfd_model.c``, compiled in ``directory``, that live in writable static
    memory (the ``.data`` and ``.bss`` sections, static locals included), by ``nm``: none, when every node's work is
    in its own struct and nodes may step side by side."""
    if shutil.which("nm") is None:
        pytest.skip("no nm")
    objects = []
    for name in ("cfd_node", "cfd_model"):
        subprocess.run([CC, "-std=c99", "-O2", "-c", f"{name}.c", "-o", f"{name}.static.o"], cwd=directory, check=True,
                       capture_output=True, timeout=300)
        objects.append(f"{name}.static.o")
    table = subprocess.run(["nm", "--format=sysv", *objects], cwd=directory, check=True, capture_output=True,
                           text=True).stdout
    return [line.split("|")[0].strip() for line in table.splitlines()
            if line.count("|") >= 6 and line.split("|")[-1].strip() in (".data", ".bss")]


def moved_replay_fails(out, line: int, at, what: str, nodes) -> None:
    """The check has power: ``replay.txt``'s number ``at`` (an index into line ``line``'s cells, the first component
    ``what`` of an expected estimate or prediction) moved by 1e-7 (relative) makes ``make test`` fail, naming the
    step, the node (of ``nodes``, the exported ones in order), the quantity and both values."""
    lines = (out / "replay.txt").read_text().splitlines()
    cells = lines[line].split()
    want = float(cells[at])
    cells[at] = repr(want * (1 + 1e-7) + 1e-9)
    lines[line] = " ".join(cells)
    (out / "replay.txt").write_text("\n".join(lines) + "\n")
    bad = make_test(out)
    step, node = (line - 1) // len(nodes) + 1, nodes[(line - 1) % len(nodes)]
    named = re.search(rf"^step {step}, node {node}: {re.escape(what)}\[0\] is (\S+) in C, (\S+) in Python", bad.stdout,
                      re.M)
    assert bad.returncode != 0 and named, bad.stdout
    assert float(named.group(2)) == float(cells[at]) and abs(float(named.group(1)) - want) <= 1e-9 * abs(want)
    assert int(re.search(r"(\d+) above the tolerance", bad.stdout).group(1)) >= 1


def falsified_packet_taken_as_sent_fails_the_network_run(out, scenario, design_dir) -> None:
    """The network run has power: the first falsified arrival of ``replay.txt`` (arrival flag 2) relabelled as sent
    (1) makes the network run's C node take its neighbour's own C packet in its place, so ``make test`` fails,
    naming the network run, that step and that node; each step from Python's state takes the log's packet either
    way and still agrees.  The replay's rows: 4 tolerances, the inputs, the node's measurement, then its flags."""
    from studies.scenarios import scenario_of

    sc = scenario_of(scenario)
    net = studies.node_filter(scenario, schedule=design_dir)
    lines = (out / "replay.txt").read_text().splitlines()
    n_nodes = int(lines[0].split()[1])
    for at, line in enumerate(lines[1:], 1):
        node, cells = (at - 1) % n_nodes, line.split()
        first = 4 + sc.model.n_u + sc.model.sensor_dims[node]
        flags = cells[first:first + net.nodes[node].senders.size]
        if "2.0" in flags:
            cells[first + flags.index("2.0")] = "1.0"
            break
    else:
        raise AssertionError("no falsified arrival in the replay")
    lines[at] = " ".join(cells)
    (out / "replay.txt").write_text("\n".join(lines) + "\n")
    bad = make_test(out)
    step = (at - 1) // n_nodes + 1
    assert bad.returncode != 0 and re.search(rf"^network run, step {step}, node {node}: ", bad.stdout, re.M), bad.stdout
    assert re.search(r"^step \d+, node", bad.stdout, re.M) is None, bad.stdout


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    path = tmp_path_factory.mktemp("user") / "cart.py"
    path.write_text(USER_MODEL)
    return path


@pytest.mark.slow
def test_the_robots_relay_design_in_c_replays_the_python_node_filter(tmp_path, capsys):
    """design --mode relay, export, make test: every node's estimate and bound over the design's simulated run (DoS
    and FDI) within 1e-10 of the Python node filter's; the sources need libc and libm only and allocate nothing;
    a replay whose expected numbers are moved by 1e-7 fails."""
    des, out = tmp_path / "design", tmp_path / "c"
    # a parameter set at design time (--set): export rebuilds the model with it (its digest must match)
    assert main(["design", "indoor-robot", "--mode", "relay", "--seed", "2", "--set", "dos_prob=0.15", "--out",
                 str(des)]) in (0, 1)
    assert main(["export", str(des), "--target", "c", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    verdict = json.loads((des / "schedule.json").read_text())["verdict"]
    assert "make -C" in said and ("not certified" in said) == (verdict != "certified")
    assert f"The design's verdict: {verdict} " in (out / "cfd_node.h").read_text()
    run = make_test(out)
    assert run.returncode == 0, run.stdout + run.stderr
    worst = float(re.search(r"largest difference from the Python node filter (\S+)", run.stdout).group(1))
    assert worst <= 1e-10 and "8 nodes" in run.stdout
    sources = {p.name: p.read_text() for p in out.glob("cfd_*.[ch]")}
    includes = {m for text in sources.values() for m in re.findall(r"#include\s*[<\"]([^>\"]+)", text)}
    libc_libm = {"float.h", "math.h", "string.h", "stdio.h", "stdlib.h"}
    assert includes <= libc_libm | {"cfd_model.h", "cfd_node.h"}
    assert not any(re.search(r"\b(malloc|calloc|realloc|free)\s*\(", t) for t in sources.values())
    assert mutable_static_data(out) == []
    single = float_test(out)
    scaled = float(re.search(r"above the tolerance \((\S+);", single.stdout).group(1))
    assert single.returncode == 0 and scaled == pytest.approx(1e-12 * np.finfo(np.float32).eps / np.finfo(float).eps,
                                                              rel=1e-5), single.stdout
    n_x = 3
    moved_replay_fails(out, 5, -n_x * n_x - n_x, "x", range(8))  # the first component of an expected estimate


def test_an_estimates_entry_is_checked_on_its_standard_deviation(tmp_path):
    """make test compares an estimate's x[i] with Python's on max(|x[i]|, sqrt(P[i][i])): at the entry where the
    standard deviation is largest against max(|x[i]|, P[i][i]) (the variance, on which the driver had compared it,
    so that a correct export of a 24-state beam of ours failed), an expected value moved by half the row's tolerance
    times sqrt(P[i][i]) passes and by three times fails, naming that entry."""
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", "indoor-robot", "--mode", "relay", "--seed", "2", "--out", str(des)]) in (0, 1)
    assert main(["export", str(des), "--target", "c", "--out", str(out)]) == 0
    lines = (out / "replay.txt").read_text().splitlines()
    n_x, n_nodes = 3, int(lines[0].split()[1])
    best = None
    for at, line in enumerate(lines[1:], 1):  # each row: 4 tolerances, ..., the expected x, then P
        cells = [float(c) for c in line.split()]
        x, P = cells[-n_x * n_x - n_x:-n_x * n_x], np.reshape(cells[-n_x * n_x:], (n_x, n_x))
        for i in range(n_x):
            ratio = np.sqrt(P[i, i]) / max(abs(x[i]), P[i, i])
            if best is None or ratio > best[0]:
                best = (ratio, at, i, np.sqrt(P[i, i]), min(cells[0], cells[2]))
    ratio, at, i, sd, tol = best
    assert ratio > 4  # the variance's scale would be at most a quarter of the deviation's: the check has power
    for factor, passes in ((0.5, True), (3.0, False)):
        moved = list(lines)
        cells = moved[at].split()
        k = len(cells) - n_x * n_x - n_x + i
        cells[k] = repr(float(float(cells[k]) + factor * tol * sd))
        moved[at] = " ".join(cells)
        (out / "replay.txt").write_text("\n".join(moved) + "\n")
        run = make_test(out)
        assert (run.returncode == 0) == passes, run.stdout
        step, node = (at - 1) // n_nodes + 1, (at - 1) % n_nodes
        assert passes or re.search(rf"^step {step}, node {node}: x\[{i}\] is ", run.stdout, re.M), run.stdout


def test_the_network_runs_tolerances_are_the_same_beside_the_replay_or_after_it(tmp_path, monkeypatch):
    """export runs the network run's drifting copies (designer.export_c.drift_tolerances) in a process of its own
    beside the per-step twins (studies.runner.Background); with one usable core it runs them here, after the replay:
    replay.txt, whose rows start with both tolerances, is the same file bit for bit."""
    import designer.cores

    if designer.cores.usable_cores() < 2:
        pytest.skip("one usable core: the drifting copies run here either way")
    des = tmp_path / "design"
    assert main(["design", "indoor-robot", "--mode", "relay", "--seed", "2", "--out", str(des)]) in (0, 1)
    assert main(["export", str(des), "--target", "c", "--out", str(tmp_path / "beside")]) == 0
    monkeypatch.setattr(designer.cores, "usable_cores", lambda: 1)
    assert main(["export", str(des), "--target", "c", "--out", str(tmp_path / "after")]) == 0
    beside, after = ((tmp_path / d / "replay.txt").read_bytes() for d in ("beside", "after"))
    assert beside == after and len(beside.splitlines()) > 8


@pytest.mark.slow
def test_a_users_flood_design_in_c_replays_a_recorded_log(cart, tmp_path, capsys):
    """The user's cart (a known input, bearings wrapped at +-pi, ranges), its flood design exported for two nodes and
    replayed on a CSV log of another run: make test agrees with the Python node filter; the exported node filter
    is the one studies.node_filter gives (the replay's expected estimates are its)."""
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", str(cart), "--mode", "flood", "--out", str(des)]) in (0, 1)
    assert main(["export", str(des), "--out", str(tmp_path / "said")]) == 0
    verdict = json.loads((des / "schedule.json").read_text())["verdict"]
    assert ("not certified" in capsys.readouterr().out) == (verdict != "certified")
    log = tmp_path / "log.csv"
    sim = studies.simulate(str(cart), seed=9, run=2, out=log)
    files = studies.export(des, out=out, nodes=[3, 5], data=log)
    assert {p.name for p in files} >= {"cfd_node.c", "cfd_node.h", "cfd_model.c", "Makefile", "replay.txt"}
    run = make_test(out)
    assert run.returncode == 0 and "2 nodes" in run.stdout, run.stdout + run.stderr
    net = studies.node_filter(str(cart), schedule=des)
    x, _ = net.run(sim.z, sim.attacks, sim.inputs)
    last = (out / "replay.txt").read_text().splitlines()[-1].split()
    assert np.array_equal([float(v) for v in last[-16 - 4:-16]], x[-1, 5])


@pytest.mark.parametrize("gate", [0.0, 0.05])
def test_the_robots_default_design_in_c_replays_the_python_node_filter(gate, tmp_path, capsys):
    """design without --mode (the paper rule), export, make test: at every step every node's packet (prediction, its
    covariance, whether it is a bound) and its estimate and covariance after the update within 1e-10 of the Python
    consensus node's, over the design's simulated run (DoS and FDI; with the χ² gate, which rejects packets on this
    run), and so are the nodes run as a network on their own packets; a replay whose expected prediction is moved
    by 1e-7 fails, and so does the network run with a falsified packet taken as sent."""
    from designer.design import DesignOptions
    from filters.consensus_batch import run_consensus_batch
    from studies.consensus_design import consensus_design
    from studies.scenarios import load_scenario

    des, out = tmp_path / "design", tmp_path / "c"
    gated = ["--gate", str(gate)] if gate else []
    assert main(["design", "indoor-robot", "--mode", "paper", "--out", str(des)] + gated) in (0, 1)
    assert main(["export", str(des), "--target", "c", "--out", str(out)]) == 0
    meta = json.loads((des / "schedule.json").read_text())
    assert meta["mode"] == "paper" and meta["options"]["mode"] == "paper"
    assert ("not certified" in capsys.readouterr().out) == (meta["verdict"] != "certified")
    header = (out / "cfd_node.h").read_text()
    assert "gain rule paper" in header and f"gate = {gate}" in header
    if gate:  # the gate has work to do on the replayed run
        sc = load_scenario("indoor-robot")
        sim = studies.simulate(sc, seed=int(meta["seed"]))
        ref = run_consensus_batch(sc.model, sc.network, sim.z[None], consensus_design(sc, DesignOptions(gate=gate)),
                                  inputs=sim.inputs, attacks=[sim.attacks]).detail
        assert ref.gate_counts[..., 1].sum() > 0
    run = make_test(out)
    assert run.returncode == 0, run.stdout + run.stderr
    worst = float(re.search(r"largest difference from the Python node filter (\S+)", run.stdout).group(1))
    assert worst <= 1e-10 and "30 steps x 8 nodes" in run.stdout
    sources = {p.name: p.read_text() for p in out.glob("cfd_*.[ch]")}
    assert not any(re.search(r"\b(malloc|calloc|realloc|free)\s*\(", t) for t in sources.values())
    assert mutable_static_data(out) == []
    single = float_test(out)
    assert single.returncode == 0, single.stdout
    network = re.search(r"as a network .* the Python node network (\S+) .*, (\d+) above", run.stdout)
    assert float(network.group(1)) <= 1e-10 and network.group(2) == "0", run.stdout
    if not gate:
        falsified_packet_taken_as_sent_fails_the_network_run(out, "indoor-robot", des)
        return
    n_x = 3
    moved_replay_fails(out, 9, -2 * (n_x * n_x + n_x) - 1, "x_pred", range(8))  # an expected prediction's first


def test_a_users_paper_design_in_c_replays_a_recorded_log(cart, tmp_path):
    """The user's cart designed with the paper rule (its own σ, β, U, V: the defaults break (29) at once), exported
    for two nodes and replayed on a CSV log: make test agrees (the run goes through (28)/(29) failures into the
    fallback, bearings wrapped); the replay's expected estimates are the node network's, and cfdesign filter with the
    design directory (recorded without a mode) gives them too."""
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", str(cart), "--mode", "paper", "--sigma", "0.1", "--beta", "0.05", "--u-scale", "0.001",
                 "--v-scale",
                 "0.001", "--out", str(des)]) in (0, 1)
    log = tmp_path / "log.csv"
    sim = studies.simulate(str(cart), seed=9, run=2, out=log)
    studies.export(des, out=out, nodes=[1, 6], data=log)
    run = make_test(out)
    assert run.returncode == 0 and "18 steps x 2 nodes" in run.stdout, run.stdout + run.stderr
    x, _ = studies.node_filter(str(cart), schedule=des).run(sim.z, sim.attacks, sim.inputs)
    assert np.isfinite(x).all()
    last = (out / "replay.txt").read_text().splitlines()[-1].split()
    assert np.array_equal([float(v) for v in last[-16 - 4:-16]], x[-1, 6])
    assert np.array_equal(studies.filter(str(cart), log, schedule=des).x_hat, x)


def test_a_diverging_paper_design_is_replayed_step_by_step_up_to_its_divergence(tmp_path, capsys, monkeypatch):
    """The README's ring with the paper rule's defaults leaves (28) at step 4 and its fallback's bound explodes
    (condition numbers 3e6 at step 4, 1e15 by step 7, where it diverges).  Each step of make test starts from the
    Python node's state, so every step before the divergence is replayed and agrees, although the nodes run as a
    network drift beyond 1e-10 (which failed the check before it re-synchronised): the network run is checked at
    the drift of a perturbed Python network, which grows step by step (in float it passes its cap: information
    there); at a flat 1e-12 it fails correct code.  Its ill-conditioned steps are checked at their measured
    sensitivity: at a flat 1e-12 they fail correct code.  A node step too ill-conditioned for the check (here: a cap
    lowered to 1e-9) is information, counted and named by export and by make test, and the steps after it are
    checked (a changed number after one fails)."""
    import pathlib

    import designer.export_c

    model = tmp_path / "ring.py"
    model.write_text((pathlib.Path(__file__).parents[1] / "examples" / "ring_model.py").read_text())
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", str(model), "--mode", "paper", "--seed", "1", "--out", str(des)]) == 1
    assert main(["export", str(des), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "diverged at step 7 of the replayed run" in said and "replay.txt holds the 6 steps before" in said
    run = make_test(out)
    assert run.returncode == 0 and "6 steps x 4 nodes" in run.stdout, run.stdout + run.stderr
    network = re.search(r"as a network .* largest difference from the Python node network (\S+) .*, (\d+) above",
                        run.stdout)
    assert float(network.group(1)) > 1e-10 and network.group(2) == "0", run.stdout
    lines = (out / "replay.txt").read_text().splitlines()
    tol = np.array([float(line.split()[0]) for line in lines[1:]]).reshape(6, 4)
    assert tol.min() == designer.export_c.REPLAY_TOLERANCE and tol.max() > 1e-9
    drift = np.array([float(line.split()[2]) for line in lines[1:]]).reshape(6, 4)  # the network run's
    assert np.all(np.diff(drift, axis=0) >= 0) and drift[0].min() == designer.export_c.REPLAY_TOLERANCE
    assert np.isfinite(drift).all() and drift.max() > 1e-4 and "information: at" not in run.stdout
    single = float_test(out)  # in float the drift passes the cap: those node steps are information
    assert single.returncode == 0 and re.search(r"information: at \d+ of its 24 node steps", single.stdout), \
        single.stdout
    (out / "replay.txt").write_text("\n".join(lines[:1] + [" ".join(line.split()[:2] + ["1e-12"] + line.split()[3:])
                                                          for line in lines[1:]]) + "\n")
    flat = make_test(out)
    assert flat.returncode != 0 and re.search(r"^network run, step \d+, node \d+: ", flat.stdout, re.M), flat.stdout
    assert re.search(r"^(?!network)step \d+, node", flat.stdout, re.M) is None  # the steps from Python's state agree
    (out / "replay.txt").write_text("\n".join(lines[:1] + [" ".join(["1e-12"] + line.split()[1:])
                                                          for line in lines[1:]]) + "\n")
    flat = make_test(out)
    assert flat.returncode != 0 and re.search(r"^step \d+, node \d+: P", flat.stdout, re.M), flat.stdout
    first = int(np.argmax(tol.max(axis=1) > 1e-9))  # the first step the lowered cap refuses (0-based)
    ill = int((tol > 1e-9).sum())
    monkeypatch.setattr(designer.export_c, "REPLAY_TOLERANCE_CAP", 1e-9)
    with pytest.warns(RuntimeWarning, match=rf"ill-conditioned at {ill} of its 24 node steps, the first at step "
                                            rf"{first + 1}, node \d+ .*make test keeps them as information"):
        studies.export(des, out=out)
    run = make_test(out)  # the driver's own cap is the export's
    assert run.returncode == 0 and "6 steps x 4 nodes" in run.stdout, run.stdout + run.stderr
    assert re.search(rf"information: at {ill} of the 24 node steps \(the first at step {first + 1}, node \d+\)",
                     run.stdout), run.stdout
    # a node step kept as information (tolerance inf, here also its network run's) is not checked; the step after one
    # is, from Python's state
    lines = (out / "replay.txt").read_text().splitlines()
    row = lambda k, i: 1 + 4 * k + i  # noqa: E731 - the replay's line of step k (0-based) and node slot i

    def changed(line, tolerances):
        values = line.split()
        values[-1] = repr(float(values[-1]) * 1.001)  # its Python covariance's last entry
        return " ".join(tolerances + values[len(tolerances):])

    last = lines[:]
    last[row(5, 0)] = changed(last[row(5, 0)], ["inf"] * 4)
    (out / "replay.txt").write_text("\n".join(last) + "\n")
    run = make_test(out)
    assert run.returncode == 0 and "information: at" in run.stdout, run.stdout
    after = lines[:]
    after[row(0, 0)] = " ".join(["inf", "inf"] + after[row(0, 0)].split()[2:])
    after[row(1, 0)] = changed(after[row(1, 0)], [])
    (out / "replay.txt").write_text("\n".join(after) + "\n")
    run = make_test(out)
    assert run.returncode != 0 and re.search(r"^step 2, node \d+: P", run.stdout, re.M), run.stdout
    assert "information: at" in run.stdout and "(the first at step 1, node" in run.stdout, run.stdout


@pytest.mark.parametrize("target, options", [("indoor-robot", []),
                                             ("indoor-robot", ["--rounds", "3", "--exchange", "predictions"]),
                                             ("indoor-robot", ["--table-kind", "stationary"]),
                                             ("user", ["--rounds", "2", "--bank", "2"])])
@pytest.mark.slow
def test_a_scheduled_design_in_c_replays_the_python_node_filter(target, options, cart, tmp_path):
    """design --mode scheduled (the neighbours' measurements exchanged or not, 1-3 exchange rounds, a bank of
    operating points whose tables the run does pick, a falsification with a mean), export, make test: every node's
    estimate and own covariance after every step within 1e-10 of the Python scheduled node's (the tables looked up,
    the link gains solved online in C), on the design's run or a user's CSV log, and so are the nodes run as a network
    on their own packets, every round's; a replay moved by 1e-7 fails, and so does the network run with a falsified
    packet taken as sent (with several rounds)."""
    from filters.consensus_batch import run_consensus_batch
    from studies.consensus_design import consensus_design
    from studies.recorded import design_options_of
    from studies.scenarios import load_scenario

    scenario = target
    if target == "user":  # the user's cart with a constant falsification (a nonzero mean: its terms in the gains)
        scenario = str(tmp_path / "cart_bias.py")
        biased = USER_MODEL.replace("components=(0, 1))", "components=(0, 1), law='constant')")
        assert biased != USER_MODEL
        (tmp_path / "cart_bias.py").write_text(biased)
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", scenario, "--mode", "scheduled", "--out", str(des)] + options) in (0, 1)
    data = None
    if target == "user":
        data = tmp_path / "log.csv"
        studies.simulate(scenario, seed=9, run=2, out=data)
    files = studies.export(des, out=out, data=data)
    header = (out / "cfd_node.h").read_text()
    assert "gain rule scheduled" in header and {p.name for p in files} >= {"cfd_node.c", "replay.txt"}
    source = (out / "cfd_node.c").read_text()
    tables = json.loads((des / "schedule.json").read_text())
    d = np.bincount(np.asarray(np.load(des / "schedule.npz")["table_receiver"]), minlength=8)
    one_set = int(np.sum(d)) * 9  # Γ: d_i blocks of n x n per node, once
    written = int(re.search(r"cfd_gam\[(\d+)\]", source).group(1))
    if "--table-kind" in options:  # one set of tables for every step and beyond: written once
        assert tables["tables_kind"] == "stationary" and tables["tables_own_steps"] == 0
        assert written == one_set
        assert int(re.search(r"cfd_sig\[(\d+)\]", source).group(1)) == int(np.sum(d * (d + 1) // 2)) * 9
    elif target == "indoor-robot" and options == []:  # each step's own, and beyond the horizon the stationary ones
        # (the first step's are zeros at every node, its neighbours' errors the prior's: written once a size)
        assert tables["tables_kind"] == "per-step"
        assert one_set * tables["steps"] < written <= one_set * (tables["steps"] + 1)
    run = make_test(out)
    assert run.returncode == 0, run.stdout + run.stderr
    worst = float(re.search(r"largest difference from the Python node filter (\S+)", run.stdout).group(1))
    assert worst <= 1e-10
    if "--bank" in options:  # the run picks bank tables (the test would not cover them otherwise)
        sc = load_scenario(scenario)
        design = consensus_design(sc, design_options_of(des, sc)[1])
        sim = studies.simulate(sc, seed=int(json.loads((des / "schedule.json").read_text())["seed"]))
        ref = run_consensus_batch(sc.model, sc.network, sim.z[None], design, inputs=sim.inputs,
                                  attacks=[sim.attacks]).detail
        picks = [design.tables.choose(k, ref.x_pred[0, k]) for k in range(ref.x_pred.shape[1])]
        assert np.concatenate(picks).max() > 0
    assert mutable_static_data(out) == []
    single = float_test(out)
    assert single.returncode == 0, single.stdout
    n_x = 3 if target == "indoor-robot" else 4
    if data is not None:  # the replay's expected numbers are the node network's (the perturbed twins beside it
        # change nothing of it): its last estimate is the one cfdesign filter gives with the design directory
        last = (out / "replay.txt").read_text().splitlines()[-1].split()
        x_hat = studies.filter(scenario, data, schedule=des).x_hat
        assert np.array_equal([float(v) for v in last[-n_x * n_x - n_x:-n_x * n_x]], x_hat[-1, 6])
    network = re.search(r"as a network .* the Python node network (\S+) .*, (\d+) above", run.stdout)
    assert float(network.group(1)) <= 1e-10 and network.group(2) == "0", run.stdout
    if options:  # exchanged measurements or a bank: the network run's own packets, every round's
        falsified_packet_taken_as_sent_fails_the_network_run(out, scenario, des)
        return
    # the first component of an expected estimate
    moved_replay_fails(out, 7, -n_x * n_x - n_x, "x", range(8 if target == "indoor-robot" else 7))


@pytest.mark.slow
def test_what_cannot_be_exported_is_refused(cart, tmp_path):
    des = tmp_path / "mse"
    assert main(["design", str(cart), "--mode", "mse", "--steps", "4", "--out", str(des)]) in (0, 1)
    with pytest.raises(InputError, match="gain rule 'mse' cannot be exported to C: an oracle"):
        studies.export(des, out=tmp_path / "c")
    assert main(["export", str(des), "--out", str(tmp_path / "c")]) == 2
    with pytest.raises(InputError, match="target must be 'c'"):
        studies.export(des, target="python", out=tmp_path / "c")
    tuned = tmp_path / "tuned"
    assert main(["design", str(cart), "--mode", "tuned", "--steps", "4", "--out", str(tuned)]) in (0, 1)
    with pytest.raises(InputError, match="gain rule 'tuned' cannot be exported to C: its node solves a convex "
                                         "problem online.*exported: paper, scheduled, relay, flood"):
        studies.export(tuned, out=tmp_path / "c")
    hess = tmp_path / "hessian"
    assert main(["design", str(cart), "--mode", "paper", "--linearization", "hessian", "--steps", "4", "--sigma",
                 "0.1", "--beta",
                 "0.005", "--out", str(hess)]) in (0, 1)
    with pytest.raises(InputError, match="linearization must be 'fixed' to export a paper design"):
        studies.export(hess, out=tmp_path / "c")
    relay = tmp_path / "relay"
    assert main(["design", str(cart), "--mode", "relay", "--steps", "4", "--out", str(relay)]) in (0, 1)
    with pytest.raises(InputError, match=r"nodes must be an integer in 0..6, got 9"):
        studies.export(relay, out=tmp_path / "c", nodes=[9])
    for bad in ("Robo", "9lives", "casadi", "a_b", "x" * 17, ""):
        with pytest.raises(InputError, match="prefix must be 1 to 16 lower-case letters and digits"):
            studies.export(relay, out=tmp_path / "c", prefix=bad)
    assert main(["export", str(relay), "--out", str(tmp_path / "c"), "--prefix", "Robo"]) == 2
    cart.write_text(USER_MODEL.replace("0.002]]", "0.003]]"))  # the model edited since the design
    try:  # refused before it is imported (its bytes), and given by the user (its content)
        with pytest.raises(InputError, match="names the model file .*cart.py., whose content is not the design's"):
            studies.export(relay, out=tmp_path / "c")
        with pytest.raises(InputError, match="was designed for another version of the model .cart."):
            studies.export(relay, out=tmp_path / "c", scenario=str(cart))
    finally:
        cart.write_text(USER_MODEL)
    assert not (tmp_path / "c" / "cfd_node.c").exists()


@pytest.mark.slow
def test_two_designs_link_into_one_program_under_two_prefixes(tmp_path):
    """The robot's relay design exported with --prefix rly and its scheduled design with --prefix sch: every global
    symbol of each library carries its prefix (CasADi's aside), each passes its own make test, and one program
    includes both headers, links both libraries and steps node 0 of each from its prior, side by side (its own
    measurement, nothing received), to the Python node filter's estimates within 1e-12."""
    if shutil.which("make") is None or shutil.which("nm") is None:
        pytest.skip("no make or nm")
    out = {}
    for mode, prefix in (("relay", "rly"), ("scheduled", "sch")):
        des = tmp_path / mode
        assert main(["design", "indoor-robot", "--mode", mode, "--seed", "2", "--out", str(des)]) in (0, 1)
        out[prefix] = tmp_path / prefix
        assert main(["export", str(des), "--out", str(out[prefix]), "--prefix", prefix]) == 0
        assert {p.name for p in out[prefix].iterdir()} >= {f"{prefix}_node.c", f"{prefix}_node.h", f"{prefix}_model.c",
                                                           f"{prefix}_test.c"}
        run = make_test(out[prefix])
        assert run.returncode == 0, run.stdout + run.stderr
        table = subprocess.run(["nm", "--format=posix", f"lib{prefix}_node.a"], cwd=out[prefix], check=True,
                               capture_output=True, text=True).stdout
        globals_ = [f.split()[0] for f in table.splitlines() if len(f.split()) > 1 and f.split()[1] in "TDBR"]
        assert globals_ and all(g.startswith(prefix + "_") or g.startswith("casadi_") for g in globals_), globals_
    z = {"rly": [0.3, 0.1], "sch": [-0.2, 0.05]}  # node 0's camera reading
    u = [0.1, 0.02]  # the robot's known inputs
    relay = studies.node_filter("indoor-robot", schedule=tmp_path / "relay", node=0)
    scheduled = studies.node_filter("indoor-robot", schedule=tmp_path / "scheduled", node=0)
    scheduled.predict(z["sch"], u)
    want = np.concatenate([relay.step(z["rly"], {}, u), scheduled.update({})])
    program = tmp_path / "both.c"
    program.write_text(r"""#include <math.h>
#include <stdio.h>
#include "rly_node.h"
#include "sch_node.h"
/* node 0 of each design, one step each, side by side: its own measurement and nothing received */
int main(void) {
    static rly_node a;
    static sch_node b;
    static sch_packet mine, got[SCH_DEG_MAX];
    static unsigned char none[RLY_BALL_MAX > SCH_DEG_MAX ? RLY_BALL_MAX : SCH_DEG_MAX];
    static double rec[RLY_ROWS_MAX];
    const double z_a[] = {%s}, z_b[] = {%s}, u[] = {%s};
    int i;
    if (rly_init(&a, 0) || sch_init(&b, 0)) return 2;
    if (rly_step(&a, z_a, none, rec, u) || sch_predict(&b, z_b, u, &mine) || sch_update(&b, none, got))
        return 3;
    for (i = 0; i < RLY_NX; ++i) printf("%%.17g ", rly_estimate(&a)[i]);
    for (i = 0; i < SCH_NX; ++i) printf("%%.17g ", sch_estimate(&b)[i]);
    printf("\n");
    for (i = 0; i < SCH_NX; ++i) printf("%%.17g ", sch_certificate(&b) ? sch_certificate(&b)[i] : -1.0);
    printf("\n");
    return 0;
}
""" % tuple(", ".join(map(repr, v)) for v in (z["rly"], z["sch"], u)))
    build = subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-pedantic", f"-I{out['rly']}", f"-I{out['sch']}",
                            "-o", "both", "both.c", str(out["rly"] / "librly_node.a"),
                            str(out["sch"] / "libsch_node.a"), "-lm"], cwd=tmp_path, capture_output=True, text=True)
    assert build.returncode == 0 and "warning" not in build.stderr, build.stderr
    ran = subprocess.run(["./both"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert ran.returncode == 0, ran.stderr
    lines = ran.stdout.splitlines()
    x = np.array([float(v) for v in lines[0].split()])
    assert x.shape == want.shape and np.allclose(x, want, rtol=1e-12, atol=1e-12 * np.abs(want).max()), (x, want)
    # the certificate's diagonal at the node's step: the bound of each state's expected squared error
    bound = np.diag(scheduled.bound)
    assert np.isfinite(bound).all() and np.array_equal([float(v) for v in lines[1].split()], bound)


def test_the_certified_inverse_holds_where_the_eigenvalues_say_it_may(tmp_path):
    """spd_inverse (the C nodes' fast path beside the eigen-decomposition): on symmetric matrices of condition
    numbers 1 to 1e16, indefinite and singular ones, it certifies only matrices whose every eigenvalue exceeds rcond
    times the largest (numpy's eigvalsh), then gives numpy's inverse within the conditioning's rounding; and it
    certifies the well-conditioned ones (it has power)."""
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", "indoor-robot", "--mode", "relay", "--steps", "4", "--out", str(des)]) in (0, 1)
    studies.export(des, out=out)
    (out / "harness.c").write_text(r"""#include <stdio.h>
#include "cfd_node.c"
int main(void) {
    static double A[64 * 64], Ainv[64 * 64], L[64 * 64];
    double rcond;
    int m, i;
    while (scanf("%d %lf", &m, &rcond) == 2) {
        for (i = 0; i < m * m; ++i) if (scanf("%lf", &A[i]) != 1) return 2;
        if (spd_inverse(m, A, Ainv, L, rcond)) { printf("no\n"); continue; }
        printf("yes");
        for (i = 0; i < m * m; ++i) printf(" %.17g", Ainv[i]);
        printf("\n");
    }
    return 0;
}
""")
    build = subprocess.run([CC, "-std=c99", "-O2", "-o", "harness", "harness.c", "cfd_model.c", "-lm"], cwd=out,
                           capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    rng = np.random.default_rng(41)
    cases = []
    for _ in range(300):
        m = int(rng.integers(1, 16))
        Q, _ = np.linalg.qr(rng.standard_normal((m, m)))
        lam = 10.0 ** rng.uniform(-16 * rng.uniform(), 0, m) * rng.choice([1, 1, 1, 1, -1, 0], m)
        A = (Q * lam) @ Q.T
        cases.append((m, float(10.0 ** rng.uniform(-14, -2)), 0.5 * (A + A.T)))
    text = "".join(f"{m} {rc!r} " + " ".join(repr(float(v)) for v in A.reshape(-1)) + "\n" for m, rc, A in cases)
    ran = subprocess.run(["./harness"], cwd=out, input=text, capture_output=True, text=True, timeout=60)
    assert ran.returncode == 0
    certified = 0
    for (m, rc, A), line in zip(cases, ran.stdout.splitlines()):
        lam = np.linalg.eigvalsh(A)
        if line == "no":
            continue
        certified += 1
        assert lam.min() > rc * lam.max() > 0, (m, rc, lam)
        inv = np.array([float(v) for v in line.split()[1:]]).reshape(m, m)
        cond = lam.max() / lam.min()
        assert np.allclose(inv, np.linalg.inv(A), rtol=0, atol=1e3 * cond * np.finfo(float).eps / lam.min())
    wellcond = sum(1 for m, rc, A in cases if (lambda w: w.min() > 0 and w.max() / w.min() * m * m < 0.5 / rc)(
        np.linalg.eigvalsh(A)))
    assert certified >= wellcond > 20


TWINS = '''"""Two states on a star of five nodes: nodes 1 and 2 measure x0 alike (one direction, twice, one hop from node 0),
node 3 measures x0 + x1 1e7 times more precisely than the others (its variance 1e-14), node 4 x1."""
import casadi as ca
import numpy as np

from designer import AttackSpec, Gaussian, Model, SensorNetwork, Sensor

STEPS = 20
NETWORK = SensorNetwork.from_edges(5, [(0, 1), (0, 2), (0, 3), (3, 4)])
ATTACKS = AttackSpec(dos=0.2)


def model() -> Model:
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(0.95 * x[0] + 0.1 * x[1], 0.9 * x[1])
    g = lambda v: Gaussian.zero_mean([[v]])
    sensors = [Sensor("a0", x[0] - x[1], g(1.0)), Sensor("a1", x[0], g(1.0)), Sensor("a2", 2.0 * x[0], g(4.0)),
               Sensor("fine", x[0] + x[1], g(1e-14)), Sensor("a4", x[1], g(1.0))]
    return Model("twins", x, f, sensors, process_noise=Gaussian.zero_mean(0.01 * np.eye(2)),
                 prior=Gaussian(np.zeros(2), np.eye(2)))
'''


@pytest.mark.skipif(shutil.which("gcov") is None, reason="no gcov")
def test_the_relay_nodes_two_ways_agree_where_rows_repeat_and_where_the_fast_inverse_gives_way(tmp_path):
    """The C relay node updates in its ball's rows (directly, K_r G0 = X S^-1, where the traces of S and of G0's
    blocks certify M = Ls^T G0 Ls), and where S is not positive definite or M has no certified inverse (two rows of
    one depth along one direction) reduces each hop group's rows to an orthonormal basis of their span
    (-DCFD_BASES_ONLY=1 takes that way at every step); neither is numpy's pseudo-inverse of the whole G n x G n Q, as
    rules.relay.design.relay_update's fallback computes it.  On a model where two sensors of one hop depth measure one
    direction (a row the reduction drops) and one sensor is 1e7 x more precise (Q' beyond the certified Cholesky
    inverse, so the eigen-decomposition decides), and on the same model with that sensor as precise as the others
    (balls whose depths' rows are independent: the direct update), both ways replay the Python node filter, and
    coverage (gcov) shows that their branches ran: in the rows the direct update and the bases' where rows repeat a
    direction."""
    keys = ("if (nr > GS_TOL", "kg_[nk++] = g", "eigsym(&wk->m, nk", "lp = l * cfd_p[r0 + c]")
    counts = dict.fromkeys(((way, key) for way in ("rows", "bases") for key in keys), 0)
    for name, text in (("twins", TWINS), ("alike", TWINS.replace("g(1e-14)", "g(1.0)"))):
        model = tmp_path / f"{name}.py"
        model.write_text(text)
        des, out = tmp_path / f"design-{name}", tmp_path / f"c-{name}"
        assert main(["design", str(model), "--mode", "relay", "--out", str(des)]) in (0, 1)
        studies.export(des, out=out)
        _count_relay_ways(out, keys, counts)
    assert counts["rows", "lp = l * cfd_p[r0 + c]"] > 0 and counts["rows", "if (nr > GS_TOL"] > 0
    assert counts["bases", "if (nr > GS_TOL"] > counts["bases", "kg_[nk++] = g"] > 0  # rows dropped, directions kept
    assert counts["bases", "eigsym(&wk->m, nk"] > 0 and counts["bases", "lp = l * cfd_p[r0 + c]"] == 0


def _count_relay_ways(out, keys, counts):
    """Build the relay export in ``out`` with coverage each way (in the rows where they can be, by bases at every
    step), check that its replay passes, and add how often each line holding a key ran to ``counts[way, key]``."""
    for flag, way in (("-DCFD_BASES_ONLY=0", "rows"), ("-DCFD_BASES_ONLY=1", "bases")):
        build = subprocess.run([CC, "-std=c99", "-O0", "--coverage", flag, "-o", "cov", "cfd_test.c", "cfd_node.c",
                                "cfd_model.c", "-lm"], cwd=out, capture_output=True, text=True, timeout=300)
        assert build.returncode == 0, build.stderr
        for stale in out.glob("*.gcda"):
            stale.unlink()
        run = subprocess.run(["./cov", "replay.txt"], cwd=out, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0 and "0 above the tolerance" in run.stdout, (way, run.stdout)
        subprocess.run(["gcov", "cov-cfd_node.c"], cwd=out, capture_output=True, text=True, timeout=300, check=True)
        for line in (out / "cfd_node.c.gcov").read_text().splitlines():
            count, _, code = (part.strip() for part in line.split(":", 2))
            for key in keys:
                if key in code:
                    counts[way, key] += 0 if count.startswith("#") else int(count.rstrip("*"))


@pytest.mark.slow
def test_a_relay_design_whose_nodes_carry_their_regions_in_c_replays_the_python_node_filter(tmp_path, monkeypatch):
    """A model declaring REGIONS (tests/test_carry.py's ring: coupled dynamics, a bearing, FDI and DoS): its relay
    design's nodes carry their regions, and so do its C nodes: CFD_NC below CFD_NX, each node's ``cfd_states`` the
    design's carried states, and make test (double and float) agrees with the Python node filter in the carried
    coordinates.  The check has power: the states of one node's data swapped, or an expected estimate moved by 1e-7,
    fail it.  The float node drops eigenvalues the double keeps (below rules.relay.design.FLOAT_RTOL of the largest:
    at step 1 the 4e-6 of node 2's M), which moves its estimate by a few percent: its float tolerance is the relay
    export's float twin's, which cuts where the float node cuts; with the base class's twin (float's rounding alone)
    the float replay fails there."""
    from test_carry import model_file

    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", str(model_file(tmp_path)), "--mode", "relay", "--rounds", "1", "--out", str(des)]) in (0, 1)
    card = json.loads((des / "schedule.json").read_text())
    assert card["carry"] == "region"
    assert main(["export", str(des), "--out", str(out)]) == 0
    header = (out / "cfd_node.h").read_text()
    n_x, nc = (int(re.search(rf"#define CFD_{k} (\d+)", header).group(1)) for k in ("NX", "NC"))
    carried = [[card["state_names"].index(s) for s in row] for row in card["carried"]]
    assert nc == max(map(len, carried)) < n_x
    run = make_test(out)
    assert run.returncode == 0 and "8 nodes" in run.stdout, run.stdout + run.stderr
    assert float(re.search(r"largest difference from the Python node filter (\S+)", run.stdout).group(1)) <= 1e-10
    assert float_test(out).returncode == 0
    from designer.export_c import NodeExport
    from rules.relay.export_c import RelayExport

    with monkeypatch.context() as m:
        m.setattr(RelayExport, "float_twin", NodeExport.float_twin)
        studies.export(des, out=tmp_path / "uncut")
    uncut = float_test(tmp_path / "uncut")
    assert uncut.returncode != 0 and re.search(r"^step 1, node 2: (x|P)", uncut.stdout, re.M), uncut.stdout
    # cfd_states: each node's carried states, in the design's order
    (out / "states.c").write_text('#include <stdio.h>\n#include "cfd_node.h"\nint main(void) {\n'
                                  '    int i, j, c; const int *s;\n    for (i = 0; i < CFD_NODES; ++i) {\n'
                                  '        c = cfd_states(cfd_exported_node(i), &s);\n'
                                  '        for (j = 0; j < c; ++j) printf("%d ", s[j]);\n        printf("\\n");\n'
                                  '    }\n    return cfd_states(99, &s) == -1 ? 0 : 1;\n}\n')
    built = subprocess.run([CC, "-std=c99", "-o", "states", "states.c", "cfd_node.c", "cfd_model.c", "-lm"], cwd=out,
                           capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stderr
    said = subprocess.run(["./states"], cwd=out, capture_output=True, text=True, timeout=60)
    assert said.returncode == 0 and [[int(v) for v in ln.split()] for ln in said.stdout.splitlines()] == carried
    # power: a node whose carried states are read in another order gathers the wrong block, and make test fails
    source = (out / "cfd_node.c").read_text()
    table = re.search(r"cfd_state\[\d+\] = \{([^}]*)\}", source)
    cells = table.group(1).split(", ")
    first = len(carried[0])
    cells[0], cells[first - 1] = cells[first - 1], cells[0]
    (out / "cfd_node.c").write_text(source[:table.start(1)] + ", ".join(cells) + source[table.end(1):])
    bad = make_test(out)
    assert bad.returncode != 0 and re.search(r"^step \d+, node 0: (x|P)\[", bad.stdout, re.M), bad.stdout
    (out / "cfd_node.c").write_text(source)
    moved_replay_fails(out, 5, -nc * nc - nc, "x", range(8))
    # the memory estimate counts what these nodes record: replay.txt's numbers (less each row's tolerances), all of them
    # for every node and for three, against the rule's replay_numbers over the steps (an upper bound, and close)
    import rules
    from studies.design_options import effective
    from studies.recorded import design_options_of
    from studies.scenarios import scenario_of

    sc = scenario_of(str(tmp_path / "ring.py"))
    mode, options, _ = design_options_of(des, sc)
    used = effective(sc, options)[1]
    assert used.carry == "region"
    for nodes in (list(range(8)), [1, 4, 6]):
        if len(nodes) < 8:
            studies.export(des, out=tmp_path / "few", nodes=nodes)
        rows = ((out if len(nodes) == 8 else tmp_path / "few") / "replay.txt").read_text().splitlines()[1:]
        written = sum(len(r.split()) - 2 for r in rows)
        record, _ = rules.get(mode).c_export().replay_numbers(sc.model, sc.network, used, sc.regions, nodes)
        assert 0.7 * record * sc.steps <= written <= record * sc.steps, (written, record * sc.steps)
