"""Filters on recorded logs (studies.recorded, studies.filter, cfdesign filter): a simulated run written as a log and
filtered gives that run's numbers in the comparison; bad logs are refused naming the file, the array and where."""
from __future__ import annotations

import json

import numpy as np
import pytest

import studies
from designer.validation import InputError
from studies import memory
from studies.cli import main
from studies.comparison import FILTER_REGISTRY, FILTERS
from studies.pipeline import run_study
from studies.recorded import filter_keys, find_filter
from studies.runner import Backend

# A user's model file: a unicycle steered by a known turn rate, seven posts on a ring with two chords, bearings at the
# odd posts and ranges at the even ones.
USER_MODEL = '''"""Seven posts around a steered cart (a user's file): ranges and bearings, a known turn rate."""
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, Sensor, SensorNetwork

STEPS = 18
POSTS = [(0.0, 0.0), (12.0, -2.0), (24.0, 0.0), (26.0, 8.6), (14.0, 22.0), (2.0, 18.0), (12.0, 9.0)]
NETWORK = SensorNetwork.from_edges(7, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (6, 1), (6, 4)])
ATTACKS = AttackSpec(dos=0.25, fdi=0.1, signal=FDISignal(amplitude=0.4, components=(0, 1)))


def inputs(steps):
    return 0.08 * np.sin(0.3 * np.arange(steps))[:, None]


def model():
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 1)
    sensors = []
    for i, (a, b) in enumerate(POSTS):
        if i % 2:
            sensors.append(Sensor(f"post{i}", ca.atan2(x[1] - b, x[0] - a), Gaussian.zero_mean([[0.002]]),
                                  angles=(0,)))
        else:
            sensors.append(Sensor(f"post{i}", ca.sqrt((x[0] - a) ** 2 + (x[1] - b) ** 2),
                                  Gaussian.zero_mean([[0.3]])))
    f = ca.vertcat(x[0] + x[3] * ca.cos(x[2]), x[1] + x[3] * ca.sin(x[2]), x[2] + u[0], x[3])
    return Model("cart", x, f, sensors, Gaussian.zero_mean(np.diag([0.002, 0.002, 0.0005, 0.0005])),
                 Gaussian([10.0, 8.0, 0.3, 0.6], np.diag([0.5, 0.5, 0.02, 0.01])), u=u, position_index=(0, 1))
'''


def _pf(name: str, **options) -> dict:
    """The particle filters' options (particles, seed, run) for filter ``name``, none for another (refused there)."""
    return options if find_filter(FILTER_REGISTRY, name).particles else {}


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    path = tmp_path_factory.mktemp("user") / "cart.py"
    path.write_text(USER_MODEL)
    return path


@pytest.mark.parametrize("target", ["indoor-robot", "user"])
@pytest.mark.slow
def test_a_simulated_run_filtered_from_its_log_gives_the_comparisons_numbers(target, cart, tmp_path):
    """simulate --run r writes run r of the comparison (seed s) as a log; every filter run on it by studies.filter
    equals that run's estimates in the study, bit for bit (node 1's, as the study keeps them), the particle filters
    included (their streams from the log's seed and run)."""
    scenario = str(cart) if target == "user" else target
    res = run_study("comparison", [scenario], runs=3, particles=40, seed=5, sweep_values=(), chunk_size=3,
                    backend=Backend(), quiet=True)
    (arrays,) = res.arrays.values()
    log = tmp_path / "run2.npz"
    sim = studies.simulate(scenario, seed=5, run=2, out=log)
    assert np.array_equal(sim.x, arrays["truth"][2])
    ran = 0
    for f, name in enumerate(FILTERS):
        expected = arrays["estimate"][2, f]
        if np.isnan(expected).all():  # not run or diverged in the study: nothing to compare
            continue
        got = studies.filter(scenario, log, filter=name, **_pf(name, particles=40))
        assert np.array_equal(got.x_hat[:, 0], expected), name
        ran += 1
    assert ran >= 9
    # the seed of the particle filters matters: another seed, other numbers
    pf = FILTERS.index("centralized PF (attack-aware)")
    other = studies.filter(scenario, log, filter="centralized-pf-attack-aware", particles=40, seed=6)
    assert not np.array_equal(other.x_hat[:, 0], arrays["estimate"][2, pf])


