"""The Monte Carlo runner: seeds per run, identical bits on every backend, resume, force, failures."""
from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from designer.validation import ComputationError, InputError
from studies.runner import (CHUNKS_DIR, SUMMED, Backend, RunFailed, chunk_ranges, make_backend, monte_carlo,
                            run_seed)

ROOT = Path(__file__).resolve().parents[1]


def _interruptible() -> None:
    """The child starts with Ctrl-C's default action, as in a terminal, even when this process was started
    in the background of a shell without job control (which ignores SIGINT, and children inherit that)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def toy_task(run_ids, seeds, *, scale=1.0, fail_run=None, kill_flag=None, sleep=0.0):
    """Per run: 6 normals and a matrix product (BLAS), from the run's own Generator."""
    if sleep:
        time.sleep(sleep)
    rows = []
    for r, s in zip(run_ids, seeds):
        if kill_flag is not None and r == fail_run and os.path.exists(kill_flag):
            os.kill(os.getpid(), signal.SIGKILL)
        if kill_flag is None and r == fail_run:
            raise ValueError(f"deliberate failure in run {r}")
        g = np.random.default_rng(s)
        a = g.standard_normal((6, 6)) * scale
        rows.append(np.concatenate([g.standard_normal(6), (a @ a.T).ravel()]))
    return {"x": np.stack(rows), "run": np.asarray(run_ids)}


def reference(runs, seed, scale=1.0):
    """Independent of the runner: SeedSequence(seed).spawn(runs)[r], one run after the other."""
    out = []
    for s in np.random.SeedSequence(seed).spawn(runs):
        g = np.random.default_rng(s)
        a = g.standard_normal((6, 6)) * scale
        out.append(np.concatenate([g.standard_normal(6), (a @ a.T).ravel()]))
    return np.stack(out)


def test_run_seed_is_the_spawned_child():
    kids = np.random.SeedSequence(11).spawn(7)
    for r in (0, 3, 6):
        assert np.array_equal(run_seed(11, r).generate_state(4), kids[r].generate_state(4))
    assert not np.array_equal(run_seed(11, 1).generate_state(4), run_seed(12, 1).generate_state(4))


def test_chunk_ranges_cover_runs_once():
    assert chunk_ranges(23, 10) == [(0, 8), (8, 16), (16, 23)]  # as equal as whole runs allow, none above 10
    assert chunk_ranges(10, 3) == [(0, 3), (3, 6), (6, 8), (8, 10)]  # two workers: 5 runs each
    assert chunk_ranges(5, 10) == [(0, 5)]
    for runs in range(1, 40):
        for size in range(1, 12):
            got = chunk_ranges(runs, size)
            sizes = [b - a for a, b in got]
            assert got[0][0] == 0 and got[-1][1] == runs and all(got[i][1] == got[i + 1][0] for i in range(len(got) - 1))
            assert len(got) == -(-runs // size) and max(sizes) <= size and max(sizes) - min(sizes) <= 1
    with pytest.raises(InputError, match="chunk_size"):
        chunk_ranges(5, 0)


@pytest.mark.parametrize("chunk", [1, 4, 23])
def test_batched_matches_the_independent_reference(chunk):
    res = monte_carlo(toy_task, runs=23, seed=5, chunk_size=chunk)
    assert np.array_equal(res.arrays["x"], reference(23, 5))
    assert np.array_equal(res.arrays["run"], np.arange(23))
    assert len(res.computed) == len(chunk_ranges(23, chunk)) and not res.reused


@pytest.mark.slow
def test_same_bits_batched_processes_and_dask():
    distributed = pytest.importorskip("distributed")
    kw = dict(runs=17, seed=3, chunk_size=4)
    task = functools.partial(toy_task, scale=0.5)
    a = monte_carlo(task, **kw).arrays
    b = monte_carlo(task, backend=Backend("processes", workers=2), **kw).arrays
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        c = monte_carlo(task, backend=make_backend(dask=cl.scheduler_address), **kw).arrays
    for other in (b, c):
        assert other.keys() == a.keys()
        for k in a:
            assert np.array_equal(a[k], other[k]), k
    assert np.array_equal(a["x"], reference(17, 3, 0.5))


def _self_signed(tmp_path) -> tuple[Path, Path]:
    import shutil

    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command to make a certificate")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out",
                    str(cert), "-days", "1", "-subj", "/CN=localhost"], check=True, capture_output=True)
    return cert, key


