"""Results that cannot be silently wrong: the verified chunk store, one writer per output, workers
that die with their parent, output permissions."""
from __future__ import annotations

import functools
import json
import os
import re
import signal
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from designer.fileio import LOCK_NAME, append_line, atomic_write, output_lock
from designer.validation import ComputationError, InputError
from studies.runner import CHUNKS_DIR, monte_carlo

from test_runner import ROOT, _interruptible, reference, toy_task

KW = dict(runs=12, seed=4, chunk_size=4, label="toy", quiet=True)


def _store(tmp_path, **kw):
    return monte_carlo(toy_task, store=tmp_path, config={"scale": 1.0}, **{**KW, **kw})


def _chunk(tmp_path, start, stop):
    return tmp_path / CHUNKS_DIR / "toy" / f"runs_{start:07d}_{stop:07d}.npz"


def _rewrite(path: Path, change) -> None:
    """Load a chunk file, change its arrays (its metadata entry kept as it is), write it back."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    np.savez(path, **arrays)


def _reasons(res) -> list[str]:
    return [r["reason"] for r in res.rejected]


def test_an_untouched_store_is_reused_as_it_is(tmp_path):
    first = _store(tmp_path)
    again = _store(tmp_path)
    assert len(again.reused) == 3 and not again.computed and not again.rejected
    assert np.array_equal(again.arrays["x"], first.arrays["x"])
    assert np.array_equal(first.arrays["x"], reference(12, 4))
    assert again.describe()["chunks_rejected"] == []


def test_a_chunk_with_scaled_values_is_named_and_recomputed(tmp_path, capfd):
    _store(tmp_path)
    _rewrite(_chunk(tmp_path, 4, 8), lambda a: a.__setitem__("x", a["x"] * 1.5))
    res = _store(tmp_path)
    assert res.rejected == [{"runs": [4, 8], "reason": _reasons(res)[0]}]
    assert "checksum" in _reasons(res)[0]
    assert res.computed == [(4, 8)] and len(res.reused) == 2
    assert np.array_equal(res.arrays["x"], reference(12, 4))  # the truth, not the tampered values
    err = capfd.readouterr().err
    assert "runs_0000004_0000008.npz" in err and "runs 4..7" in err and "checksum" in err


def test_a_copy_of_another_chunk_is_not_reused(tmp_path):
    _store(tmp_path)
    _chunk(tmp_path, 8, 12).write_bytes(_chunk(tmp_path, 0, 4).read_bytes())
    res = _store(tmp_path)
    assert res.computed == [(8, 12)] and "holds runs [0, 4]" in _reasons(res)[0]
    assert np.array_equal(res.arrays["x"], reference(12, 4))


def test_a_chunk_with_missing_rows_is_not_reused(tmp_path):
    _store(tmp_path)
    _rewrite(_chunk(tmp_path, 0, 4), lambda a: a.update(x=a["x"][:2], run=a["run"][:2]))
    res = _store(tmp_path)
    assert res.computed == [(0, 4)] and "2 rows, not 4" in _reasons(res)[0]
    assert res.runs == 12 and res.arrays["x"].shape[0] == 12


def test_without_the_manifest_chunks_of_another_configuration_are_not_reused(tmp_path):
    monte_carlo(functools.partial(toy_task, scale=2.0), store=tmp_path, config={"scale": 2.0}, **KW)
    (tmp_path / CHUNKS_DIR / "toy" / "manifest.json").unlink()
    res = _store(tmp_path)
    assert len(res.rejected) == 3 and all("fingerprint differs" in r for r in _reasons(res))
    assert np.array_equal(res.arrays["x"], reference(12, 4, scale=1.0))


@pytest.mark.parametrize("content", [b"", b"garbage, not a zip file", None, "flip"])
def test_truncated_foreign_or_flipped_files_are_named_and_recomputed(tmp_path, content):
    _store(tmp_path)
    f = _chunk(tmp_path, 4, 8)
    if content is None:  # a valid npz written by someone else: no fingerprint
        np.savez(f, x=np.zeros((4, 42)), run=np.arange(4, 8))
    elif content == "flip":  # one bit of the stored data flipped
        raw = bytearray(f.read_bytes())
        raw[len(raw) // 3] ^= 0x10
        f.write_bytes(bytes(raw))
    else:
        f.write_bytes(content)
    res = _store(tmp_path)
    assert res.computed == [(4, 8)]
    expected = {None: ("no fingerprint",), "flip": ("unreadable", "checksum", "fingerprint", "no fingerprint")}
    assert any(w in _reasons(res)[0] for w in expected.get(content, ("unreadable",)))
    assert np.array_equal(res.arrays["x"], reference(12, 4))


def test_a_change_of_code_version_is_refused_by_name(tmp_path, monkeypatch):
    _store(tmp_path)
    import studies.runner as runner

    monkeypatch.setattr(runner, "code_fingerprint", lambda: "another version")
    with pytest.raises(InputError, match=r"\(code\); the code changed"):
        _store(tmp_path)


# ------------------------------------------------------------------------------------------- one writer
_HOLDER = textwrap.dedent("""
    import sys, time
    from designer.fileio import output_lock
    with output_lock(sys.argv[1]):
        print("locked", flush=True)
        time.sleep(60)
