"""Study ``encrypted-switching`` (seed 001): the paper's claim at a reduced size, files, reproducibility, inputs.

The size is reduced from 50 runs to 16 (T = 120 and M = 200 as in the paper); the three
filters filter the same data with the same random numbers, so the comparison is paired.
"""
from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

from designer import InputError
from studies.encrypted_switching import FILTERS, MEAN_DYNAMICS
from studies.pipeline import run_study


def encrypted(**kw):
    """The study through the pipeline (quiet, as every call here)."""
    return run_study("encrypted-switching", **kw)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("encrypted")
    return out, encrypted(out=out, runs=16, particles=200, seed=0)


@pytest.mark.slow
def test_ppf_beats_both_baselines_on_both_states(study):
    """The paper's claim (Figs. 5-6): PPF has the lowest RMSE_1 and RMSE_2."""
    _, res = study
    f = res["filters"]
    ppf = f["PPF"]["rmse_state"]
    for base in ("PF-RSN", "PF-SR-DE"):
        assert all(a < b for a, b in zip(ppf, f[base]["rmse_state"])), base
    assert res["claim_check"]["holds"]
    # ignoring the switching (gamma = 1) biases the prediction: the filter loses the state
    assert all(b > 3 * a for a, b in zip(ppf, f["PF-RSN"]["rmse_state"]))
    # ignoring resolution and decryption errors excludes the true state at times: collapses
    assert f["PF-SR-DE"]["collapsed_steps"] > f["PPF"]["collapsed_steps"] == 0
    # "able to well track": the median run's error is a fraction of the state's spread (prior std 1.2)
    assert all(v < 0.5 for v in f["PPF"]["rmse_state_median_run"])


@pytest.mark.slow
def test_results_table_and_figures(study):
    out, res = study
    on_disk = json.loads((out / "results.json").read_text())
    for key in ("schema", "study", "scenario", "runs", "particles", "steps", "seed", "assumptions", "wall_time_s",
                "versions", "filters", "paper", "claim_check", "transmission", "timing_s"):
        assert key in on_disk
    assert on_disk["schema"] == "cfdesign.study/1" and on_disk["steps"] == 120 and on_disk["scenario"] == "switching-2d"
    assert on_disk["paper"]["numbers"] is None and "superior" in on_disk["paper"]["claim"]
    assert set(on_disk["filters"]) == {*FILTERS, MEAN_DYNAMICS}
    for f in on_disk["filters"].values():
        assert len(f["rmse_state"]) == 2 and all(len(c) == 120 for c in f["rmse_state_curve"])
        for v, (lo, hi), curve in zip(f["rmse_state"], f["rmse_state_ci95"], f["rmse_state_curve"]):
            assert lo <= v <= hi and v == pytest.approx(np.mean(curve))
        tb = f["time_breakdown_s"]  # the fast engine (default) fuses proposal, likelihood and engine
        assert f["engine"] == "fast" and set(tb) == {"proposal", "likelihood", "engine"}
        assert all(v is None for v in tb.values()) and f["wall_time_s"] > 0
        assert "rmse_position" not in f
    tx = on_disk["transmission"]
    assert tx["available_fraction"] == 1.0 and tx["bits_per_packet"] == 3 and tx["crc_bits"] == 4
    assert all(e < b for e, b in zip(tx["max_abs_z_minus_decrypted"], tx["bound_L_bar"]))  # (12)
    assert any("ESS < M/2" in a for a in on_disk["assumptions"])
    assert any("gamma = 1" in a for a in on_disk["assumptions"])
    table = (out / "table.md").read_text()
    assert all(name in table for name in FILTERS) and "Claim holds" in table
    for fig in ("fig_state1", "fig_state2", "fig_measurements_s1", "fig_measurements_s2", "fig_rmse_1", "fig_rmse_2"):
        assert (out / f"{fig}.png").stat().st_size > 10_000


def _small(**kw):
    return encrypted(out=None, runs=3, particles=40, mean_dynamics_row=False,
                                   assignments=("steps=15",), **kw)


def test_a_seed_reproduces_the_study():
    a, b, c = _small(seed=5), _small(seed=5), _small(seed=6)
    for name in FILTERS:
        assert a["filters"][name]["rmse_state_curve"] == b["filters"][name]["rmse_state_curve"]
        assert a["filters"][name]["rmse_state_ci95"] == b["filters"][name]["rmse_state_ci95"]
    assert a["filters"]["PPF"]["rmse_state"] != c["filters"]["PPF"]["rmse_state"]


def test_numpy_engine_reports_where_the_time_goes():
    res = _small(seed=2, engine="numpy")
    for f in res["filters"].values():
        tb = f["time_breakdown_s"]
        assert f["engine"] == "numpy" and tb["proposal"] > 0 and tb["likelihood"] > 0 and tb["engine"] > 0
        assert sum(tb.values()) == pytest.approx(f["wall_time_s"])