def test_dask_over_tls_with_a_security_file(tmp_path):
    """A TLS-only scheduler: reached with --dask-security's file, the same bits; without it, a clean refusal."""
    distributed = pytest.importorskip("distributed")
    cert, key = _self_signed(tmp_path)
    sec = distributed.Security(tls_ca_file=str(cert), tls_scheduler_cert=str(cert), tls_scheduler_key=str(key),
                               tls_worker_cert=str(cert), tls_worker_key=str(key), tls_client_cert=str(cert),
                               tls_client_key=str(key), require_encryption=True)
    conf = tmp_path / "dask-security.json"
    conf.write_text(json.dumps({"tls_ca_file": "cert.pem", "tls_client_cert": "cert.pem", "tls_client_key": "key.pem",
                                "require_encryption": True}))  # relative to the file
    kw = dict(runs=9, seed=2, chunk_size=3)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tls://",
                                  security=sec, dashboard_address=None) as cl:
        assert cl.scheduler_address.startswith("tls://")
        res = monte_carlo(toy_task, backend=make_backend(dask=cl.scheduler_address, dask_security=str(conf)), **kw)
        assert res.describe()["dask_tls"] is True
        with pytest.raises(InputError, match="dask: cannot reach"):
            monte_carlo(toy_task, backend=make_backend(dask=cl.scheduler_address), **kw)
    assert np.array_equal(res.arrays["x"], reference(9, 2))


@pytest.mark.parametrize("content, needle", [
    ("not json", "not valid JSON"), ('{"tls_ca": "x"}', "unknown key 'tls_ca'"),
    ('{"tls_ca_file": "missing.pem"}', "does not exist"), ('{"require_encryption": "yes"}', "true or false"),
    ("[]", "JSON object"),
])
def test_a_bad_security_file_is_refused_by_name(tmp_path, content, needle):
    conf = tmp_path / "s.json"
    conf.write_text(content)
    with pytest.raises(InputError, match=needle):
        make_backend(dask="tls://127.0.0.1:1", dask_security=str(conf))
    with pytest.raises(InputError, match="Dask scheduler only"):
        make_backend(workers=2, dask_security=str(conf))


def test_backend_options():
    assert make_backend() == Backend("batched")
    assert make_backend(workers=1) == Backend("batched")
    assert make_backend(workers=3) == Backend("processes", workers=3)
    assert make_backend(dask="tcp://h:1").kind == "dask"
    with pytest.raises(InputError, match="--workers and --dask"):
        make_backend(workers=2, dask="tcp://h:1")
    with pytest.raises(InputError, match="workers"):
        make_backend(workers=0)
    with pytest.raises(InputError, match="backend"):
        Backend("threads")


def test_failing_run_is_named_with_its_seed_and_finished_chunks_are_kept(tmp_path):
    bad = functools.partial(toy_task, fail_run=7)
    with pytest.raises(RunFailed, match=r"run 7 failed \(seed 9, spawn key \(7,\)\).*deliberate") as info:
        monte_carlo(bad, runs=12, seed=9, chunk_size=3, store=tmp_path, config={"a": 1})
    assert info.value.run == 7 and info.value.seed == 9 and info.value.spawn_key == (7,)
    d = tmp_path / CHUNKS_DIR / "runs"
    assert sorted(p.name for p in d.glob("runs_*.npz")) == ["runs_0000000_0000003.npz", "runs_0000003_0000006.npz"]
    res = monte_carlo(toy_task, runs=12, seed=9, chunk_size=3, store=tmp_path, config={"a": 1})
    assert res.reused == [(0, 3), (3, 6)] and res.computed == [(6, 9), (9, 12)]
    assert np.array_equal(res.arrays["x"], reference(12, 9))
    log = [tuple(json.loads(line)["chunk"]) for line in (d / "log.jsonl").read_text().splitlines()]
    assert sorted(log) == chunk_ranges(12, 3)  # every chunk written exactly once
    assert not list(d.glob("*.tmp"))


def test_failing_run_reported_from_worker_processes():
    with pytest.raises(RunFailed, match="run 5 failed"):
        monte_carlo(functools.partial(toy_task, fail_run=5), runs=8, seed=1, chunk_size=2,
                    backend=Backend("processes", workers=2))