""")


def _hold(directory: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", _HOLDER, str(directory)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "locked"
    return p


def test_a_second_writer_is_refused_naming_the_holder(tmp_path):
    holder = _hold(tmp_path / "out")
    try:
        with pytest.raises(InputError, match=rf"being written by process {holder.pid} \(.*-c.*started"):
            with output_lock(tmp_path / "out"):
                pass
    finally:
        holder.kill()
        holder.wait()
    with output_lock(tmp_path / "out"):  # the lock went with its holder, even on SIGKILL
        assert json.loads((tmp_path / "out" / LOCK_NAME).read_text())["pid"] == os.getpid()


@pytest.mark.slow
def test_force_never_deletes_under_a_running_writer(tmp_path):
    out = tmp_path / "study"
    monte_carlo(toy_task, store=out, config={}, **KW)
    holder = _hold(out)
    try:
        r = subprocess.run([sys.executable, "-m", "studies", "study", "rrp-deception", "--runs", "2", "--particles",
                            "10", "--force", "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    finally:
        holder.kill()
        holder.wait()
    assert r.returncode == 2, r.stderr
    assert f"being written by process {holder.pid}" in r.stderr and "Traceback" not in r.stderr
    assert len(list((out / CHUNKS_DIR / "toy").glob("runs_*.npz"))) == 3  # nothing deleted


@pytest.mark.parametrize("make", ["file", "readonly"])
def test_an_unusable_out_is_refused_before_any_computation(tmp_path, make):
    target = tmp_path / "x"
    if make == "file":
        target.write_text("not a directory")
    else:
        if os.geteuid() == 0:
            pytest.skip("root writes into read-only directories")
        target.mkdir()
        target.chmod(0o500)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "studies", "design", "indoor-robot", "--mode", "tuned", "--out",
                        str(target)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "out" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert time.perf_counter() - t0 < 60  # refused, not designed first (a tuned design takes longer)


# ------------------------------------------------------------------------------ workers die with the parent
_PARENT = textwrap.dedent("""
    import functools, os, sys, time
    sys.path.insert(0, sys.argv[1])
    from test_runner import toy_task
    from studies.runner import Backend, monte_carlo
    print(os.getpid(), flush=True)
    monte_carlo(functools.partial(toy_task, sleep=60.0), runs=4, seed=0, chunk_size=1,
                backend=Backend("processes", workers=2), quiet=True)