def test_a_log_without_channel_records_is_a_run_without_attacks(tmp_path):
    """A log of measurements alone (every packet arrived): KCF on it equals KCF on the same run with its attack
    records zeroed; the recorded attacks change the numbers."""
    sim = studies.simulate("indoor-robot", seed=3, run=0, out=tmp_path / "full.npz")
    with np.load(tmp_path / "full.npz") as d:
        data = {k: d[k] for k in d.files}
    bare = {k: data[k] for k in ("z", "inputs", "x")}
    np.savez(tmp_path / "bare.npz", **bare)
    quiet = dict(data, channel_dos=np.zeros_like(data["channel_dos"]), channel_fdi=np.zeros_like(data["channel_fdi"]),
                 uplink=data["z"])
    np.savez(tmp_path / "quiet.npz", **quiet)
    a = studies.filter("indoor-robot", tmp_path / "bare.npz", filter="kcf")
    b = studies.filter("indoor-robot", tmp_path / "quiet.npz", filter="kcf")
    c = studies.filter("indoor-robot", tmp_path / "full.npz", filter="kcf")
    assert np.array_equal(a.x_hat, b.x_hat) and not np.array_equal(a.x_hat, c.x_hat)
    assert sim.attacks.dos.any() and sim.attacks.fdi.any()
    # the centralized EKF skips the uplinks a log marks lost (NaN)
    lossy = dict(bare, uplink=np.where(np.arange(data["z"].shape[1]) == 0, np.nan, data["z"]))
    np.savez(tmp_path / "lossy.npz", **lossy)
    e = studies.filter("indoor-robot", tmp_path / "lossy.npz", filter="centralized-ekf-trusts-every-packet")
    full = studies.filter("indoor-robot", tmp_path / "bare.npz", filter="centralized-ekf-trusts-every-packet")
    assert np.isfinite(e.x_hat).all() and not np.array_equal(e.x_hat, full.x_hat)


