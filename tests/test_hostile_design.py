"""A design directory is a file from elsewhere (a colleague's archive may be hostile): ``cfdesign export`` never turns
its text into code, never imports a model file the user did not name, and refuses a malformed ``schedule.json`` with
one line and exit 2, as ``filter --schedule``, ``node_filter`` and ``report`` do; the C it writes compiles without
a warning under ``-std=c99 -Wall -Wextra -pedantic`` for every exported rule."""
from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import shutil
import stat
import subprocess
import threading

import pytest

import studies
from designer.digest import source_files_digest
from designer.export_c import c_text
from designer.jitcache import ENV
from designer.validation import CfdesignWarning, InputError
from studies import provenance, schemas
from studies.cli import main

CC = shutil.which("gcc") or shutil.which("cc")
STRICT = ["-std=c99", "-Wall", "-Wextra", "-pedantic"]
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler")  # a fresh machine has gcc: CI always runs these

TINY = '''"""A cart on a line seen by three posts (a test's model)."""
import casadi as ca
import numpy as np
from designer import AttackSpec, Gaussian, Model, Sensor, SensorNetwork

STEPS = 6
NETWORK = SensorNetwork.from_edges(3, [(0, 1), (1, 2), (2, 0)])
ATTACKS = AttackSpec(dos=0.2)


def model():
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[0] + 0.1 * x[1], 0.95 * x[1])
    sensors = [Sensor(f"post{i}", ca.vertcat(x[0] - i), Gaussian.zero_mean([[0.1]])) for i in range(3)]
    return Model(NAME, x, f, sensors, Gaussian.zero_mean(np.diag([0.01, 0.01])),
                 Gaussian([0.0, 1.0], np.diag([1.0, 1.0])), state_names=STATES)
'''
# the fields export reads as identifiers (which model, which rule, which parameters): planted there, a payload must
# be refused (exit 2) or be harmless; every other string of schedule.json is text and export must still succeed
IDENTIFIERS = ("scenario", "source", "source_digest", "source_seal", "model_digest", "options", "params")


def payloads(marker) -> dict[str, str]:
    """Texts that would run code, break the C or flood it, were they pasted into a comment or a string; the
    constructor ``touch``-es ``marker``."""
    ctor = f'__attribute__((constructor)) static void x(void) {{ system("touch {marker}"); }}'
    return {"comment": f"certified */ #include <stdlib.h>\n{ctor} /*",
            "include": "#include <stdlib.h>",
            "newlines": f"certified\n#include <stdlib.h>\r\n{ctor}\r\n#error injected\r",
            "nul": "certified\x00*/\x00" + ctor,
            "quotes": 'certified" \\ "\\\n' + ctor,
            "trigraph": f"certified ??/\n{ctor} ??= ??( ??' *??/\n/",
            "long": "certified */ " + "x" * (1 << 20)}


def tiny_model(directory, name="tiny", states=("position", "speed")):
    path = directory / "tiny.py"
    path.write_text(f"NAME = {name!r}\nSTATES = {list(states)!r}\n" + TINY)
    return path