def test_other_config_refused_unless_forced(tmp_path):
    monte_carlo(toy_task, runs=4, seed=0, chunk_size=2, store=tmp_path, config={"particles": 100})
    with pytest.raises(InputError, match=r"other settings \(config, config.particles\).*--force"):
        monte_carlo(toy_task, runs=4, seed=0, chunk_size=2, store=tmp_path, config={"particles": 200})
    with pytest.raises(InputError, match="seed"):
        monte_carlo(toy_task, runs=4, seed=1, chunk_size=2, store=tmp_path, config={"particles": 100})
    res = monte_carlo(functools.partial(toy_task, scale=2.0), runs=4, seed=1, chunk_size=2, store=tmp_path,
                      config={"particles": 200}, force=True)
    assert not res.reused and np.array_equal(res.arrays["x"], reference(4, 1, 2.0))
    again = monte_carlo(toy_task, runs=4, seed=1, chunk_size=2, store=tmp_path, config={"particles": 200})
    assert again.reused == chunk_ranges(4, 2) and not again.computed
    assert np.array_equal(again.arrays["x"], res.arrays["x"])  # loaded, not recomputed with scale 1


def test_more_runs_reuse_the_full_chunks(tmp_path):
    monte_carlo(toy_task, runs=5, seed=2, chunk_size=2, store=tmp_path)
    res = monte_carlo(toy_task, runs=8, seed=2, chunk_size=2, store=tmp_path)
    assert res.reused == [(0, 2), (2, 4)] and res.computed == [(4, 6), (6, 8)]
    assert np.array_equal(res.arrays["x"], reference(8, 2))


def test_killed_worker_is_reported_and_the_study_resumes(tmp_path):
    flag = tmp_path / "kill"
    flag.touch()
    task = functools.partial(toy_task, fail_run=9, kill_flag=str(flag))
    with pytest.raises(ComputationError, match="worker process died.*resume"):
        monte_carlo(task, runs=12, seed=4, chunk_size=3, store=tmp_path / "s", backend=Backend("processes", workers=2))
    flag.unlink()
    res = monte_carlo(task, runs=12, seed=4, chunk_size=3, store=tmp_path / "s", backend=Backend("processes", workers=2))
    assert (9, 12) in res.computed
    assert np.array_equal(res.arrays["x"], reference(12, 4))


def totals_task(run_ids, seeds, *, slow_first=0.0):
    """toy_task's rows, also kept as their sum; the first chunks wait, so the later ones finish first."""
    if slow_first and run_ids[0] < 6:
        time.sleep(slow_first)
    out = toy_task(run_ids, seeds)
    return {**out, f"{SUMMED}x": out["x"], f"{SUMMED}count": np.ones(len(run_ids), int)}


@pytest.mark.parametrize("chunk", [3, 17])
def test_summed_rows_are_added_in_run_order_whatever_the_chunks_and_the_order_they_finish_in(tmp_path, chunk):
    """A SUMMED output is its rows added one run after the other (an independent reference: a loop over the runs'
    rows), the same bits in one chunk or several, whether they finish in order (batched), out of order (two
    workers, the first chunks slowed) or come back from the store; the per-run rows are as before."""
    rows = reference(17, 3)
    want = rows[0].copy()
    for row in rows[1:]:
        want += row
    kw = dict(runs=17, seed=3, chunk_size=chunk)
    got = [monte_carlo(totals_task, **kw).arrays,
           monte_carlo(functools.partial(totals_task, slow_first=0.5), backend=Backend("processes", workers=2),
                       **kw).arrays]
    monte_carlo(totals_task, store=tmp_path, config={"x": 1}, **kw)
    again = monte_carlo(totals_task, store=tmp_path, config={"x": 1}, **kw)
    assert len(again.reused) == len(chunk_ranges(17, chunk)) and not again.computed
    got.append(again.arrays)
    for arrays in got:
        assert np.array_equal(arrays[f"{SUMMED}x"], want) and arrays[f"{SUMMED}x"].shape == (42,)
        assert arrays[f"{SUMMED}count"] == 17
        assert np.array_equal(arrays["x"], rows) and np.array_equal(arrays["run"], np.arange(17))
    with pytest.raises(ComputationError, match="numeric"):
        monte_carlo(lambda ids, seeds: {"x": np.zeros(len(ids)), f"{SUMMED}t": np.array(["a"] * len(ids))}, runs=2,
                    seed=0, chunk_size=1)


def test_task_output_is_checked():
    with pytest.raises(ComputationError, match="one row per run"):
        monte_carlo(lambda ids, seeds: {"x": np.zeros(3)}, runs=2, seed=0, chunk_size=2)