@pytest.mark.slow
def test_cli_filter_with_a_design_directory_writes_its_estimates(cart, tmp_path, capsys):
    """cfdesign design, then cfdesign filter --schedule DIR on a simulated log of the user's model: the designed
    filter runs with the design's options and equals studies.filter with the same gain rule; the files hold what
    the result holds."""
    log, des, out = tmp_path / "log.npz", tmp_path / "des", tmp_path / "est"
    assert main(["simulate", str(cart), "--seed", "4", "--out", str(log)]) == 0
    assert main(["design", str(cart), "--mode", "relay", "--rounds", "2", "--out", str(des)]) in (0, 1)
    capsys.readouterr()
    assert main(["filter", str(cart), "--data", str(log), "--schedule", str(des), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "relay EKF (relay design)" in said and "RMSE" in said
    ref = studies.filter(str(cart), log, filter="relay", schedule=des)
    with np.load(out / "estimates.npz") as d:
        assert np.array_equal(d["x_hat"], ref.x_hat) and np.array_equal(d["Phi"], ref.cov)
        assert np.array_equal(d["x"], ref.truth)
    rows = (out / "estimates.csv").read_text().splitlines()
    assert rows[0].startswith("step,node,") and len(rows) == 1 + ref.x_hat.shape[0] * ref.x_hat.shape[1]
    last = rows[-1].split(",")
    assert np.allclose([float(v) for v in last[2:-1]], ref.x_hat[-1, -1], rtol=0, atol=0)
    assert "relay" in (out / "report.md").read_text() and (out / "fig_estimates.png").stat().st_size > 0
    # the report's per-node errors: their mean square is the overall one; each node's row is in the table
    per = ref.per_node()
    assert np.isclose(np.sqrt(np.mean(per["rmse"] ** 2)), ref.rmse(), rtol=1e-12)
    e2 = ((ref.truth[1:, None] - ref.x_hat[1:]) ** 2).sum(-1) / np.trace(ref.cov[1:], axis1=-2, axis2=-1)
    assert np.allclose(per["energy"], e2.mean(axis=0), rtol=1e-12)
    text = (out / "report.md").read_text()
    assert all(f"| {i} | {r:.4g} | {q:.3g} |" in text for i, (r, q) in enumerate(zip(per["rmse"], per["energy"])))
    assert ("exceeds the bound on average" in text) == bool(np.any(per["energy"] > 1))
    # the design's rounds are used: the default design (the diameter's rounds) gives other numbers
    default = studies.filter(str(cart), log, filter="relay")
    assert not np.array_equal(default.x_hat, ref.x_hat)
    rec = json.loads((des / "schedule.json").read_text())
    assert ref.design["options"]["rounds"] == rec["options"]["rounds"] == 2
    with pytest.raises(InputError, match="was designed for scenario 'cart', not 'indoor-robot'"):
        studies.filter("indoor-robot", log, schedule=des)
    with pytest.raises(InputError, match="was designed for scenario 'cart', not 'indoor-robot'"):
        studies.node_filter("indoor-robot", schedule=des)
    node = studies.node_filter(str(cart), schedule=des, node=0)  # the design's rounds: its ball within 2 hops
    assert len(node.ball) < 7 and node.ball[0] == 0
    cart.write_text(USER_MODEL.replace("[[0.3]]", "[[0.35]]"))  # the model file edited since the design
    try:
        for call in (lambda: studies.filter(str(cart), log, schedule=des),
                     lambda: studies.node_filter(str(cart), schedule=des)):
            with pytest.raises(InputError, match="designed for another version of the model 'cart'"):
                call()
    finally:
        cart.write_text(USER_MODEL)


def test_filter_names_and_short_names():
    keys = filter_keys(FILTER_REGISTRY)
    assert keys["kcf"] == "KCF" and keys["scheduled"] == "consensus EKF (scheduled design)"
    assert len(keys) == len(FILTER_REGISTRY)  # one short name per filter
    for key, name in keys.items():
        assert find_filter(FILTER_REGISTRY, key).name == name == find_filter(FILTER_REGISTRY, name).name
    with pytest.raises(InputError, match="filter must be one of .*kcf.*got 'kfc'"):
        find_filter(FILTER_REGISTRY, "kfc")
    # the beginning of exactly one short name will do; of two, it names them
    assert find_filter(FILTER_REGISTRY, "local").name == "local EKF at every node (no network)"
    assert find_filter(FILTER_REGISTRY, "centralized-e").name == "centralized EKF (trusts every packet)"
    with pytest.raises(InputError, match=r"'centralized-pf' begins 2 of them \(centralized-pf-attack-aware, "
                                         r"centralized-pf-trusts-every-packet\)"):
        find_filter(FILTER_REGISTRY, "centralized-pf")


def _log(tmp_path, name="bad.npz", **change):
    with np.load(tmp_path / "good.npz") as d:
        data = {k: d[k] for k in d.files}
    data.update(change)
    for k in [k for k, v in change.items() if v is None]:
        data.pop(k)
    path = tmp_path / name
    np.savez(path, **data)
    return path


@pytest.mark.parametrize("case, message", [
    ("no z", r"array 'z' is missing"),
    ("z wrong width", r"array 'z' must have shape any x 16, got 30 x 7"),
    ("z infinite", r"array 'z' holds inf at index \[3, 1\] \(only NaN, a missing value, is allowed there\)"),
    ("flag on no link", r"array 'channel_dos'\[2, 0, 4\] = 1 marks a packet from node 4 to node 0 at step 3, but "
                        r"the network has no link 4 -> 0"),
    ("flag not 0/1", r"array 'channel_fdi' must hold 0 or 1, got 2.0 at index \[0, 0, 0\]"),
    ("lost and falsified", r"the packet from node 1 to node 0 at step 1 is marked both lost"),
    ("fdi without xi", r"array 'channel_xi' is missing"),
    ("inputs missing", r"array 'inputs' must give the model's 2 known inputs per step \(30 x 2\), got none"),
    ("truth short", r"array 'x' must have shape 31 x 3, got 30 x 3"),
    ("missing measurement", r"z\[4, 2\] is missing \(NaN\): filter 'KCF' needs every node's own measurement"),
    ("not npz", r"is not an .npz archive"),
    ("bool z", r"array 'z' must hold numbers \(an integer or floating-point dtype\), got dtype bool \(booleans are "
               r"not measurements\)"),
    ("object z", r"array 'z' has dtype object: a log's arrays hold numbers"),
    ("header lies", r"array 'z' declares shape 30000000 x 16 of float64 \(3840000000 bytes\), but the archive holds "
                    r"3840 bytes for it: the file is damaged"),
])
def test_a_bad_log_is_refused_naming_the_file_and_where(case, message, tmp_path, capsys):
    studies.simulate("indoor-robot", seed=1, out=tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as d:
        z, dos, fdi, x = d["z"], d["channel_dos"], d["channel_fdi"], d["x"]
    bad = {
        "no z": lambda: _log(tmp_path, z=None),
        "z wrong width": lambda: _log(tmp_path, z=z[:, :7]),
        "z infinite": lambda: _log(tmp_path, z=np.where((np.arange(30)[:, None] == 3) & (np.arange(16) == 1), np.inf,
                                                         z)),
        "flag on no link": lambda: _log(tmp_path, channel_dos=_set(dos, (2, 0, 4), 1)),
        "flag not 0/1": lambda: _log(tmp_path, channel_fdi=_set(fdi, (0, 0, 0), 2)),
        "lost and falsified": lambda: _log(tmp_path, channel_dos=_set(dos, (0, 0, 1), 1),
                                           channel_fdi=_set(fdi, (0, 0, 1), 1)),
        "fdi without xi": lambda: _log(tmp_path, channel_xi=None, channel_fdi=_set(fdi, (0, 0, 1), 1)),
        "inputs missing": lambda: _log(tmp_path, inputs=None),
        "truth short": lambda: _log(tmp_path, x=x[:-1]),
        "missing measurement": lambda: _log(tmp_path, z=_set(z, (4, 2), np.nan)),
        "not npz": lambda: (tmp_path / "bad.npz").write_text("step,sensor\n") and tmp_path / "bad.npz",
        "bool z": lambda: _log(tmp_path, z=z > 300),
        "object z": lambda: _object_z(tmp_path, z),
        "header lies": lambda: _forged(tmp_path, 30_000_000, honest=True),
    }[case]()
    _refused(bad, message, f"log {bad}", tmp_path / "out", capsys)


def _refused(bad, message: str, prefix: str, out, capsys) -> str:
    """The log ``bad`` refused by studies.filter (the error begins ``prefix`` and matches ``message``) and by the
    command line (exit 2, one line naming the file, nothing written in ``out``); returns that line."""
    with pytest.raises(InputError, match=message) as err:
        studies.filter("indoor-robot", bad, filter="kcf")
    assert str(err.value).startswith(prefix)
    assert main(["filter", "indoor-robot", "--data", str(bad), "--filter", "kcf", "--out", str(out)]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and str(bad) in said[0]
    assert not (out / "estimates.npz").exists()
    return said[0]


def _object_z(tmp_path, z):
    with np.load(tmp_path / "good.npz") as d:
        data = {k: d[k] for k in d.files}
    data["z"] = z.astype(object)
    np.savez(tmp_path / "bad.npz", **data)  # savez pickles an object array; reading must not
    return tmp_path / "bad.npz"


def _forged(tmp_path, steps: int, *, honest: bool):
    """good.npz with its z.npy replaced by a header declaring ``steps`` x 16 doubles and 3840 zero bytes of data; with
    ``honest`` False the zip directory also claims the declared size (what a deflated run of zeros, a zip bomb,
    declares: 3.84 GB for a few MB stored), with ``honest`` the size of what it holds."""
    import io
    import struct
    import zipfile

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (steps, 16)})
    path = tmp_path / "bad.npz"
    with zipfile.ZipFile(tmp_path / "good.npz") as good, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name in good.namelist():
            zf.writestr(name, head.getvalue() + bytes(3840) if name == "z.npy" else good.read(name))
    if not honest:
        raw = bytearray(path.read_bytes())
        claimed = struct.pack("<I", len(head.getvalue()) + steps * 16 * 8)
        with zipfile.ZipFile(path) as zf:
            local = zf.getinfo("z.npy").header_offset
        raw[local + 22:local + 26] = claimed  # the local header's uncompressed size
        at = raw.index(b"PK\x01\x02")  # z.npy's record in the central directory
        while raw[at + 46:at + 51] != b"z.npy":
            at = raw.index(b"PK\x01\x02", at + 4)
        raw[at + 24:at + 28] = claimed
        path.write_bytes(bytes(raw))
    return path


def _set(a, where, value):
    a = np.array(a, dtype=float if np.isnan(value) else a.dtype)
    a[where] = value
    return a


def test_filter_options_are_checked_before_reading(tmp_path):
    with pytest.raises(InputError, match="give the filter to run"):
        studies.filter("indoor-robot", tmp_path / "none.npz")
    with pytest.raises(InputError, match="particles must be an integer >= 2, got 1"):
        studies.filter("indoor-robot", tmp_path / "none.npz", filter="centralized-pf-attack-aware", particles=1)
    with pytest.raises(InputError, match=r"log .*none.npz: no such file"):
        studies.filter("indoor-robot", tmp_path / "none.npz", filter="kcf")
    with pytest.raises(InputError, match="not a design directory"):
        studies.filter("indoor-robot", tmp_path / "none.npz", schedule=tmp_path)
    with pytest.raises(InputError, match="run applies to a scenario with a sensor network"):
        studies.simulate("switching-2d", run=1)


# ------------------------------------------------------------------------------------------------------ CSV logs
@pytest.mark.parametrize("target", ["indoor-robot", "user"])
@pytest.mark.slow
def test_the_csv_form_of_a_log_gives_the_same_numbers(target, cart, tmp_path):
    """simulate --out LOG.csv writes the same run as LOG.npz; every filter on the CSV equals the filter on the NPZ
    (the particle filters given the NPZ's seed and run, which a CSV does not carry); both follow their schemas."""
    from studies import schemas

    scenario = str(cart) if target == "user" else target
    studies.simulate(scenario, seed=7, run=1, out=tmp_path / "log.npz")
    studies.simulate(scenario, seed=7, run=1, out=tmp_path / "log.csv")
    schemas.validate_log(tmp_path / "log.npz")
    schemas.validate_log(tmp_path / "log.csv")
    for name in FILTERS:
        try:
            a = studies.filter(scenario, tmp_path / "log.npz", filter=name, **_pf(name, particles=30))
        except InputError as exc:  # a paper design that cannot start on the user's model: both refuse it
            with pytest.raises(InputError, match="cannot start"):
                studies.filter(scenario, tmp_path / "log.csv", filter=name, **_pf(name, particles=30))
            assert "cannot start" in str(exc)
            continue
        b = studies.filter(scenario, tmp_path / "log.csv", filter=name, **_pf(name, particles=30, seed=7, run=1))
        assert np.array_equal(a.x_hat, b.x_hat, equal_nan=True), name
        assert np.array_equal(a.truth, b.truth) and np.array_equal(a.cov, b.cov, equal_nan=True), name


def test_an_absent_csv_row_is_a_missing_measurement_and_lost_packets(tmp_path):
    """A (step, sensor) row left out of the CSV: the same log as the NPZ with that measurement NaN (the fusion
    centre skips it) and every packet to that node at that step lost (KCF)."""
    studies.simulate("indoor-robot", seed=2, out=tmp_path / "log.csv")
    studies.simulate("indoor-robot", seed=2, out=tmp_path / "log.npz")
    lines = (tmp_path / "log.csv").read_text().splitlines()
    gone = next(i for i, line in enumerate(lines) if line.startswith("5,3,"))
    (tmp_path / "cut.csv").write_text("\n".join(lines[:gone] + lines[gone + 1:]) + "\n")
    with np.load(tmp_path / "log.npz") as d:
        data = {k: d[k] for k in d.files}
    data["z"][4, 6:8] = np.nan
    data["uplink"][4, 6:8] = np.nan
    data["channel_dos"][4, 3] = np.asarray(load_network_adjacency())[3]
    data["channel_fdi"][4, 3] = 0
    np.savez(tmp_path / "cut.npz", **data)
    for name in ("centralized-ekf-trusts-every-packet", "centralized-pf-attack-aware"):
        a = studies.filter("indoor-robot", tmp_path / "cut.csv", filter=name, **_pf(name, seed=2))
        b = studies.filter("indoor-robot", tmp_path / "cut.npz", filter=name, **_pf(name, seed=2, run=0))
        assert np.array_equal(a.x_hat, b.x_hat), name
    with pytest.raises(InputError, match=r"z\[4, 6\] is missing"):
        studies.filter("indoor-robot", tmp_path / "cut.csv", filter="kcf")


def load_network_adjacency():
    from studies.scenarios import load_scenario

    return load_scenario("indoor-robot").network.adjacency


@pytest.mark.parametrize("case, message", [
    ("bad number", r"line 3, column 'z2': 'abc' is not a number"),
    ("infinite", r"line 3, column 'z1': 'inf' is not a finite number"),
    ("unknown column", r"line 1, column 'speed': unknown column"),
    ("missing column", r"line 1: column 'z2' is missing"),
    ("not a neighbour", r"line 3, column 'from_4': node 4 is not a neighbour of node 0: the cell must be empty"),
    ("bad flag", r"line 3, column 'from_1': 'yes' must be 1 \(received\), 0 \(lost\) or f:XI_1;...;XI_nx"),
    ("short signal", r"line 3, column 'from_1': 'f:0.1;0.2': a falsified packet is f: and its injected signal, 3 "
                     r"finite numbers"),
    ("duplicate row", r"line 4, column 'sensor': a second row for step 1 and sensor 0 \(first on line 3\)"),
    ("inputs differ", r"line 4, column 'u1': the inputs of step 1 differ from line 3's"),
    ("sensor out of range", r"line 3, column 'sensor': '8' is not an integer in \[0, 7\]"),
    ("ragged", r"line 3: 5 cells, the header has 19"),
    ("underscore", r"line 3, column 'z1': '1_0' is not a number \(a decimal number: digits with an optional sign"),
    ("other digits", r"line 3, column 'z2': '\u0661\u0662' is not a number"),
    ("nan", r"line 3, column 'z1': 'nan' is not a finite number \(leave the cell empty for a missing value\)"),
    ("superscript sensor", r"line 3, column 'sensor': '\xb2' is not an integer in \[0, 7\]"),
    ("signal underscore", r"line 3, column 'from_1': 'f:1_0;0;0': a falsified packet is f: and its injected signal"),
])
def test_a_bad_csv_log_is_refused_naming_the_line_and_column(case, message, tmp_path, capsys):
    studies.simulate("indoor-robot", seed=1, out=tmp_path / "good.csv")
    lines = (tmp_path / "good.csv").read_text().splitlines()
    head = lines[0].split(",")

    def cell(line: int, column: str, value: str) -> list[str]:
        cells = lines[line - 1].split(",")
        cells[head.index(column)] = value
        return lines[:line - 1] + [",".join(cells)] + lines[line:]

    changed = {
        "bad number": lambda: cell(3, "z2", "abc"),
        "infinite": lambda: cell(3, "z1", "inf"),
        "unknown column": lambda: [lines[0] + ",speed"] + [line + "," for line in lines[1:]],
        "missing column": lambda: [",".join(c for c in head if c != "z2")]
        + [",".join(v for c, v in zip(head, line.split(",")) if c != "z2") for line in lines[1:]],
        "not a neighbour": lambda: cell(3, "from_4", "1"),
        "bad flag": lambda: cell(3, "from_1", "yes"),
        "short signal": lambda: cell(3, "from_1", "f:0.1;0.2"),
        "duplicate row": lambda: lines[:3] + [lines[2]] + lines[3:],
        "inputs differ": lambda: cell(4, "u1", "0.07"),
        "sensor out of range": lambda: cell(3, "sensor", "8"),
        "ragged": lambda: lines[:2] + ["1,0,1,2,3"] + lines[3:],
        "underscore": lambda: cell(3, "z1", "1_0"),
        "other digits": lambda: cell(3, "z2", "\u0661\u0662"),  # Arabic-Indic 12: Python's float() reads it
        "nan": lambda: cell(3, "z1", "nan"),
        "superscript sensor": lambda: cell(3, "sensor", "\xb2"),  # a digit to str.isdigit, not to int()
        "signal underscore": lambda: cell(3, "from_1", "f:1_0;0;0"),
    }[case]()
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(changed) + "\n", encoding="utf-8")
    assert "line" in _refused(bad, message, f"log {bad}: line ", tmp_path / "o", capsys)


def test_the_log_schemas_reject_what_breaks_the_format(tmp_path):
    from studies import schemas

    studies.simulate("indoor-robot", seed=1, out=tmp_path / "log.npz")
    good = schemas.log_json(tmp_path / "log.npz")
    schemas.validate("log", good)
    flag = json_copy(good)
    flag["channel_dos"][0][0][1] = 2
    with pytest.raises(InputError, match=r"\$\.channel_dos\[0\]\[0\]\[1\]"):
        schemas.validate("log", flag)
    both = json_copy(good)
    both["channel_dos"][3][0][1], both["channel_fdi"][3][0][1] = 1, 1
    with pytest.raises(InputError, match=r"\$\.channel_fdi\[3\]\[0\]\[1\]: a packet marked both lost"):
        schemas.validate("log", both)
    short = json_copy(good)
    short["x"] = short["x"][:-1]
    with pytest.raises(InputError, match=r"\$\.x: 30 entries along its first axis, expected 31"):
        schemas.validate("log", short)
    row = schemas.read_log_csv_rows(write_csv(tmp_path))[1]
    schemas.validate("log_csv", row)
    for change, where in (({"speed": 1.0}, r"\$: 'speed' does not match any of the regexes"),
                          ({"from_1": "yes"}, r"\$\.from_1"), ({"step": -1}, r"\$\.step"), ({"z1": "abc"}, r"\$\.z1")):
        with pytest.raises(InputError, match=where):
            schemas.validate("log_csv", {**row, **change})
    lines = (tmp_path / "log.csv").read_text().splitlines()  # a number only in decimal notation, as the reader
    head = lines[0].split(",")
    for text in ("1_0", "\u0661\u0662", "nan"):
        cells = lines[2].split(",")
        cells[head.index("z1")] = text
        (tmp_path / "odd.csv").write_text("\n".join([*lines[:2], ",".join(cells), *lines[3:]]) + "\n", encoding="utf-8")
        with pytest.raises(InputError, match=r"odd.csv row 1 \(line 3\).*\$\.z1"):
            schemas.validate_log(tmp_path / "odd.csv")


# ------------------------------------------------------------------ what spreadsheets write, and sizes beyond memory
def test_a_bom_and_crlf_csv_log_gives_the_clean_logs_numbers_bit_for_bit(tmp_path):
    """A CSV log as a spreadsheet program saves it (a UTF-8 BOM before the header, CRLF line ends) is the same log:
    every filter's estimates and covariances equal those on the clean file, bit for bit; the schema reads it too."""
    from studies import schemas

    clean = write_csv(tmp_path)
    text = clean.read_text(encoding="utf-8")
    ref = {name: studies.filter("indoor-robot", clean, filter=name) for name in ("kcf", "centralized-ekf")}
    for variant, content in {"bom": "\ufeff" + text, "crlf": text.replace("\n", "\r\n"),
                             "bom-crlf": "\ufeff" + text.replace("\n", "\r\n")}.items():
        path = tmp_path / f"{variant}.csv"
        path.write_bytes(content.encode("utf-8"))
        schemas.validate_log(path)
        for name, a in ref.items():
            b = studies.filter("indoor-robot", path, filter=name)
            assert np.array_equal(a.x_hat, b.x_hat) and np.array_equal(a.cov, b.cov, equal_nan=True), (variant, name)


def test_boolean_channel_flags_are_read_as_0_and_1(tmp_path):
    """The channel flags may be booleans (the schema allows false and true beside 0 and 1): the same log."""
    from studies import schemas

    studies.simulate("indoor-robot", seed=1, out=tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as d:
        dos, fdi = d["channel_dos"], d["channel_fdi"]
    flags = _log(tmp_path, "flags.npz", channel_dos=dos.astype(bool), channel_fdi=fdi.astype(bool))
    schemas.validate_log(flags)
    a, b = (studies.filter("indoor-robot", p, filter="kcf") for p in (tmp_path / "good.npz", flags))
    assert np.array_equal(a.x_hat, b.x_hat) and np.array_equal(a.cov, b.cov)


GiB = 2**30


@pytest.mark.parametrize("case, needles", [
    ("zip bomb", ["the arrays of log", "30000000 steps"]),
    ("step 10^9", ["the arrays of log", "1000000000 steps", "to fit, use a shorter log (fewer steps)"]),
])
def test_a_log_beyond_memory_is_refused_before_it_is_read(case, needles, tmp_path, monkeypatch, capsys):
    """An .npz whose directory and header declare 3.84 GB for z (a zip bomb: a few kB stored), a CSV row at step
    10^9: refused with the estimate and the memory available, before an array is made."""
    monkeypatch.setattr(memory, "available_memory", lambda: 8 * GiB)
    studies.simulate("indoor-robot", seed=1, out=tmp_path / "good.npz")
    if case == "zip bomb":
        bad = _forged(tmp_path, 30_000_000, honest=False)
        assert bad.stat().st_size < 10**5
    else:
        lines = write_csv(tmp_path).read_text().splitlines()
        assert lines[2].startswith("1,0,")
        bad = tmp_path / "bad.csv"
        bad.write_text("\n".join(lines[:2] + ["1000000000" + lines[2][1:]] + lines[3:]) + "\n")
    said = _refused(bad, "would need about", "filter would need about", tmp_path / "out", capsys)
    assert "more than the 8 GiB available" in said and all(n in said for n in needles), said


def test_particles_beyond_memory_are_refused_before_filtering(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(memory, "available_memory", lambda: 8 * GiB)
    log = tmp_path / "log.npz"
    studies.simulate("indoor-robot", seed=1, out=log)
    with pytest.raises(InputError, match=r"^filter would need about .* more than the 8 GiB available: the particle "
                                         r"filter: the particles \(1 runs x 100000000000 particles x 3 states\).*"
                                         r"to fit, use fewer particles \(--particles\)$"):
        studies.filter("indoor-robot", log, filter="centralized-pf-attack-aware", particles=10**11)
    out = tmp_path / "out"
    assert main(["filter", "indoor-robot", "--data", str(log), "--filter", "centralized-pf-attack-aware",
                 "--particles", str(10**11), "--out", str(out)]) == 2
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and said[0].startswith("cfdesign: error: filter would need about") and not out.exists()
    assert studies.filter("indoor-robot", log, filter="centralized-pf-attack-aware", particles=20).x_hat.shape[0] == 31


def test_node_filter_estimates_its_design_before_computing(tank_model, monkeypatch):
    """A scheduled node filter designs its tables over the model's horizon: refused when they cannot fit; a rule
    without tables holds nothing that grows with the steps."""
    monkeypatch.setattr(memory, "available_memory", lambda: 8 * GiB)
    huge = tank_model(steps=10**10, name="huge.py")
    with pytest.raises(InputError, match=r"^node_filter would need about .*the design's offline tables.*"
                                         r"to fit, use fewer steps \(a model file's STEPS; steps = 10000000000\)"):
        studies.node_filter(str(huge), mode="scheduled")
    assert studies.node_filter(str(huge), mode="paper", node=0) is not None


def json_copy(obj):
    return json.loads(json.dumps(obj))


def write_csv(tmp_path):
    studies.simulate("indoor-robot", seed=1, out=tmp_path / "log.csv")
    return tmp_path / "log.csv"


def test_validating_a_zip_bomb_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """schemas.validate_log (the log as JSON) checks the memory from the sizes the archive's directory declares
    before it reads an array: the forged .npz that claims 3.84 GB for z is refused, not inflated."""
    from studies import schemas

    monkeypatch.setattr(memory, "available_memory", lambda: 8 * GiB)
    studies.simulate("indoor-robot", seed=1, out=tmp_path / "good.npz")
    schemas.validate_log(tmp_path / "good.npz")  # a log that fits is validated as before
    bad = _forged(tmp_path, 30_000_000, honest=False)
    with pytest.raises(InputError, match="validating a log would need about .* more than the 8 GiB available"):
        schemas.validate_log(bad)


def test_a_scheduled_design_directory_is_filtered_with_its_recorded_tables_not_designed_again(tmp_path, monkeypatch):
    """filter, node_filter and export of a scheduled design read its tables from schedule.npz: the same numbers as
    the tables designed again (the first steps of a design do not depend on its horizon), without calling the
    rule's design of tables; a log longer than the recorded horizon gets tables designed for it; a schedule.npz whose
    tables do not fit the model is refused naming the array."""
    import rules.scheduled.design as scheduled
    import studies

    from pathlib import Path

    ring = str(Path(__file__).resolve().parents[1] / "examples" / "ring_model.py")
    des = tmp_path / "d"
    studies.design(ring, mode="scheduled", steps=25, seed=1, out=des)
    log = tmp_path / "log.npz"
    studies.simulate(ring, steps=20, seed=4, out=log)
    again = studies.filter(ring, log, filter="scheduled")  # the tables designed again for the log's 20 steps
    calls = []
    real = scheduled.design_scheduled
    monkeypatch.setattr(scheduled, "design_scheduled", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    read = studies.filter(ring, log, schedule=des)
    assert not calls  # read, not designed
    np.testing.assert_array_equal(read.x_hat, again.x_hat)
    np.testing.assert_array_equal(read.cov, again.cov)
    net = studies.node_filter(ring, schedule=des)
    assert not calls and net.nodes[0].tables.steps == 25
    longer = tmp_path / "long.npz"
    studies.simulate(ring, steps=37, seed=4, out=longer)
    assert np.asarray(studies.filter(ring, longer, schedule=des).valid).all()  # a certificate over all 37 steps:
    # beyond the recorded horizon of 25 the tables were designed for the log (the recorded ones end at 25)
    with np.load(des / "schedule.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["table_Gamma"] = arrays["table_Gamma"][:, :-1]
    np.savez(des / "schedule.npz", **arrays)
    with pytest.raises(InputError, match="table_Gamma has shape"):
        studies.filter(ring, log, schedule=des)


def test_recorded_tables_of_another_kind_are_refused_naming_the_array(tmp_path):
    """A schedule.npz whose certificate arrays are text, or whose tables are for other channel probabilities, is
    refused before any filtering (InputError naming what), never a traceback."""
    from pathlib import Path

    ring = str(Path(__file__).resolve().parents[1] / "examples" / "ring_model.py")
    des = tmp_path / "d"
    studies.design(ring, mode="scheduled", steps=12, seed=1, out=des)
    log = tmp_path / "log.npz"
    studies.simulate(ring, steps=10, seed=4, out=log)
    with np.load(des / "schedule.npz") as z:
        good = {k: z[k] for k in z.files}
    np.savez(des / "schedule.npz", **{**good, "sigma": np.full(good["sigma"].shape, "x")})
    with pytest.raises(InputError, match="must be numbers"):
        studies.filter(ring, log, schedule=des)
    np.savez(des / "schedule.npz", **{**good, "table_p": good["table_p"] * 0.5})
    with pytest.raises(InputError, match="other channel probabilities"):
        studies.filter(ring, log, schedule=des)


def test_a_logs_channel_signal_is_written_and_read_step_by_step(tmp_path):
    """A log's channel_xi (dense N x N x n_x a step, nearly all zeros) is written from the falsified entries and read
    back to them one step at a time: the file holds the dense array (np.load reads it, equal to the pattern's), the
    read log holds the same signals, and neither writing nor reading ever holds the dense array (tracemalloc's peak
    below half of it, on a model of 40 states where it is most of the log); a value that is not finite is refused
    naming its index, as before."""
    import tracemalloc

    from studies.recorded import read_log
    from studies.scenarios import load_scenario

    model = tmp_path / "wide.py"
    model.write_text(WIDE_MODEL)
    sim = studies.simulate(str(model), steps=400, seed=3)
    dense = sim.attacks.xi
    assert sim.attacks.fdi.sum() > 1000 and dense.nbytes > 4e6
    path = tmp_path / "log.npz"
    sc = load_scenario(str(model))
    tracemalloc.start()
    try:
        sim.save(path)
        write_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        log = read_log(path, sc)
        read_peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    with np.load(path) as f:
        np.testing.assert_array_equal(f["channel_xi"], dense)
    np.testing.assert_array_equal(log.attacks.fdi, sim.attacks.fdi)
    np.testing.assert_array_equal(log.attacks.xi_fdi, sim.attacks.xi_fdi)
    # reading held the dense signal twice (as stored and as floats), writing once: now neither
    assert write_peak < dense.nbytes / 2 and read_peak < dense.nbytes / 2, (write_peak, read_peak, dense.nbytes)

    bad = dense.copy()
    k, i, j = (int(v) for v in np.argwhere(sim.attacks.fdi)[5])
    bad[k, i, j, 1] = np.nan
    with np.load(path) as f:
        arrays = {key: f[key] for key in f.files}
    arrays["channel_xi"] = bad
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=rf"array 'channel_xi' holds nan at index \[{k}, {i}, {j}, 1\]"):
        read_log(tmp_path / "bad.npz", sc)


#: 40 states watched by a ring of 6 nodes, each measuring 3 of them, every channel attacked: a log whose dense channel
#: signal (N x N x 40 a step) is most of it
WIDE_MODEL = """
import casadi as ca
import numpy as np
from designer import AttackSpec, FDISignal, Gaussian, Model, SensorNetwork, Sensor
STEPS = 400
NETWORK = SensorNetwork.from_edges(6, [(i, (i + 1) % 6) for i in range(6)])
ATTACKS = AttackSpec(dos=0.2, fdi=0.4, signal=FDISignal(amplitude=0.5))
def model() -> Model:
    x = ca.SX.sym("x", 40)
    sensors = [Sensor(f"s{i}", ca.vertcat(x[3 * i], x[3 * i + 1], x[3 * i + 2]), Gaussian.zero_mean(0.1 * np.eye(3)))
               for i in range(6)]
    return Model("wide", x, 0.98 * x, sensors, process_noise=Gaussian.zero_mean(1e-2 * np.eye(40)),
                 prior=Gaussian(np.zeros(40), np.eye(40)))
"""