def test_transmission_errors_make_measurements_unavailable():
    res = _small(seed=1, overrides={"bit_error_prob": 0.05, "dropout_prob": 0.2})
    tx = res["transmission"]
    assert 0.5 < tx["available_fraction"] < 0.75  # (1 - 0.2) (0.95^7 + misses) = 0.56
    assert tx["dropped"] > 0 and tx["crc_detected"] > 0
    assert all(np.isfinite(f["rmse_state"]).all() for f in res["filters"].values())


@pytest.mark.parametrize("kw, name", [
    ({"engine": "gpu"}, "engine"),
    ({"engine": "numpy", "threads": 2}, "threads"),
    ({"threads": 0}, "threads"),
    ({"workers": 2}, "workers"),
    ({"runs": 1}, "runs"),
    ({"particles": 0}, "particles"),
    ({"seed": -1}, "seed"),
    ({"overrides": {"bit_error_prob": 1.5}}, "bit_error_prob"),
    ({"assignments": ("quant_levels=6",)}, "quant_levels"),
    ({"assignments": ("nonsense=1",)}, "nonsense"),
])
def test_bad_inputs_name_the_parameter(kw, name):
    with pytest.raises(InputError, match=name):
        encrypted(out=None, **kw)


def _same_numbers(a: dict, b: dict) -> bool:
    """results.json numbers, without timings, the runner's description and the thread count."""
    import json

    def strip(r):
        r = json.loads(json.dumps(r.results))
        for key in ("wall_time_s", "runner", "versions", "timing_s", "threads"):  # how it ran, not what
            r.pop(key, None)
        for f in r["filters"].values():
            for key in ("time_per_step_s", "wall_time_s", "time_breakdown_s"):
                f.pop(key, None)
        return r

    return strip(a) == strip(b)


@pytest.mark.slow
def test_runner_backends_give_the_same_numbers_and_resume(tmp_path):
    distributed = pytest.importorskip("distributed")
    from studies.runner import Backend, make_backend

    kw = dict(runs=4, particles=30, seed=3, chunk_size=2, mean_dynamics_row=False)
    a = encrypted(out=tmp_path / "a", **kw)
    b = encrypted(out=tmp_path / "b", backend=Backend("processes", workers=2), **kw)
    assert _same_numbers(a, b) and b["runner"]["chunks_computed"] == 2
    again = encrypted(out=tmp_path / "a", **kw)
    assert again["runner"]["chunks_reused"] == 2 and _same_numbers(a, again)
    with pytest.raises(InputError, match="--force"):
        encrypted(out=tmp_path / "a", **{**kw, "particles": 40})
    n = dict(kw, engine="numpy")
    c = encrypted(out=None, **n)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        d = encrypted(out=None, backend=make_backend(dask=cl.scheduler_address), **n)
    assert _same_numbers(c, d)


USER_MODEL = """
    \"\"\"A user's scalar system switching between two dynamics, one encrypted sensor that drops packets.\"\"\"
    import casadi as ca

    from designer import Gaussian, Model, Sensor, TruncatedGaussian
    from filters.encryption import Codec, EncryptedChannel

    STEPS = 10


    def model():
        x, r = ca.SX.sym("x", 1), ca.SX.sym("mode")
        f = 0.9 * x + r * 0.2 * ca.sin(x) + (1 - r) * 0.1 * ca.cos(x)
        noise = TruncatedGaussian([0.0], [1.0], [-2.0], [2.0])
        return Model("user-switching", x, f, [Sensor("s", 2.0 * ca.sin(x), noise)], Gaussian.zero_mean([[0.01]]),
                     Gaussian([0.5], [[0.25]]), mode=r, mode_probs=[0.5, 0.5])


    CHANNEL = EncryptedChannel(Codec(resolution=0.1, quant_scale=1.0, quant_levels=8, quant_range=4.0),
                               dropout_prob=0.3)
"""


@pytest.mark.slow
def test_a_user_model_file_with_an_encrypted_channel_runs_the_study(tmp_path):
    path = tmp_path / "user_switching.py"
    path.write_text(textwrap.dedent(USER_MODEL))
    res = run_study("encrypted-switching", [str(path)], runs=3, particles=30, out=tmp_path / "o")
    r = res.results
    assert r["scenario"] == "user-switching" and r["steps"] == 10 and "paper" not in r  # the paper's claim: its own
    assert set(r["filters"]) == {*FILTERS, MEAN_DYNAMICS}
    tx = r["transmission"]  # the model's channel was used: its codec's bound and its dropouts
    assert tx["bound_L_bar"] == [pytest.approx(1.0 * 4.0 / 8 + 0.1)] and tx["dropped"] > 0
    A = res.arrays["user-switching"]
    assert tx["available_fraction"] == A["available"].mean() < 1.0
    for j, f in enumerate(r["filters"].values()):  # RMSE_1(t) recomputed from the per-run estimates
        e2 = (A["truth"][:, 1:, 0] - A["mean"][:, j, 1:, 0]) ** 2
        np.testing.assert_allclose(f["rmse_state_curve"][0], np.sqrt(e2.mean(axis=0)), rtol=1e-12)
    assert (tmp_path / "o" / "table.md").read_text().startswith("# encrypted-switching on user-switching")
    assert (tmp_path / "o" / "fig_rmse_1.png").stat().st_size > 10_000