""")


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


@pytest.mark.skipif(not Path("/proc").exists(), reason="needs /proc to find the workers")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT])
def test_workers_die_with_their_parent(sig):
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, str(ROOT / "tests")], cwd=ROOT, stdout=subprocess.PIPE,
                              text=True, preexec_fn=_interruptible)  # Ctrl-C's default action, as in a terminal
    workers = []
    try:
        assert int(parent.stdout.readline()) == parent.pid
        deadline = time.monotonic() + 60
        while len(workers) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
            workers = [w for w in _children(parent.pid) if _alive(w)]
        assert len(workers) >= 2, "the workers did not start"
        parent.send_signal(sig)
        parent.wait(timeout=30)
        deadline = time.monotonic() + 10
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(w) for w in workers), "a worker outlived its parent"
    finally:
        parent.kill()
        parent.wait()
        for w in workers:  # reparented by now: kill them by the PIDs seen
            if _alive(w):
                os.kill(w, signal.SIGKILL)


# ----------------------------------------------------------------------------------------- permissions
@pytest.mark.parametrize("umask, mode", [(0o027, 0o640), (0o022, 0o644), (0o077, 0o600)])
def test_output_files_respect_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        atomic_write(tmp_path / "a.txt", lambda fh: fh.write(b"x"))
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == mode


def test_appended_lines_are_whole_under_concurrent_writers(tmp_path):
    log = tmp_path / "log.jsonl"
    code = textwrap.dedent(f"""
        import json, sys
        from designer.fileio import append_line
        for i in range(300):
            append_line({str(log)!r}, json.dumps({{"writer": int(sys.argv[1]), "i": i, "pad": "x" * 200}}))
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code, str(w)], cwd=ROOT) for w in range(3)]
    assert all(p.wait(timeout=120) == 0 for p in procs)
    lines = log.read_text().splitlines()
    assert len(lines) == 900
    seen = [json.loads(x) for x in lines]  # every line parses: none interleaved
    assert sorted((s["writer"], s["i"]) for s in seen) == [(w, i) for w in range(3) for i in range(300)]
    append_line(log, "last")
    assert log.read_text().endswith("last\n")


def test_the_runs_returned_are_the_runs_asked_for(tmp_path):
    res = _store(tmp_path)
    assert res.runs == 12
    with pytest.raises(ComputationError, match="one row per run"):
        monte_carlo(lambda r, s: {"x": np.zeros((len(r) + 1, 2))}, runs=4, seed=0, chunk_size=2)


# ------------------------------------------------------------------------ outputs replaced as a whole
def test_outputs_replace_the_last_ones_as_a_whole(tmp_path):
    from designer.fileio import OUTPUTS_NAME, replaced_outputs

    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("the user's own file")
    with replaced_outputs(out) as st:
        (st / "fig_a.png").write_bytes(b"a")
        (st / "results.json").write_text("{}")
    with replaced_outputs(out) as st:  # another command: fig_a.png is not one of its outputs
        (st / "schedule.json").write_text("{}")
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["mine.txt", "schedule.json", OUTPUTS_NAME, LOCK_NAME])  # the lock: held while writing
    with pytest.raises(RuntimeError):
        with replaced_outputs(out) as st:  # fails half-way: the last outputs stay, complete
            (st / "results.json").write_text("{}")
            raise RuntimeError("boom")
    assert sorted(p.name for p in out.iterdir()) == names


def test_a_nan_in_the_results_is_refused_before_anything_is_written(tmp_path):
    from studies.outputs import write_outputs

    out = tmp_path / "out"
    write_outputs(out, {"filters": {"a": {"rmse": 1.0}}}, lambda d: (d / "fig.png").write_bytes(b"png"),
                  lambda r: "| table |\n")
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    with pytest.raises(ComputationError, match=r"filters\.a\.rmse is nan"):
        write_outputs(out, {"filters": {"a": {"rmse": float("nan")}}}, lambda d: (d / "fig2.png").write_bytes(b"x"),
                      lambda r: "| table |\n")
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert not [p for p in out.iterdir() if p.name.startswith(".staging")]