SIGINT_SCRIPT = textwrap.dedent("""
    import functools, sys
    sys.path.insert(0, {tests!r})
    from test_runner import toy_task
    from studies.runner import monte_carlo, Backend
    backend = Backend("processes", workers=2) if sys.argv[2] == "processes" else Backend()
    monte_carlo(functools.partial(toy_task, sleep=0.4), runs=16, seed=8, chunk_size=2, store=sys.argv[1],
                backend=backend, config={{"x": 1}}, quiet=True)
""")


@pytest.mark.parametrize("kind", ["batched", "processes"])
@pytest.mark.slow
def test_sigint_then_resume_equals_an_uninterrupted_run(tmp_path, kind):
    script = tmp_path / "run.py"
    script.write_text(SIGINT_SCRIPT.format(tests=str(ROOT / "tests")))
    store = tmp_path / "store"
    log = store / CHUNKS_DIR / "runs" / "log.jsonl"
    p = subprocess.Popen([sys.executable, str(script), str(store), kind], cwd=ROOT, stderr=subprocess.PIPE,
                         preexec_fn=_interruptible)
    deadline = time.time() + 60
    while time.time() < deadline and (not log.exists() or len(log.read_text().splitlines()) < 2):
        time.sleep(0.05)
    assert p.poll() is None, p.stderr.read().decode()
    p.send_signal(signal.SIGINT)
    err = p.communicate(timeout=30)[1].decode()
    assert p.returncode != 0 and "KeyboardInterrupt" in err
    written = len(log.read_text().splitlines())
    assert 2 <= written < 8
    res = monte_carlo(functools.partial(toy_task, sleep=0.4), runs=16, seed=8, chunk_size=2, store=store,
                      config={"x": 1})
    assert len(res.reused) == written and len(res.computed) == 8 - written
    chunks = [tuple(json.loads(line)["chunk"]) for line in log.read_text().splitlines()]
    assert sorted(chunks) == chunk_ranges(16, 2)  # no chunk computed (written) twice
    assert np.array_equal(res.arrays["x"], reference(16, 8))
    assert not list(log.parent.glob("*.tmp"))


def swallowing_task(run_ids, seeds):
    """Run 2 receives Ctrl-C inside code that swallows every exception (as CasADi's bare excepts do)."""
    for r in run_ids:
        if r == 2:
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.5)
            except BaseException:  # noqa: BLE001 - the point of the test
                pass
    return toy_task(run_ids, seeds)