def strings(obj, path=()):
    """Every string value of a JSON document, with its path."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from strings(v, path + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from strings(v, path + (i,))
    elif isinstance(obj, str):
        yield path


def planted(obj, paths, text):
    for path in paths:
        o = obj
        for p in path[:-1]:
            o = o[p]
        o[path[-1]] = text
    return obj


def plant(design, into, paths_of, text):
    """A copy of design directory ``design`` in ``into`` whose ``schedule.json`` has ``text`` at every string path
    ``paths_of(schedule)`` gives."""
    shutil.copytree(design, into)
    meta = json.loads((into / "schedule.json").read_text())
    (into / "schedule.json").write_text(json.dumps(planted(meta, list(paths_of(meta)), text)))
    return into


def build_strict(directory) -> subprocess.CompletedProcess:
    """``make test`` with the generated Makefile and every warning an error (or its two commands without make)."""
    flags = " ".join(STRICT + ["-O1", "-Werror"])
    if shutil.which("make"):
        return subprocess.run(["make", "-s", "test", f"CC={CC}", f"CFLAGS={flags}"], cwd=directory,
                              capture_output=True, text=True, timeout=300)
    run = subprocess.run([CC, *flags.split(), "-o", "cfd_test", "cfd_test.c", "cfd_node.c", "cfd_model.c", "-lm"],
                         cwd=directory, capture_output=True, text=True, timeout=300)
    return run if run.returncode else subprocess.run(["./cfd_test", "replay.txt"], cwd=directory,
                                                     capture_output=True, text=True, timeout=300)


def one_line_error(err: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cfdesign: error: ") and "Traceback" not in err, err[:2000]
    assert len(lines[0]) < 1000


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("user"))


@pytest.fixture(scope="module")
def relay(tiny, tmp_path_factory):
    """A relay design of the tiny model (its directory)."""
    des = tmp_path_factory.mktemp("relay") / "design"
    assert main(["design", str(tiny), "--mode", "relay", "--out", str(des)]) in (0, 1)
    return des


@pytest.fixture(scope="module")
def log(tiny, tmp_path_factory):
    out = tmp_path_factory.mktemp("log") / "run.npz"
    assert main(["simulate", str(tiny), "--steps", "6", "--seed", "3", "--out", str(out)]) == 0
    return out


def test_c_text_never_ends_a_comment_or_a_string():
    """Whatever the text, c_text's is printable ASCII with no comment or string end, no backslash, no trigraph, no
    line end, and at most its limit; plain names pass unchanged."""
    marker = "/tmp/PWNED"
    texts = list(payloads(marker).values()) + ["*/", "/*", "*" + "/", "a*\n/", "??/", "é ü \u202e", "\x7f\x1b[2J"]
    for t in texts:
        for limit in (120, 10):
            got = c_text(t, limit)
            assert all(0x20 <= ord(c) < 0x7F for c in got) and len(got) <= limit
            assert not any(s in got for s in ("*/", "/*", "\\", '"', "??", "\n", "\r", "\x00"))
    assert c_text("indoor-robot") == "indoor-robot" and c_text("x, y, theta") == "x, y, theta"


@pytest.mark.parametrize("kind", list(payloads("m")))
def test_hostile_text_in_every_field_never_becomes_code(kind, relay, tiny, log, tmp_path, capsys):
    """Each payload in every string of schedule.json but the identifiers: export succeeds, states the verdict as
    'unknown', echoes none of the text; the sources build and pass make test with -std=c99 -Wall -Wextra -pedantic
    -Werror; the constructor's marker is never created, anywhere; filter --schedule's report names the verdict as
    'unknown'."""
    marker = tmp_path / "PWNED"
    text = payloads(marker)[kind]
    des = plant(relay, tmp_path / "design", lambda meta: [p for p in strings(meta) if p[0] not in IDENTIFIERS],
                text)
    out = tmp_path / "c"
    assert main(["export", str(des), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "the design's verdict is 'unknown'" in said and "touch" not in said and "\x00" not in said
    header = (out / "cfd_node.h").read_text()
    assert "The design's verdict: unknown (" in header
    sources = "".join((out / name).read_text() for name in ("cfd_node.h", "cfd_node.c", "cfd_test.c", "Makefile"))
    assert "touch" not in sources and "#error" not in sources and "??/" not in sources
    run = build_strict(out)
    assert run.returncode == 0, run.stdout + run.stderr
    assert not marker.exists()
    # the designed filter on a log: its report names the design's verdict as a word of the vocabulary only
    assert main(["filter", str(tiny), "--data", str(log), "--schedule", str(des), "--out", str(tmp_path / "f")]) == 0
    report = (tmp_path / "f" / "report.md").read_text()
    assert "(verdict there: unknown)" in report and "touch" not in report


@pytest.mark.parametrize("field", IDENTIFIERS)
def test_hostile_identifiers_are_refused_or_harmless(field, relay, tmp_path, capsys):
    """The constructor payload in an identifier field (every string under it): exit 2 with one line and nothing
    written, or an export that builds strictly and runs nothing."""
    marker = tmp_path / "PWNED"
    des = tmp_path / "design"
    shutil.copytree(relay, des)
    meta = json.loads((des / "schedule.json").read_text())
    text = payloads(marker)["comment"]
    paths = [p for p in strings(meta) if p[0] == field]
    if not paths:  # no string there (a model without parameters): a string field of that name
        meta[field] = {"x": text} if field in ("options", "params") else text
    (des / "schedule.json").write_text(json.dumps(planted(meta, paths, text)))
    out = tmp_path / "c"
    code = main(["export", str(des), "--out", str(out)])
    if code == 2:
        one_line_error(capsys.readouterr().err)
        assert not out.exists()
    else:
        assert code == 0
        run = build_strict(out)
        assert run.returncode == 0, run.stdout + run.stderr
    assert not marker.exists()


def test_export_imports_no_model_file_it_cannot_verify(relay, tiny, log, tmp_path, capsys):
    """source naming a planted Python file (which would create a marker when imported): without a recorded
    source_digest, with the design's own digest, by a relative path, or the design's file edited since: exit 2
    with one line asking for --scenario, nothing imported or written; the model given with --scenario exports;
    filter --schedule and node_filter never import it."""
    marker = tmp_path / "IMPORTED"
    evil = tmp_path / "evil.py"
    evil.write_text(f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n" + tiny.read_text())
    edited = tmp_path / "edited" / "tiny.py"
    edited.parent.mkdir()
    edited.write_text(f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n" + tiny.read_text())
    original = json.loads((relay / "schedule.json").read_text())
    assert original["source"] == str(tiny.resolve()) and len(original["source_digest"]) == 64
    cases = {"no digest": {"source": str(evil), "source_digest": None},
             "the design's digest": {"source": str(evil)},
             "relative": {"source": "evil.py", "source_digest": None},
             "edited since": {"source": str(edited)}}
    for name, change in cases.items():
        des = tmp_path / name.replace(" ", "_")
        shutil.copytree(relay, des)
        (des / "schedule.json").write_text(json.dumps({**original, **change}))
        out = tmp_path / f"c_{des.name}"
        assert main(["export", str(des), "--out", str(out)]) == 2, name
        err = capsys.readouterr().err
        one_line_error(err)
        assert "--scenario" in err and not out.exists() and not marker.exists(), name
    out = tmp_path / "given"
    assert main(["export", str(tmp_path / "no_digest"), "--scenario", str(tiny), "--out", str(out)]) == 0
    assert (out / "cfd_node.c").is_file() and not marker.exists()
    # filter --schedule and node_filter take the model from the user and read the design as data only
    des = tmp_path / "the_design's_digest"
    assert main(["filter", str(tiny), "--data", str(log), "--schedule", str(des), "--out", str(tmp_path / "f")]) == 0
    assert studies.node_filter(str(tiny), schedule=des, node=0) is not None and not marker.exists()


REMOVED = object()  # a field taken out of a record


def forged(relay, into, change: dict) -> None:
    """A copy of design directory ``relay`` in ``into`` whose ``schedule.json`` has the fields ``change`` (REMOVED:
    the field taken out)."""
    shutil.copytree(relay, into)
    meta = {**json.loads((relay / "schedule.json").read_text()), **change}
    (into / "schedule.json").write_text(json.dumps({k: v for k, v in meta.items() if v is not REMOVED}))


def test_a_design_made_here_is_sealed_and_exports(relay, tmp_path):
    """design writes source_seal, this account's HMAC of the fields that decide the model (recomputed here from
    the key file, independently of studies.provenance), and export builds the design's own file without
    --scenario."""
    meta = json.loads((relay / "schedule.json").read_text())
    key = provenance.key_path().read_bytes()
    fields = {k: meta.get(k) for k in ("source", "source_digest", "model_digest", "scenario", "params")}
    text = b"cfdesign.design-seal/1\0" + json.dumps(fields, sort_keys=True, separators=(",", ":")).encode()
    assert len(key) == 32 and meta["source_seal"] == hmac.new(key, text, hashlib.sha256).hexdigest()
    assert schemas.validate_output(relay / "schedule.json") == [relay / "schedule.json"]
    assert main(["export", str(relay), "--out", str(tmp_path / "c")]) == 0
    assert (tmp_path / "c" / "cfd_node.c").is_file()


def test_a_forged_record_of_a_planted_file_is_refused(relay, tiny, tmp_path, monkeypatch, capsys):
    """source naming a planted Python file (which would create a marker when imported) with that file's own
    source_digest, and no seal, a null one, one not of hex digits, the design's seal (of another record), or a seal
    of the forged record under another account's key; and a sealed record whose parameters or model digest were
    edited: exit 2 with one line saying the directory was not written on this account and asking for --scenario;
    nothing imported, nothing written."""
    marker = tmp_path / "IMPORTED"
    evil = tmp_path / "evil.py"
    evil.write_text(f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n" + tiny.read_text())
    original = json.loads((relay / "schedule.json").read_text())
    record = {**original, "source": str(evil), "source_digest": source_files_digest(evil)}
    home = os.environ[ENV]
    monkeypatch.setenv(ENV, str(tmp_path / "elsewhere"))  # the colleague's account, its own key
    theirs = provenance.seal(record)
    monkeypatch.setenv(ENV, home)
    cases = {"no seal": {"source_seal": REMOVED}, "null seal": {"source_seal": None},
             "not hex": {"source_seal": "*/" * 32}, "the design's seal": {},
             "another account's seal": {"source_seal": theirs}}
    for name, change in cases.items():
        des = tmp_path / name.replace(" ", "_").replace("'", "")
        forged(relay, des, {**record, **change})
        out = tmp_path / f"c_{des.name}"
        assert main(["export", str(des), "--out", str(out)]) == 2, name
        err = capsys.readouterr().err
        one_line_error(err)
        assert "not written by cfdesign design on this account" in err and "--scenario" in err, name
        assert not out.exists() and not marker.exists(), name
    for name, change in {"params": {"params": {"x": 1.0}}, "model_digest": {"model_digest": "0" * 64}}.items():
        des = tmp_path / f"edited_{name}"
        forged(relay, des, change)
        assert main(["export", str(des), "--out", str(tmp_path / "c")]) == 2, name
        err = capsys.readouterr().err
        one_line_error(err)
        assert "its seal does not verify" in err and not (tmp_path / "c").exists(), name


def test_a_design_sealed_under_another_key_needs_the_model_given(relay, tiny, tmp_path, monkeypatch, capsys):
    """The design, exported from another account (another CFDESIGN_CACHE_DIR, with a key of its own or none yet):
    exit 2 naming the reason, nothing written; with --scenario it exports."""
    monkeypatch.setenv(ENV, str(tmp_path / "other"))
    out = tmp_path / "c"
    assert main(["export", str(relay), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    one_line_error(err)
    assert "no design key yet" in err and "--scenario" in err and not out.exists()
    assert not (tmp_path / "other").exists()  # verifying makes no key: a new key verifies nothing
    provenance.seal({"source": "x.py"})  # that account's own key
    assert main(["export", str(relay), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    one_line_error(err)
    assert "its seal does not verify" in err and not out.exists()
    assert main(["export", str(relay), "--scenario", str(tiny), "--out", str(out)]) == 0
    assert (out / "cfd_node.c").is_file()


def test_an_unusable_key_is_named_and_never_fails_a_design(relay, tmp_path, monkeypatch, capsys):
    """A cache directory that cannot hold the key (a read-only home: here its parent is a file): sealing warns and
    seals nothing, export's refusal names the key and why; a built-in's record is not sealed and the key is not
    touched; a damaged or shared key is named, never overwritten."""
    blocked = tmp_path / "file"
    blocked.write_text("")
    monkeypatch.setenv(ENV, str(blocked / "cache"))
    with pytest.warns(CfdesignWarning, match="not sealed as this account's: the design key .* cannot be created"):
        assert provenance.design_seal({"source": str(tmp_path / "m.py"), "source_digest": "0" * 64}) is None
    assert main(["export", str(relay), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    one_line_error(err)
    assert "design key" in err and "cannot be read" in err and "--scenario" in err
    monkeypatch.setenv(ENV, str(tmp_path / "fresh"))
    assert provenance.design_seal({"source": "switching-2d", "source_digest": None}) is None
    assert not (tmp_path / "fresh").exists()
    key = provenance.key_path()
    key.parent.mkdir(parents=True)
    key.write_bytes(b"short")
    key.chmod(0o600)
    with pytest.raises(provenance.KeyUnavailable, match="damaged"):
        provenance.seal({"source": "x.py"})
    key.write_bytes(bytes(32))
    key.chmod(0o644)
    with pytest.raises(provenance.KeyUnavailable, match="readable or writable by other accounts"):
        provenance.seal({"source": "x.py"})
    assert key.read_bytes() == bytes(32)


def test_the_key_is_private_kept_by_cache_clear_and_never_overwritten(tmp_path, monkeypatch, capsys):
    """The key made on first use is 32 bytes, mode 0600 in a 0700 directory; cache clear removes the kernels and
    keeps it; a key already there (another process's) is used, not replaced; eight threads making it at once end
    with one key and one seal."""
    monkeypatch.setenv(ENV, str(tmp_path / "cache"))
    record = {"source": "/m.py", "source_digest": "1" * 64, "params": {"a": [1.5, 2]}}
    s = provenance.seal(record)
    key = provenance.key_path()
    assert key == tmp_path / "cache" / "keys" / "design.key" and len(key.read_bytes()) == 32
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and stat.S_IMODE(key.parent.stat().st_mode) == 0o700
    assert provenance.sealed(record, s) and not provenance.sealed({**record, "params": {"a": [1.5, 3]}}, s)
    (tmp_path / "cache" / "CACHEDIR.TAG").write_text("Signature: 8a477f597d28d172789f06886806bc55\n")
    (tmp_path / "cache" / "kernels").mkdir()
    (tmp_path / "cache" / "kernels" / "k.py").write_text("")
    before = key.read_bytes()
    assert main(["cache", "clear"]) == 0
    assert not (tmp_path / "cache" / "kernels").exists() and key.read_bytes() == before
    assert provenance.sealed(record, s)
    # a key made first by another process: read back, never overwritten
    monkeypatch.setenv(ENV, str(tmp_path / "other"))
    theirs = secrets.token_bytes(32)
    provenance.key_path().parent.mkdir(parents=True)
    provenance.key_path().write_bytes(theirs)
    provenance.key_path().chmod(0o600)
    expected = hmac.new(theirs, b"cfdesign.design-seal/1\0" + json.dumps(
        {k: record.get(k) for k in provenance.SEALED}, sort_keys=True, separators=(",", ":")).encode(),
        hashlib.sha256).hexdigest()
    assert provenance.seal(record) == expected
    with monkeypatch.context() as m:  # made by the other process after this one looked: the creation path
        m.setattr(os.path, "lexists", lambda path: False)
        assert provenance.seal(record) == expected
    assert provenance.key_path().read_bytes() == theirs and os.listdir(provenance.key_path().parent) == ["design.key"]
    # made at once by eight threads
    monkeypatch.setenv(ENV, str(tmp_path / "race"))
    start = threading.Barrier(8)
    seals = []

    def make():
        start.wait()
        seals.append(provenance.seal(record))

    threads = [threading.Thread(target=make) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(seals) == 8 and len(set(seals)) == 1
    assert provenance.sealed(record, seals[0]) and os.listdir(tmp_path / "race" / "keys") == ["design.key"]


MALFORMED = {"a list": "[1, 2]", "a string": '"schedule"', "null": "null", "not JSON": "{", "not UTF-8": b"\xff\xfe{",
             "NaN": '{"scenario": "tiny", "seed": NaN}', "infinity": '{"scenario": "tiny", "seed": -Infinity}',
             "beyond a double": '{"scenario": "tiny", "sigma": 1e999}', "nested": "[" * 100000 + "]" * 100000,
             "a huge integer": '{"scenario": "tiny", "seed": ' + "9" * 5000 + "}"}
WRONG_TYPES = {"scenario": 5, "verdict": ["certified"], "options": 3, "params": [1], "seed": "1", "source": 7,
               "source_digest": "*/", "model_digest": {}, "mode": 2}
WRONG_VALUES = {"seed": -1, "options": {"mode": "relay", "sigma": "x"}}


def test_a_malformed_schedule_is_refused_with_one_line(relay, tiny, log, tmp_path, capsys):
    """schedule.json not an object, not JSON, NaN, infinities, numbers beyond a double, too deep, wrong types or
    values of the fields a command uses: export, filter --schedule and node_filter say so in one line (exit 2,
    nothing written); report refuses what is not a JSON object (it renders the fields it can of any other)."""
    original = json.loads((relay / "schedule.json").read_text())
    cases = dict(MALFORMED)
    cases.update({f"{k} of a wrong type": json.dumps({**original, k: v}) for k, v in WRONG_TYPES.items()})
    cases.update({f"{k} wrong": json.dumps({**original, k: v}) for k, v in WRONG_VALUES.items()})
    for name, text in cases.items():
        des = tmp_path / "d"
        shutil.rmtree(des, ignore_errors=True)
        shutil.copytree(relay, des)
        (des / "schedule.json").write_bytes(text if isinstance(text, bytes) else text.encode())
        commands = [["export", str(des), "--out", str(tmp_path / "c")],
                    ["filter", str(tiny), "--data", str(log), "--schedule", str(des), "--out", str(tmp_path / "f")]]
        if name in MALFORMED:
            commands.append(["report", str(des)])
        for args in commands:
            assert main(args) == 2, (name, args[0])
            one_line_error(capsys.readouterr().err)
        assert not (tmp_path / "c").exists() and not (tmp_path / "f").exists()
        with pytest.raises(InputError):
            studies.node_filter(str(tiny), schedule=des)
    # the parameters a design ran with (export builds the model with them; filter takes the model as given)
    (des / "schedule.json").write_text(json.dumps({**original, "params": {"x" * 100000: 1}}))
    assert main(["export", str(des), "--out", str(tmp_path / "c")]) == 2
    one_line_error(capsys.readouterr().err)


def test_hostile_names_in_the_users_model_are_escaped(tmp_path, capsys):
    """The user's own model named with comment ends, a directive, a trigraph and quotes: its names reach the header
    only through c_text, and the export builds strictly."""
    marker = tmp_path / "PWNED"
    ctor = f'__attribute__((constructor)) static void x(void) {{ system("touch {marker}"); }}'
    model = tiny_model(tmp_path, name=f"t */\n#include <stdlib.h>\n{ctor} /*", states=(f'p"??/\n{ctor}', "v\\"))
    des, out = tmp_path / "design", tmp_path / "c"
    assert main(["design", str(model), "--mode", "flood", "--out", str(des)]) in (0, 1)
    assert main(["export", str(des), "--out", str(out)]) == 0
    header = (out / "cfd_node.h").read_text()
    assert "The model: t _/_#include <stdlib.h>___attribute__" in header
    run = build_strict(out)
    assert run.returncode == 0, run.stdout + run.stderr
    assert not marker.exists()


@pytest.mark.parametrize("mode", ["paper", "scheduled", "relay", "flood"])
def test_every_rules_export_compiles_without_a_warning(mode, relay, tiny, tmp_path):
    """Each exported rule's sources compile with -std=c99 -Wall -Wextra -pedantic and not one warning (the
    compiler's own diagnostics, every file), and the Makefile builds with those flags."""
    des = relay
    if mode != "relay":
        des = tmp_path / "design"
        assert main(["design", str(tiny), "--mode", mode, "--out", str(des)]) in (0, 1)
    out = tmp_path / "c"
    assert main(["export", str(des), "--out", str(out)]) == 0
    assert "-std=c99" in (out / "Makefile").read_text() and "-Wextra -pedantic" in (out / "Makefile").read_text()
    for name in ("cfd_model.c", "cfd_node.c", "cfd_test.c"):
        run = subprocess.run([CC, *STRICT, "-c", name, "-o", "/dev/null"], cwd=out, capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0 and "warning" not in run.stderr, (name, run.stderr[:2000])
    run = subprocess.run(["make", "-s", "test"], cwd=out, capture_output=True, text=True, timeout=300) \
        if shutil.which("make") else build_strict(out)
    assert run.returncode == 0 and "warning" not in run.stderr, run.stdout + run.stderr