_NAN_MODEL = '''
import casadi as ca
from designer import AttackSpec, DesignOptions, Gaussian, Model, SensorNetwork, Sensor

STEPS = 12
X0 = [10.0]
NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2)])
ATTACKS = AttackSpec(dos=0.1)  # no FDI signal: the comparison's FDI sweep keeps its points without FDI
DESIGN = DesignOptions(u_scale=0, v_scale=0, sigma=0.05, beta=0.05)


def model() -> Model:
    x = ca.SX.sym("x", 1)
    # the truth stays at 10 +- 0.1; a quarter of the prior's particles lie below {edge}: where the square root is
    # NaN, so the particle filters' states leave the reals at their first propagation
    f = 0.9 * x + 1.0 + 1e-9 * ca.sqrt(x - {edge})
    sensors = [Sensor(f"s{{i}}", x, Gaussian.zero_mean([[0.5]])) for i in range(3)]
    return Model("nan-demo", x, f, sensors, Gaussian.zero_mean([[1e-4]]), Gaussian([10.0], [[9.0]]))
'''


@pytest.mark.slow
def test_a_filter_that_leaves_the_reals_fails_the_study_by_name_and_keeps_the_last_results(tmp_path):
    """A study whose particle filter produces NaN states: exit 1, one line naming the filter, the run and the
    step; the output directory keeps the previous complete results (nothing of the failed run)."""
    import studies

    good, bad = tmp_path / "good.py", tmp_path / "bad.py"
    good.write_text(_NAN_MODEL.format(edge=-100.0))
    bad.write_text(_NAN_MODEL.format(edge=8.0))
    out = tmp_path / "out"
    opts = dict(runs=2, particles=50, quiet=True, sweep_values=[0.2], tuned_in_sweeps=False)
    studies.study("comparison", str(good), out=out, **opts)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and not p.name.startswith(".cfdesign")}
    assert "results.json" in before
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-m", "studies", "study", "comparison", str(bad), "--runs", "2",
                           "--particles", "50", "--set", "sweep_values=[0.2]", "--set", "tuned_in_sweeps=false",
                           "--quiet", "--force", "--out", str(out)], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=600)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert re.search(r"filter 'centralized PF \(attack-aware\)' failed at run 0, step 1:", lines[0]), lines[0]
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and not p.name.startswith(".cfdesign")}
    assert after == before
    assert not [p for p in out.iterdir() if p.name.startswith(".staging")]
    # and a fresh directory is not left behind (no chunk was finished)
    fresh = tmp_path / "fresh"
    proc = subprocess.run([sys.executable, "-m", "studies", "study", "comparison", str(bad), "--runs", "2",
                           "--particles", "50", "--set", "sweep_values=[0.2]", "--set", "tuned_in_sweeps=false",
                           "--quiet", "--out", str(fresh)], capture_output=True, text=True, env=env, cwd=ROOT,
                          timeout=600)
    assert proc.returncode == 1, proc.stderr
    assert not fresh.exists()


# --------------------------------------------------------------- symlinks, --force, empty out, full disk
def _snapshot(root: Path) -> dict:
    """Every entry under ``root`` (links not followed): path -> the file's bytes, the link's target, or a dir."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            out[rel] = ("link", os.readlink(p)) if p.is_symlink() else ("dir",) if p.is_dir() else p.read_bytes()
    return out


def _victim(tmp_path) -> Path:
    """A directory of the user's, outside OUT, holding files named as cfdesign names its own."""
    v = tmp_path / "victim"
    (v / "toy").mkdir(parents=True)
    for d in (v, v / "toy"):
        for name in ("manifest.json", "log.jsonl", "runs_0000000_0000004.npz", "notes.txt", LOCK_NAME):
            (d / name).write_text(f"the user's {name}\n")
    return v


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("planted", [CHUNKS_DIR, f"{CHUNKS_DIR}/toy", f"{CHUNKS_DIR}/toy/manifest.json",
                                     f"{CHUNKS_DIR}/toy/log.jsonl", f"{CHUNKS_DIR}/toy/runs_0000000_0000004.npz",
                                     LOCK_NAME])