@pytest.fixture
def ctrl_c_raises():
    """Ctrl-C raises KeyboardInterrupt in this process, as in a terminal, also when the tests were started in the
    background of a shell without job control (SIGINT ignored, see :func:`_interruptible`); restored after."""
    old = signal.getsignal(signal.SIGINT)
    if old is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def test_a_swallowed_ctrl_c_still_stops_the_study_and_discards_its_chunk(tmp_path, ctrl_c_raises):
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        pytest.skip("SIGINT is handled by someone else in this process")
    with pytest.raises(KeyboardInterrupt, match="discarded"):
        monte_carlo(swallowing_task, runs=6, seed=0, chunk_size=2, store=tmp_path)
    d = tmp_path / CHUNKS_DIR / "runs"
    assert sorted(p.name for p in d.glob("runs_*.npz")) == ["runs_0000000_0000002.npz"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    res = monte_carlo(toy_task, runs=6, seed=0, chunk_size=2, store=tmp_path)
    assert res.reused == [(0, 2)] and np.array_equal(res.arrays["x"], reference(6, 0))


# ----------------------------------------------------------------------------------------- Background
def _pid_and_square(x):
    import warnings

    warnings.warn(f"computed {x}", UserWarning)
    return os.getpid(), x * x


def _fails(x):
    raise ValueError(f"bad {x}")


def test_background_computes_in_a_child_and_replays_its_warnings(monkeypatch):
    """Where there are two cores, ``Background`` computes in a forked child (another PID) the value a call here
    gives, and the child's warnings are raised here; with one core it is the call here."""
    from studies.runner import Background

    monkeypatch.setattr("designer.cores.usable_cores", lambda: 2)
    with pytest.warns(UserWarning, match="computed 7"):
        with Background(_pid_and_square, 7) as bg:
            pid, value = bg.result()
    assert value == 49 and pid != os.getpid()
    monkeypatch.setattr("designer.cores.usable_cores", lambda: 1)
    with pytest.warns(UserWarning, match="computed 3"):
        pid, value = Background(_pid_and_square, 3).result()
    assert value == 9 and pid == os.getpid()


def test_background_failure_is_the_exception_of_a_call_here_and_an_abandoned_child_is_killed(monkeypatch):
    from studies.runner import Background

    monkeypatch.setattr("designer.cores.usable_cores", lambda: 2)
    with pytest.raises(ValueError, match="bad 5"):
        Background(_fails, 5).result()
    with pytest.raises(KeyError):
        with Background(time.sleep, 60) as bg:
            child = bg.pid
            raise KeyError("the parent fails first")
    with pytest.raises(ChildProcessError):  # reaped: no such child any more
        os.waitpid(child, os.WNOHANG)


def test_a_ctrl_c_while_waiting_for_the_background_is_the_ctrl_c(monkeypatch):
    """A Ctrl-C while this process waits for or reads the child's result: the block ends with the KeyboardInterrupt (not an
    error of closing what the reader closed), and the child is killed and reaped."""
    from studies import runner

    monkeypatch.setattr("designer.cores.usable_cores", lambda: 2)

    class Interrupted:
        def __init__(self, fd, mode):
            os.close(fd)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def fileno(self):  # a Ctrl-C while waiting for the child (Background.result's progress lines)
            raise KeyboardInterrupt

        def read(self):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        with runner.Background(time.sleep, 60) as bg:
            child = bg.pid
            monkeypatch.setattr(runner.os, "fdopen", Interrupted)
            bg.result()
    monkeypatch.undo()
    with pytest.raises(ChildProcessError):
        os.waitpid(child, os.WNOHANG)


def shared_task(run_ids, seeds, *, share=None, disagree=False):
    """:func:`toy_task`'s two outputs, as two shares: share 0 computes ``x``, share 1 ``run``; both the runs' ``truth``
    (its first normal, drawn again), different in share 1 with ``disagree``."""
    whole = toy_task(run_ids, seeds)
    truth = whole["x"][:, 0] + (1.0 if disagree and share == (1, 2) else 0.0)
    if share is None:
        return {**whole, "truth": truth}
    k, s = share
    assert s == 2, "the runner cuts 3 chunks on 2 workers into 2 shares"
    return {"truth": truth, **({"x": whole["x"]} if k == 0 else {"run": whole["run"]})}


def test_split_into_makes_the_pieces_of_work_a_multiple_of_the_workers():
    from studies.runner import split_into

    assert [split_into(5, c, 2) for c in (1, 2, 3, 4, 5)] == [2, 1, 2, 1, 2]  # odd chunks on 2 workers: 2 shares
    assert [split_into(5, c, 4) for c in (1, 2, 3, 4, 6)] == [4, 2, 4, 1, 2]
    assert split_into(1, 3, 2) == 1 and split_into(5, 3, 1) == 1  # a task that cannot cut; one worker
    for shares in (1, 2, 3, 8):
        for workers in (2, 3, 4):
            for chunks in range(1, 12):
                s = split_into(shares, chunks, workers)
                assert 1 <= s <= shares
                if s == workers // np.gcd(chunks, workers):  # not capped by shares: the pieces fill the workers
                    assert (chunks * s) % workers == 0


def test_shares_of_a_chunk_merge_to_the_whole_chunks_bits():
    kw = dict(runs=11, seed=7, chunk_size=4)  # 3 chunks on 2 workers: each cut in 2 shares
    whole = monte_carlo(shared_task, **kw).arrays
    cut = monte_carlo(shared_task, backend=Backend("processes", workers=2), shares=2, **kw).arrays
    assert cut.keys() == whole.keys() == {"x", "run", "truth"}
    for k in whole:
        assert np.array_equal(cut[k], whole[k]), k
    assert np.array_equal(cut["x"], reference(11, 7))
    with pytest.raises(ComputationError, match="shares of runs .* return different 'truth'"):
        monte_carlo(functools.partial(shared_task, disagree=True), backend=Backend("processes", workers=2),
                    shares=2, **kw)


def test_consensus_robot_deals_its_filters_out_to_the_shares_once_each():
    from studies.consensus_robot import shared_out

    assert shared_out(5, None) == set(range(5))
    assert shared_out(5, (0, 2)) == {0, 3, 4} and shared_out(5, (1, 2)) == {1, 2}  # back and forth: 0 1 1 0 0
    for count in range(1, 9):
        for s in range(1, 6):
            parts = [shared_out(count, (k, s)) for k in range(s)]
            assert set().union(*parts) == set(range(count)) and sum(map(len, parts)) == count  # each once
            assert max(map(len, parts)) - min(map(len, parts)) <= 1
