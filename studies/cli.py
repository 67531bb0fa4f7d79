"""The ``cfdesign`` command line (a thin layer over :mod:`studies.api`).

Errors: one line on stderr; exit 2 for bad input, 1 for a failed or infeasible
computation; a traceback only with ``--debug``.
"""
from __future__ import annotations

import json
import sys
import traceback

import click

from designer.validation import ComputationError, InputError

from . import api

_SET_HELP = "override a scenario parameter (repeatable); see 'cfdesign scenarios'"


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--debug", is_flag=True, help="show tracebacks on errors")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """cfdesign: design and compare attack-resilient consensus and particle filters."""
    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug


@cli.command("scenarios")
@click.option("--json", "as_json", is_flag=True, help="machine-readable output with every parameter")
def scenarios_cmd(as_json: bool) -> None:
    """List the built-in scenarios."""
    info = api.list_scenarios()
    if as_json:
        click.echo(json.dumps(info, indent=2))
        return
    for s in info:
        click.echo(f"{s['name']:22s} seed {s['paper']}  n_x={s['n_x']}  sensors={s['sensors']:2d}  "
                   f"steps={s['steps']:3d}  {s['title']}")
        for p in s["parameters"]:
            tag = " [assumption]" if p["source"] == "assumption" else ""
            click.echo(f"    {p['name']} = {json.dumps(p['default'])}{tag}  ({p['doc']})")


@cli.command("simulate")
@click.argument("scenario")
@click.option("--steps", type=int, default=None, help="number of time steps (default: the scenario's)")
@click.option("--seed", type=int, default=0, show_default=True, help="random seed")
@click.option("--out", required=True, help="output .npz file")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def simulate_cmd(scenario: str, steps: int | None, seed: int, out: str, assignments) -> None:
    """Simulate SCENARIO (a built-in name or a MODEL.py file) and write true states and measurements."""
    traj = api.simulate_scenario(scenario, steps=steps, seed=seed, out=out, assignments=assignments)
    click.echo(f"wrote {out}: x {traj.x.shape}, z {traj.z.shape}")


@cli.command("design")
@click.argument("scenario")
@click.option("--mode", type=click.Choice(["paper", "tuned"]), default="paper", show_default=True,
              help="paper: the published choices (sigma = beta = 0.1, C = tau Phi); tuned: convex tuning")
@click.option("--steps", type=int, default=None, help="time steps (default: the scenario's)")
@click.option("--seed", type=int, default=0, show_default=True, help="seed of the simulated run")
@click.option("--out", required=True, help="output directory (schedule.json, schedule.npz)")
@click.option("--epsilon", type=float, default=None, help="epsilon in (0, 1/d_max) (default 0.5/d_max)")
@click.option("--sigma", type=float, default=None, help="sigma of (26) (default 0.1)")
@click.option("--beta", type=float, default=None, help="beta of (27) (default 0.1)")
@click.option("--tau", type=float, default=None, help="consensus gain C = tau Phi_pred (default 0.01)")
@click.option("--dos", type=float, default=None, help="DoS probability on every channel, in [0, 1)")
@click.option("--fdi", type=float, default=None, help="FDI probability on every channel, in [0, 1)")
@click.option("--delta", type=float, default=None, help="bound on the injected signal (default: the scenario's)")
@click.option("--u-scale", type=float, default=None, help="U = u I, linearisation scaling of f (default 0.01)")
@click.option("--v-scale", type=float, default=None, help="V = v I, linearisation scaling of h (default 0.1)")
@click.option("--linearization", type=click.Choice(["fixed", "hessian", "structured"]), default="fixed", show_default=True,
              help="fixed: U = u I, V = v I as given; hessian: U, V from the model's Hessians per node and step; "
                   "structured: the same with the remainder restricted to the variables the model is nonlinear in")
@click.option("--radius", type=float, default=3.0, show_default=True,
              help="hessian: the remainder bound covers errors within this many standard deviations of Phi")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def design_cmd(scenario, mode, steps, seed, out, epsilon, sigma, beta, tau, dos, fdi, delta, u_scale, v_scale,
               linearization, radius, assignments) -> None:
    """Design the consensus filter of SCENARIO and write its gain schedule to OUT."""
    from .design import design

    res = design(scenario, out=out, mode=mode, steps=steps, seed=seed, epsilon=epsilon, sigma=sigma, beta=beta,
                 tau=tau, dos=dos, fdi=fdi, delta=delta, u_scale=u_scale, v_scale=v_scale,
                 linearization=linearization, radius=radius, assignments=assignments)
    sch = res.schedule
    click.echo(f"wrote {out}/schedule.json and schedule.npz: {sch.nodes} nodes, {sch.steps} steps, "
               f"epsilon {sch.epsilon:.4g}, feasible {str(sch.feasible).lower()}")
    hard = [v for v in sch.violations if v["condition"] in ("(28)", "(29)", "diverged")]
    for v in hard:
        click.echo(f"  violation: node {v['node']} step {v['step']} condition {v['condition']} "
                   + (v["reason"] if "reason" in v else f"margin {v['margin']:.4g}"))
    n_th2 = len(sch.violations) - len(hard)
    if n_th2:
        click.echo(f"  Theorem 2 (mean-square boundedness) not certified at {n_th2} (node, step) pairs")
    if hard:
        first = min(hard, key=lambda v: (v["step"], v["node"]))
        raise ComputationError(
            f"infeasible design: {len(hard)} violations of (28)-(29) or divergence; first at node {first['node']}, "
            f"step {first['step']}, condition {first['condition']}, "
            + (first["reason"] if "reason" in first else f"margin {first['margin']:.4g}")
            + " (schedule written, marked feasible: false)")


@cli.command("feasibility")
@click.argument("scenario")
@click.option("--grid", "grids", multiple=True, required=True, metavar="NAME=START:STOP:COUNT",
              help="grid over dos, fdi, delta or tau (repeatable)")
@click.option("--out", required=True, help="output directory (feasibility.csv, feasibility.png)")
@click.option("--mode", type=click.Choice(["paper", "tuned"]), default="tuned", show_default=True)
@click.option("--workers", type=int, default=None, help="local worker processes [default: this process]")
@click.option("--dask", "dask", default=None, metavar="ADDRESS",
              help="compute the chunks of grid points on the Dask scheduler at ADDRESS")
@click.option("--force", is_flag=True, help="recompute grid points already stored in OUT")
@click.option("--quiet", is_flag=True, help="no progress bar")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def feasibility_cmd(scenario, grids, out, mode, workers, dask, force, quiet, assignments) -> None:
    """Map where the consensus design of SCENARIO admits a bounded steady-state bound."""
    from .feasibility import feasibility_map

    rows = feasibility_map(scenario, grids, out=out, mode=mode, workers=workers, dask=dask, force=force,
                           quiet=quiet, assignments=assignments)
    n_ok = sum(r["feasible"] for r in rows)
    click.echo(f"wrote {out}/feasibility.csv: {n_ok} of {len(rows)} grid points feasible")


STUDIES = {"consensus-robot": None, "rrp-deception": None, "binary-multi-attack": None, "encrypted-switching": None,
           "fdi-four-tank": None, "comparison": None}
_PF_STUDIES = ("rrp-deception", "binary-multi-attack", "encrypted-switching", "fdi-four-tank")


def _reject(study: str, **given) -> None:
    """Options that the study does not use are an error, not silently ignored."""
    for name, value in given.items():
        if value is not None and value is not False and value != ():
            raise InputError(f"option --{name.replace('_', '-')} does not apply to study {study!r}")


@cli.command("study")
@click.argument("study")
@click.option("--out", required=True, help="output directory (results.json, table.md, figures)")
@click.option("--runs", type=int, default=None,
              help="Monte Carlo runs [default: the paper's: 500 consensus-robot, 50 otherwise]")
@click.option("--particles", type=int, default=None,
              help="particles M of the particle filters [default: the paper's: 500, 200 encrypted-switching, "
                   "100 fdi-four-tank]")
@click.option("--seed", type=int, default=0, show_default=True, help="random seed")
@click.option("--workers", type=int, default=None,
              help="local worker processes that compute the chunks of runs (the numbers do not depend on it) "
                   "[default: this process]")
@click.option("--dask", "dask", default=None, metavar="ADDRESS",
              help="compute the chunks of runs on the Dask scheduler at ADDRESS (e.g. tcp://host:8786)")
@click.option("--force", is_flag=True,
              help="recompute runs already stored in OUT (otherwise an interrupted study resumes from them)")
@click.option("--scenario", "scenarios", multiple=True,
              help="comparison: a scenario to compare on (repeatable) [default: indoor-robot and "
                   "target-range-bearing]")
@click.option("--engine", type=click.Choice(["fast", "numpy"]), default=None,
              help="particle-filter engine: fused numba kernels or the NumPy reference [default: fast where the "
                   "study has it, else numpy]")
@click.option("--mode", type=click.Choice(["paper", "tuned"]), default=None,
              help="consensus-robot: design mode [default: paper]")
@click.option("--quiet", is_flag=True, help="no progress bar")
@click.option("--schedule", default=None, help="replay the gains of this design directory (consensus-robot)")
@click.option("--linearization", type=click.Choice(["fixed", "hessian", "structured"]), default=None,
              help="consensus-robot: U, V of the consensus designs, fixed (0.01 I, 0.1 I) or from the model's "
                   "Hessians [default: fixed]")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def study_cmd(study, out, runs, particles, seed, workers, dask, force, scenarios, engine, mode, quiet, schedule,
              linearization, assignments) -> None:
    """Run the Monte Carlo study STUDY and write its results and figures to OUT."""
    if study not in STUDIES:
        raise InputError(f"unknown study {study!r}; studies: {', '.join(STUDIES)}")
    if STUDIES[study] is not None:
        built = ", ".join(k for k, v in STUDIES.items() if v is None)
        raise InputError(f"study {study!r} is not built yet (issue {STUDIES[study]}); available: {built}")
    if study == "comparison":
        _reject(study, engine=engine, mode=mode, schedule=schedule, linearization=linearization)
        _comparison(out, runs, particles, seed, workers, dask, force, scenarios, quiet, assignments)
        return
    _reject(study, scenario=scenarios)
    from .runner import make_backend

    backend = make_backend(workers, dask)
    if study in _PF_STUDIES:
        _reject(study, mode=mode, schedule=schedule, linearization=linearization)
        _pf_study(study, out, runs, particles, seed, backend, force, engine, quiet, assignments)
        return
    _reject(study, particles=particles, engine=engine)
    from .consensus_robot import run_consensus_robot

    res = run_consensus_robot(out=out, runs=500 if runs is None else runs, seed=seed, mode=mode or "paper",
                              quiet=quiet, assignments=assignments, schedule=schedule,
                              design_options={"linearization": linearization or "fixed"}, backend=backend,
                              force=force)
    click.echo(f"wrote {out}/results.json ({res['runs']} runs, {res['wall_time_s']:.1f} s)")
    for name, f in res["filters"].items():
        if f["rmse_position"] is None:
            click.echo(f"  {name}: every run diverged ({len(f['diverged_runs'])})")
            continue
        bc = f["bound_check"]
        if bc is None:
            click.echo(f"  {name}: RMSE_p {f['rmse_position']:.4g} m (median run {f['rmse_position_median_run']:.4g})")
            continue
        frac = "n/a" if bc["fraction_exceeding"] is None else f"{bc['fraction_exceeding']:.3f}"
        click.echo(f"  {name}: RMSE_p {f['rmse_position']:.4g} m (median run {f['rmse_position_median_run']:.4g}), "
                   f"diverged {len(f['diverged_runs'])}, spread {f['node_spread']:.4f} m, "
                   f"feasible runs {f['feasibility']['runs_feasible']}/{f['feasibility']['runs']}, "
                   f"bound checked at {bc['pairs_checked']}/{bc['pairs_total']} (node, step) pairs, "
                   f"exceeded at {frac}")


def _comparison(out, runs, particles, seed, workers, dask, force, scenarios, quiet, assignments) -> None:
    from .comparison import run_comparison
    from .runner import make_backend

    kw = {k: v for k, v in {"runs": runs, "particles": particles, "scenarios": scenarios or None}.items()
          if v is not None}
    res = run_comparison(out=out, seed=seed, quiet=quiet, assignments=assignments, force=force,
                         backend=make_backend(workers, dask), **kw)
    done = sum(r["chunks_computed"] for r in res["runner"].values())
    reused = sum(r["chunks_reused"] for r in res["runner"].values())
    click.echo(f"wrote {out}/results.json, table.md, report.html and figures (M = {res['particles']}, "
               f"{res['wall_time_s']:.1f} s; {done} chunks computed, {reused} reused)")
    for name, f in res["filters"].items():
        acc = "every run diverged" if f["rmse_position"] is None else f"RMSE_p {f['rmse_position']:.4g} m"
        click.echo(f"  {name}: {acc}, {f['time_per_step_s'] * 1e3:.3g} ms/step, "
                   f"{f['messages_per_step']} messages/step")


def _pf_study(study, out, runs, particles, seed, backend, force, engine, quiet, assignments) -> None:
    given = {"runs": runs, "particles": particles, "engine": engine}
    kw = dict(out=out, seed=seed, quiet=quiet, assignments=assignments, backend=backend, force=force,
              **{k: v for k, v in given.items() if v is not None})  # unset: the study's own default
    if study == "rrp-deception":
        from .rrp_deception import run_rrp_deception as run
    elif study == "binary-multi-attack":
        from .binary_multi_attack import run_binary_multi_attack as run
    elif study == "encrypted-switching":
        from .encrypted_switching import run_encrypted_switching as run
    else:
        from .fdi_four_tank import run_fdi_four_tank as run
    res = run(**kw)
    click.echo(f"wrote {out}/results.json, table.md and figures ({res['runs']} runs, M = {res['particles']}, "
               f"{res['wall_time_s']:.1f} s)")
    for name, f in res["filters"].items():
        if "rmse_position" in f:
            acc = f"RMSE_p {f['rmse_position']:.4g}, RMSE_v {f['rmse_velocity']:.4g}"
        elif "rmse_truth" in f:
            acc = f"RMSE {f['rmse']:.4g} against the no-attack PF, {f['rmse_truth']:.4g} against the truth"
        else:
            acc = "RMSE per state " + ", ".join(f"{v:.4g}" for v in f["rmse_state"])
        comm = f", {f['communications']} communications" if "communications" in f else ""
        click.echo(f"  {name}: {acc}, {f['time_per_step_s'] * 1e3:.3g} ms/step{comm}")


@cli.command("report")
@click.argument("directory")
def report_cmd(directory: str) -> None:
    """Write DIRECTORY/report.html (self-contained) and report.md from a study's results.json and figures."""
    html, md = api.report(directory)
    click.echo(f"wrote {html} and {md}")


def main(argv=None) -> int:
    """Entry point of the console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    try:
        cli.main(args=argv, prog_name="cfdesign", standalone_mode=False)
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        click.echo(f"cfdesign: error: {exc.format_message()}", err=True)
        return 2
    except click.exceptions.Abort:
        click.echo("cfdesign: interrupted", err=True)
        return 130
    except InputError as exc:
        if debug:
            traceback.print_exc()
        click.echo(f"cfdesign: error: {exc}", err=True)
        return 2
    except ComputationError as exc:
        if debug:
            traceback.print_exc()
        click.echo(f"cfdesign: failed: {exc}", err=True)
        return 1
    except Exception as exc:  # noqa: BLE001 - the CLI contract is one line, no traceback
        if debug:
            traceback.print_exc()
        msg = str(exc).splitlines()[0] if str(exc) else ""
        click.echo(f"cfdesign: internal error: {type(exc).__name__}: {msg} (rerun with --debug)", err=True)
        return 1
    return 0


def run() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run()