def test_a_link_planted_in_the_chunk_store_is_refused_and_its_target_untouched(tmp_path, planted, force):
    out, victim = tmp_path / "out", _victim(tmp_path)
    _store(out)
    link = out / planted
    target = victim / ("toy" if planted == CHUNKS_DIR + "/toy" else "" if planted == CHUNKS_DIR
                       else "toy/" + Path(planted).name)
    if link.is_dir() and not link.is_symlink():
        import shutil
        shutil.rmtree(link)
    else:
        link.unlink()
    link.symlink_to(target)
    before = _snapshot(victim)
    with pytest.raises(InputError, match=re.escape(str(link))) as exc:
        _store(out, force=force)
    assert "symbolic link" in str(exc.value) and "\n" not in str(exc.value)
    assert _snapshot(victim) == before


def test_force_removes_only_what_the_chunk_store_wrote(tmp_path):
    out = tmp_path / "out"
    _store(out)
    label = out / CHUNKS_DIR / "toy"
    mine = {"notes.txt": b"the user's notes", "runs_0000000_0000004.npz.bak": b"a copy the user keeps",
            "runs_old.npz": b"not a name the store gives"}
    for name, data in mine.items():
        (label / name).write_bytes(data)
    res = _store(out, force=True)
    assert len(res.computed) == 3 and not res.reused
    for name, data in mine.items():
        assert (label / name).read_bytes() == data, name
    assert np.array_equal(res.arrays["x"], reference(12, 4))


def test_a_stale_staging_directory_is_removed_when_the_lock_is_taken(tmp_path):
    from designer.fileio import replaced_outputs

    out = tmp_path / "out"
    out.mkdir()
    stale = out / ".staging-killed"  # what a killed writer leaves
    (stale / "sub").mkdir(parents=True)
    (stale / "results.json").write_text("{}")
    (out / "mine.txt").write_text("the user's")
    with output_lock(out):
        pass
    assert not stale.exists() and (out / "mine.txt").read_text() == "the user's"
    holder = _hold(out)  # a live writer's staging directory is never touched
    try:
        (out / ".staging-live").mkdir()
        with pytest.raises(InputError, match="being written"):
            with replaced_outputs(out):
                pass
        assert (out / ".staging-live").is_dir()
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize("planted", [".cfdesign-outputs.json", "results.json", "report.html", "fig_a.png",
                                     ".staging-x", "table.md"])
def test_a_link_planted_among_the_outputs_is_refused_and_its_target_untouched(tmp_path, planted):
    from studies.outputs import write_outputs

    out, victim = tmp_path / "out", _victim(tmp_path)
    results = {"filters": {"a": {"rmse": 1.0}}}
    write_outputs(out, results, lambda d: (d / "fig_a.png").write_bytes(b"png"), lambda r: "| table |\n")
    link = out / planted
    if link.exists():
        link.unlink()
    link.symlink_to(victim / "notes.txt")
    before = _snapshot(victim)
    with pytest.raises(InputError, match=re.escape(str(link))):
        write_outputs(out, results, lambda d: (d / "fig_a.png").write_bytes(b"png2"), lambda r: "| table |\n")
    assert _snapshot(victim) == before
    assert link.is_symlink()


def test_a_file_the_user_wrote_is_never_replaced_by_an_output(tmp_path):
    """One rule for every command, from the CLI and the API alike: an output replaces only what cfdesign wrote."""
    from studies.outputs import write_outputs

    out = tmp_path / "out"
    out.mkdir()
    (out / "report.html").write_text("the user's own report")
    with pytest.raises(InputError, match=re.escape(str(out / "report.html")) + ".*not written by cfdesign"):
        write_outputs(out, {"filters": {"a": {"rmse": 1.0}}}, lambda d: None, lambda r: "| table |\n")
    assert (out / "report.html").read_text() == "the user's own report"
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".cfdesign")) == ["report.html"]


def test_only_a_changed_model_is_named_as_such(tmp_path):
    monte_carlo(toy_task, store=tmp_path, config={"scale": 1.0, "model": "sha256:aaa"}, **KW)
    with pytest.raises(InputError, match=r"other settings \(config, config\.model\); the model changed since these "
                                         r"runs were computed"):
        monte_carlo(toy_task, store=tmp_path, config={"scale": 1.0, "model": "sha256:bbb"}, **KW)
    with pytest.raises(InputError) as exc:  # another key too: still named, the model's hint kept
        monte_carlo(toy_task, store=tmp_path, config={"scale": 2.0, "model": "sha256:bbb"}, **KW)
    assert "config.model, config.scale" in str(exc.value) and "the model changed" in str(exc.value)
    with pytest.raises(InputError) as exc:
        monte_carlo(toy_task, store=tmp_path, config={"scale": 2.0, "model": "sha256:aaa"}, **KW)
    assert "model changed" not in str(exc.value)


def test_the_refusal_names_force_as_the_caller_gives_it(tmp_path):
    monte_carlo(toy_task, store=tmp_path, config={"scale": 1.0}, **KW)
    with pytest.raises(InputError) as exc:
        monte_carlo(toy_task, store=tmp_path, config={"scale": 2.0}, **KW)
    assert "force=True" in str(exc.value) and "--force" in str(exc.value)


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _enospc(*args, **kwargs):
    import errno

    if args and hasattr(args[0], "write"):
        args[0].write(b"half a file")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_while_writing_a_chunk_is_one_line_naming_it(tmp_path, monkeypatch, capfd):
    from studies.cli import main
    import studies.runner as runner

    out = tmp_path / "out"
    monkeypatch.setattr(runner.np, "savez", _enospc)
    code = main(["study", "consensus-robot", "--runs", "2", "--quiet", "--set", "steps=3", "--out", str(out)])
    line = _one_line(capfd.readouterr().err)
    assert code == 1
    assert str(out / CHUNKS_DIR / "consensus-robot" / "runs_0000000_0000002.npz") in line, line
    assert "No space left on device" in line
    left = [str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()]
    assert not [p for p in left if p.endswith(".tmp") or p.endswith(".npz")], left  # nothing half-written


@pytest.mark.slow
def test_a_full_disk_while_writing_the_outputs_names_the_file_and_keeps_the_last_ones(tmp_path, monkeypatch, capfd):
    from studies.cli import main
    import designer.fileio as fileio

    out = tmp_path / "out"
    # exit 1: written, but a 2-step design is never certified (too short to show a steady bound)
    assert main(["design", "indoor-robot", "--mode", "paper", "--steps", "2", "--out", str(out)]) == 1
    assert (out / "schedule.json").is_file()
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK_NAME}
    capfd.readouterr()
    monkeypatch.setattr(fileio.os, "fsync", _enospc)
    code = main(["design", "indoor-robot", "--mode", "paper", "--steps", "3", "--out", str(out)])
    line = _one_line(capfd.readouterr().err)
    assert code == 1 and "No space left on device" in line
    assert re.search(re.escape(str(out)) + r"/(schedule\.npz|schedule\.json|fig_\w+\.png|report\.\w+)'", line), line
    # the last outputs, complete; no staging directory left
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK_NAME} == before


def test_a_full_disk_while_appending_to_the_log_names_it(tmp_path, monkeypatch):
    import designer.fileio as fileio

    monkeypatch.setattr(fileio.os, "write", _enospc)
    with pytest.raises(OSError) as exc:
        append_line(tmp_path / "log.jsonl", "a line")
    assert exc.value.filename == str(tmp_path / "log.jsonl")
    assert (tmp_path / "log.jsonl").read_bytes() == b""


@pytest.mark.slow
def test_report_takes_the_one_writer_lock(tmp_path, capfd):
    from studies import api
    from studies.cli import main

    out = tmp_path / "out"
    assert main(["design", "indoor-robot", "--mode", "paper", "--steps", "2", "--out",
                 str(out)]) == 1  # written, not certified
    capfd.readouterr()
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK_NAME}
    holder = _hold(out)
    try:
        with pytest.raises(InputError, match=rf"being written by process {holder.pid}"):
            api.report(out)
        assert main(["report", str(out)]) == 2
        assert f"being written by process {holder.pid}" in _one_line(capfd.readouterr().err)
    finally:
        holder.kill()
        holder.wait()
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != LOCK_NAME} == before
    html, md = api.report(out)  # free again: rewritten in place
    assert html == out / "report.html" and md == out / "report.md" and html.is_file()
