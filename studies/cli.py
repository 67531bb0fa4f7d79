"""The ``cfdesign`` command line: a thin layer over :mod:`studies.api`.

Every command calls one public function and prints what it returns, so a design
script and the command line give the same numbers.  Errors: one line on stderr; exit
2 for bad input, 1 for a failed or infeasible computation; a traceback only with
``--debug``.
"""
from __future__ import annotations

import errno
import functools
import json
import sys
import traceback
import warnings

import click

import rules
from designer.rule import CARRIES, EXCHANGES, ROBUSTNESS, TABLE_KINDS
from designer.validation import CfdesignWarning, ComputationError, InputError

_SET_HELP = ("override a scenario parameter, or for 'study' one of the study's own options such as "
             "hcmci_iterations=3 (repeatable); see 'cfdesign scenarios'")


_DEBUG_HELP = "show tracebacks on errors (accepted anywhere on the line)"


def _debug(ctx: click.Context, param, value: bool) -> None:
    """``--debug`` given to the group or to a command: tracebacks on errors (read by :func:`main`)."""
    if value:
        ctx.ensure_object(dict)["debug"] = True


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """cfdesign: design and compare attack-resilient consensus and particle filters."""


def _design_options(f, *, auto: bool = False):
    """The design options every design command shares (``design``, ``feasibility``, ``study``); ``auto``: the
    command's default mode is the automatic design (``design``)."""
    rule_help = "; ".join(r.help for r in rules.all_rules().values())
    opts = [
        click.option("--mode", type=click.Choice((["auto"] if auto else []) + list(rules.names())), default=None,
                     help=("auto: every deployable rule's candidate designs, and the certified one inside --budget "
                           "with the smallest predicted error (feasibility: at each grid point, the smallest "
                           "stationary bound); " + rule_help + " [default: auto]") if auto else
                     rule_help + f" [default: {rules.DEFAULT}]"),
        click.option("--epsilon", type=float, default=None, help="epsilon in (0, 1/d_max) [default: 0.5/d_max]"),
        click.option("--sigma", type=float, default=None, help="sigma of (26), paper mode [default: 0.1]"),
        click.option("--beta", type=float, default=None, help="beta of (27), paper mode [default: 0.1]"),
        click.option("--tau", type=float, default=None, help="consensus gain C = tau Phi_pred, paper mode "
                                                             "[default: 0.01]"),
        click.option("--dos", type=float, default=None, help="DoS probability on every channel and uplink, [0, 1)"),
        click.option("--fdi", type=float, default=None, help="FDI probability on every channel and uplink, [0, 1)"),
        click.option("--delta", type=float, default=None,
                     help="bound on the injected signal (the simulated signal is scaled to it) [default: the "
                          "model's]"),
        click.option("--amplitude", type=float, default=None,
                     help="amplitude of the injected signal per attacked component (its bound follows)"),
        click.option("--u-scale", "u_scale", default=None, metavar="SCALE",
                     help="U: a number (u I), a comma list (diagonal), a JSON matrix, or 'prior' (from the "
                          "Hessians) [default: the model's, else prior]"),
        click.option("--v-scale", "v_scale", multiple=True, metavar="[SENSOR=]SCALE",
                     help="V_i, as --u-scale, for every sensor or for one sensor by name (repeatable) "
                          "[default: the model's, else prior]"),
        click.option("--linearization", type=click.Choice(["fixed", "hessian", "structured"]), default=None,
                     help="fixed: U, V as given; hessian: u I, v I from the model's Hessians per node and step; "
                          "structured: the same restricted to the variables the model is nonlinear in "
                          "[default: fixed]"),
        click.option("--radius", type=float, default=None,
                     help="hessian/prior scalings cover errors within this many standard deviations [default: 3]"),
        click.option("--exchange", type=click.Choice(list(EXCHANGES)), default=None,
                     help="what a packet carries, mode scheduled: the sender's prediction and its measurement "
                          "(as KCF and HCMCI exchange measurement information) or its prediction alone, as in "
                          "(7) [default: measurements]"),
        click.option("--robustness", type=float, default=None,
                     help="mode scheduled: the margin δ of the link gains, [0, 100]: each neighbour's difference is "
                          "taken to carry an extra independent error δ P_ii (0: the tables' MMSE gains, fragile "
                          f"where the state leaves the nominal geometry) [default: {ROBUSTNESS:g}]"),
        click.option("--rounds", type=int, default=None,
                     help="exchange rounds per step, [1, 64], one packet per channel and round; mode scheduled: "
                          "the first carries the predictions and measurements, the others the current estimates "
                          "(with more than one no certificate) [default: 1]; modes relay and flood: the hops over "
                          "which every measurement is relayed [default: the network's diameter, at most 8]"),
        click.option("--bank", type=int, default=None,
                     help="mode scheduled: axes A of a bank of operating points, [0, 3]: stationary tables also at "
                          "3^A - 1 points off the nominal trajectory (along the open-loop covariance's A principal "
                          "axes), each node using those nearest its own prediction, for a state that may leave the "
                          "nominal geometry; not covered by the certificate [default: 0, none]"),
        click.option("--table-kind", type=click.Choice(list(TABLE_KINDS)), default=None,
                     help="mode scheduled: 'per-step', each step's own tables; 'stationary', the tables of the "
                          "expected recursion's fixed point at the operating point at every step (one set per node: "
                          "a C export of one step's size; slower to settle from the prior) [default: per-step while "
                          "the per-step tables hold at most rules.scheduled.design.TABLES_PER_STEP_MAX numbers; "
                          "beyond, where the nominal keeps the operating point's linearisation, the first steps' "
                          "own as far as they fit, then stationary]"),
        click.option("--carry", type=click.Choice(list(CARRIES)), default=None,
                     help="modes relay and flood on a model with REGIONS: 'region', each node carries only the "
                          "states its region, its ball's measurements and their dynamics need (the same numbers "
                          "on them; bound and verdict on its region); 'whole', the whole state [default: region on "
                          "a model with REGIONS, else whole]"),
        click.option("--gate", type=float, default=None,
                     help="chi-square gate on neighbour packets: its false-rejection probability for a clean "
                          "packet, [0, 1) (0: no gate; with a gate the bound is validated by Monte Carlo only) "
                          "[default: 0]"),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _quiet(ctx, param, value):
    if value:
        from designer.progress import hush

        hush()
    return value


def _runner_options(f):
    opts = [
        click.option("--workers", type=int, default=None,
                     help="local worker processes that compute the chunks (the numbers do not depend on it) "
                          "[default: this process; study comparison and feasibility: one per usable core]"),
        click.option("--dask", "dask", default=None, metavar="ADDRESS",
                     help="compute the chunks on the Dask scheduler at ADDRESS (e.g. tcp://host:8786); the "
                          "scheduler and its workers must be trusted"),
        click.option("--dask-security", "dask_security", default=None, metavar="FILE",
                     help="JSON file of TLS options for the Dask scheduler: tls_ca_file, tls_client_cert, "
                          "tls_client_key, require_encryption (address tls://host:port)"),
        click.option("--force", is_flag=True, help="recompute what is stored in OUT (otherwise an interrupted run "
                                                    "resumes from it)"),
        click.option("--quiet", is_flag=True, callback=_quiet, expose_value=True,
                     help="no progress bar or progress lines"),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _scale_options(u_scale, v_scale) -> dict:
    from designer.design import parse_scale

    out = {"u_scale": None if u_scale is None else parse_scale("u-scale", u_scale), "v_scale": None}
    named, plain = {}, []
    for item in v_scale or ():
        name, _, text = item.rpartition("=") if "=" in item else ("", "", item)
        if name:
            named[name.strip()] = parse_scale("v-scale", text)
        else:
            plain.append(parse_scale("v-scale", text))
    if len(plain) > 1:
        raise InputError("--v-scale without a sensor name may be given once (it applies to every sensor)")
    if named:
        out["v_scale"] = {**({"*": plain[0]} if plain else {}), **named}
    elif plain:
        out["v_scale"] = plain[0]
    return out


def _options(kw: dict) -> dict:
    """The design keyword options of the API from the CLI values."""
    kw = dict(kw)
    kw.update(_scale_options(kw.pop("u_scale", None), kw.pop("v_scale", ())))
    return kw


@cli.command("scenarios")
@click.option("--json", "as_json", is_flag=True, help="machine-readable output with every parameter")
def scenarios_cmd(as_json: bool) -> None:
    """List the built-in scenarios."""
    from .api import list_scenarios  # here, not at the top: the model layer loads only for a command that runs

    info = list_scenarios()
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
@click.option("--run", type=int, default=None,
              help="simulate run RUN of a study with seed SEED instead (truth, measurements and attacks as study "
                   "comparison --seed SEED draws it), >= 0")
@click.option("--out", required=True, help="output .npz file, or .csv for the CSV form (a log for cfdesign filter)")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def simulate_cmd(scenario: str, steps: int | None, seed: int, run: int | None, out: str, assignments) -> None:
    """Simulate SCENARIO (a built-in name or a MODEL.py file) and write true states, measurements and, on a sensor
    network, the channels' and uplinks' attacks."""
    from .api import simulate

    sim = simulate(scenario, steps=steps, seed=seed, run=run, out=out, assignments=assignments)
    click.echo(f"wrote {out}: x {sim.x.shape}, z {sim.z.shape}"
               + ("" if sim.attacks is None else f", channels {sim.attacks.dos.shape} ({int(sim.attacks.dos.sum())} "
                  f"packets lost, {int(sim.attacks.fdi.sum())} falsified)"))


@cli.command("filter")
@click.argument("scenario")
@click.option("--data", required=True, metavar="LOG.npz|LOG.csv",
              help="the recorded log: an .npz as cfdesign simulate writes it (z, inputs, channel_dos, channel_fdi, "
                   "channel_xi, uplink, optionally the truth x), or its CSV form (one row per step and sensor)")
@click.option("--filter", "name", default=None, metavar="NAME",
              help="a filter of study comparison, by name, short name (kcf, hcmci, local-ekf-at-every-node-no-"
                   "network, scheduled, tuned, relay, flood, ...) or the beginning of one (local) [default: the "
                   "design of --schedule]")
@click.option("--schedule", default=None, metavar="DIR",
              help="a design directory written by cfdesign design: the designed filter runs with its gain rule and "
                   "options [default: the scenario's design defaults]")
@click.option("--seed", type=int, default=None,
              help="study seed of the particle filters' streams (particle filters only) [default: the log's seed, "
                   "else 0]")
@click.option("--run", type=int, default=None,
              help="study run of the particle filters' streams (particle filters only) [default: the log's run, "
                   "else 0]")
@click.option("--particles", type=int, default=None, help="particles of the particle filters, >= 2 [default: 500]")
@click.option("--iterations", type=int, default=None, help="consensus rounds per step of HCMCI, >= 1 [default: 1]")
@click.option("--out", required=True, help="output directory (estimates.npz, estimates.csv, report.md)")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def filter_cmd(scenario, data, name, schedule, seed, run, particles, iterations, out, assignments) -> None:
    """Run a filter of study comparison on a recorded LOG of SCENARIO (a built-in name or a MODEL.py file)."""
    from .api import filter as filter_log

    res = filter_log(scenario, data, filter=name, schedule=schedule, seed=seed, run=run, particles=particles,
                     iterations=iterations, out=out, assignments=assignments)
    K1, nodes, _ = res.x_hat.shape
    rmse, region = res.rmse(), res.rmse_region()
    if rmse is None:
        score = ""
    elif res.carried is not None:  # its nodes estimate their regions alone
        score = f", RMSE {rmse:.4g} against the log's truth on each node's region"
    elif region is not None:  # on the regions first, as the studies and a design's validation score it
        whole = "the position" if res.scenario.model.position_index else "the whole state"
        score = f", RMSE {region:.4g} against the log's truth on each node's region ({rmse:.4g} over {whole})"
    else:
        score = f", RMSE {rmse:.4g} against the log's truth"
    click.echo(f"wrote {out}/estimates.npz, estimates.csv and report.md: {res.name}, {K1 - 1} steps, {nodes} "
               f"estimate{'s' if nodes > 1 else ''}, runtime {res.runtime}{score}"
               + ("" if res.verdict is None else f", bound {res.verdict}"))
    if res.diverged is not None:
        raise ComputationError(f"filter {res.name!r} diverged at step {res.diverged['step']} (estimates written)")


def _budget_options(f):
    """The automatic design's budget (``design``, ``feasibility``)."""
    f = click.option("--budget-bytes", "budget_bytes", type=int, default=None, metavar="B",
                     help="mode auto: the most bytes per step over the network (8 per number a packet carries), >= 1 "
                          "[default: no cap]")(f)
    return click.option("--budget", default=None, metavar="MSGS|kcf",
                        help="mode auto: the most messages per step over the network, a whole number >= 1, or kcf "
                             "(no more than KCF sends: one per directed channel) [default: no cap]")(f)


@cli.command("design")
@click.argument("scenario")
@functools.partial(_design_options, auto=True)
@_budget_options
@click.option("--validate", type=int, default=None, metavar="R",
              help="fresh Monte Carlo runs of the design (mode auto: of its pick) beside KCF, HCMCI, the local and "
                   "the centralized EKF, written to validation.json, >= 0 [default: 20 in mode auto (fewer, at "
                   "least 5, on a network of more than 4096 node-state rows N n), else 0]")
@click.option("--auto-seconds", "auto_seconds", type=float, default=None, metavar="S",
              help="mode auto: seconds the candidate designs may take; one not done by then is listed as not "
                   "computed, > 0 [default: 45]")
@click.option("--steps", type=int, default=None, help="time steps (default: the scenario's)")
@click.option("--seed", type=int, default=0, show_default=True, help="seed of the simulated run")
@click.option("--out", required=True, help="output directory (schedule.json, schedule.npz, report; mode auto: "
                                           "candidates.json, validation.json)")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def design_cmd(scenario, steps, seed, out, assignments, **kw) -> None:
    """Design the consensus filter of SCENARIO (a built-in name or a MODEL.py file) and write its gain schedule:
    by default the automatic design (every deployable rule's candidates, the best certified one picked)."""
    from .api import design

    res = design(scenario, steps=steps, seed=seed, out=out, assignments=assignments, **_options(kw))
    if hasattr(res, "candidates"):
        return _auto_lines(res, out)
    sch = res.schedule
    click.echo(f"wrote {out}/schedule.json, schedule.npz and report.html: {sch.nodes} nodes, {sch.steps} steps, "
               f"gain rule: {res.gain_rule.label}, epsilon {sch.epsilon:.4g}, feasible {str(sch.feasible).lower()}, "
               f"verdict {res.verdict}" + (", still growing at the horizon" if res.certified and res.growing else "")
               + (f", bounded {str(res.bounded).lower()}" if res.verdict in ("certified", "vacuous") else ""))
    hard = res.hard_violations
    for v in hard[:20]:
        click.echo(f"  violation: node {v['node']} step {v['step']} condition {v['condition']} "
                   + (v["reason"] if "reason" in v else f"margin {v['margin']:.4g}"))
    if len(hard) > 20:
        click.echo(f"  ... and {len(hard) - 20} more (see schedule.json)")
    n_th2 = sum(v["condition"] == "theorem2" for v in sch.violations)
    if n_th2:
        from .reports.design import theorem2_words

        click.echo(f"  {theorem2_words(f'{n_th2} (node, step) pairs', res.verdict)}")
    _validation_lines(res.validation)
    if hard:
        raise ComputationError(f"infeasible design: {res.reason()} (schedule written, marked feasible: false)")
    if not res.certified:  # certified, growing or not, exits 0; anything else 1
        raise ComputationError(f"design {res.verdict_line()} (schedule written, marked certified: false)")
    click.echo(f"  {res.verdict_line()}")


def _validation_lines(validation) -> None:
    """A design's validation on fresh runs (``validation.json``): each filter's RMSE (on the regions, where the
    model declares them, first: what the pick was ranked by), its diverged runs, and whether the pick's bound held on
    them (why not, when it did not: a certified design whose bound the fresh runs exceed must not read as sound)."""
    for f in (validation or {}).get("filters", {}).values():
        parts = [f"{words} {f[key]:.4g}" for key, words in (("rmse_region", "RMSE on the regions"), ("rmse", "RMSE"))
                 if isinstance(f.get(key), (int, float))]
        check = f.get("bound_check") or {}  # the pick's: does its bound hold on the fresh runs?
        if check.get("verdict") in ("holds", "violated"):
            mean = (check.get("run_test") or {}).get("ratio_mean")
            parts.append(f"its bound violated on these runs ({check['verdict_reason']})" if check["verdict"] ==
                         "violated" else f"its bound {'is not refuted' if _above(mean) else 'holds'} on these "
                         f"runs{_held_how(check, said=_above(mean))}")
        if f.get("better_than_local") is not None:  # the pick's, as study comparison says it of a filter
            from .results import local_ratio_text

            parts.append(("better" if f["better_than_local"] else "no better") + " than the nodes alone (its RMSE "
                         f"over theirs on the same runs {local_ratio_text(f)}, the 95 % paired interval "
                         + ("entirely" if f["better_than_local"] else "not entirely") + " below 1)")
        if parts:
            click.echo(f"  validation, {validation['runs']} fresh runs: {f['filter']}: {', '.join(parts)}"
                       + (f", {f['diverged_runs']} diverged" if f.get("diverged_runs") else ""))


def _above(mean) -> bool:
    """A bound check's runs' error energy over their bound on average, above 1."""
    return isinstance(mean, (int, float)) and mean > 1.0


def _held_how(check: dict, said: bool = False) -> str:
    """What a bound check that found no excess measured (``" (...)"``, or ``""`` without its run test): the runs'
    error energy over their bound on average, and where that is above 1 that the bound is not refuted (not shown
    to hold: ``holds`` alone would read stronger than its numbers), with the excess these runs cannot see; ``said``:
    the caller says "not refuted" itself."""
    rt = check.get("run_test") or {}
    mean, tol = rt.get("ratio_mean"), rt.get("tolerance")
    if not isinstance(mean, (int, float)):
        return ""
    text = f"their error energy {mean:.3g} x the bound on average"
    if _above(mean):
        text = ("" if said else "not refuted: ") + text + (
            f"; an excess below {1 + tol:.3g} x goes unseen in these runs" if isinstance(tol, (int, float)) else "")
    return f" ({text})"


def _clipped(text: str, width: int) -> str:
    """``text`` in at most ``width`` characters and ``...``: cut at a space, never inside a word or a number (a reason
    cut at ``got 0.1`` would read ``got 0``); the whole text is in candidates.json."""
    if len(text) <= width:
        return text
    cut = text.rfind(" ", 0, width + 1)
    return text[:cut if cut > 0 else width].rstrip() + " ..."


def _auto_lines(res, out: str) -> None:
    """What ``cfdesign design --mode auto`` prints: the candidates, the pick, the validation; exit 1 without an
    eligible pick (:class:`studies.auto.AutoDesign`)."""
    click.echo(f"wrote {out}/candidates.json" + (", schedule.json, schedule.npz" if res.pick is not None else "")
               + (", validation.json" if res.validation is not None else "") + f" and report.html: "
               f"{len(res.candidates)} candidates in {res.seconds:.1f} s")
    over = " over the regions" if res.scenario.regions is not None else ""
    for i, c in enumerate(res.candidates):
        what = (f"{c.verdict}" + (f", predicted tr Φ{over} {c.predicted:.4g}" if c.predicted is not None else "")
                if c.status == "designed" else f"{c.status}: {_clipped(c.reason or '', 100)}")
        flags = "".join([" [pick]" if i == res.pick_index else "", "" if c.in_budget else " [over budget]",
                         " [no better than local EKFs]" if c.better_than_local is False else ""])
        click.echo(f"  {c.label:44s} {c.messages:5d} msgs {c.bytes:8d} B/step  {what}{flags}")
    _validation_lines(res.validation)
    if not res.certified:
        raise ComputationError(res.message + (" (the best design inside the budget is written, not certified)"
                                              if res.pick is not None else ""))
    click.echo(f"  {res.verdict_line()}")


@cli.command("export")
@click.argument("design_dir")
@click.option("--target", type=click.Choice(["c"]), default="c", show_default=True, help="what to write: C99 sources")
@click.option("--out", required=True, help="output directory (sources, Makefile, test driver, replay.txt)")
@click.option("--node", "nodes", type=int, multiple=True,
              help="a node to export (repeatable) [default: every node]")
@click.option("--data", default=None, metavar="LOG.npz|LOG.csv",
              help="a log to replay in make test [default: the design's simulated run]")
@click.option("--scenario", default=None, metavar="SCENARIO|MODEL.py",
              help="the model, when the design's own file has moved [default: the design's]")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
@click.option("--prefix", default="cfd", show_default=True, metavar="NAME",
              help="the C names: functions, types and files NAME_..., macros in capitals (two exports link into one "
                   "program under two prefixes)")
def export_cmd(design_dir, target, out, nodes, data, scenario, assignments, prefix) -> None:
    """Export the node filter of the design in DESIGN_DIR (gain rule paper, scheduled, relay or flood) as C99 sources
    with a Makefile and a test driver (make test: the C against the Python node filter)."""
    import warnings

    from .api import export

    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always", RuntimeWarning)
        files = export(design_dir, target=target, out=out, nodes=list(nodes) or None, data=data,
                       scenario=scenario, assignments=assignments, prefix=prefix)
    click.echo(f"wrote {len(files)} files to {out}: {', '.join(p.name for p in files)}; build and check with "
               f"make -C {out} test")
    from designer.verdict import known_verdict

    from .recorded import read_design_record

    # a word of the verdicts' vocabulary ("unknown" for any other text): the file's text never reaches the terminal
    verdict = known_verdict(read_design_record(design_dir, "design_dir")[1].get("verdict"))
    if verdict != "certified":  # said plainly: the code runs the design, whose bound is not certified
        click.echo(f"  the design's verdict is {verdict!r}, not certified: its bound is not a guarantee (see "
                   f"{design_dir}/report.md)")
    for w in said:
        click.echo(f"  {w.message}")


@cli.command("feasibility")
@click.argument("scenario")
@click.option("--grid", "grids", multiple=True, required=True, metavar="NAME=START:STOP:COUNT",
              help="grid over dos, fdi, delta, amplitude, tau, sigma, beta, epsilon, u_scale or v_scale (repeatable)")
@click.option("--out", required=True, help="output directory (feasibility.csv, feasibility.png, report)")
@functools.partial(_design_options, auto=True)
@_budget_options
@_runner_options
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def feasibility_cmd(scenario, grids, out, workers, dask, dask_security, force, quiet, assignments, **kw) -> None:
    """Map where the consensus design of SCENARIO admits a bounded steady-state bound: by default the automatic map
    (at each grid point, the best certified candidate of every rule the map maps)."""
    from .api import feasibility

    fmap = feasibility(scenario, grids, out=out, workers=workers, dask=dask, dask_security=dask_security,
                       force=force, quiet=quiet,
                       assignments=assignments, **_options(kw))
    n_ok = sum(r["feasible"] for r in fmap.rows)
    failed = f", {len(fmap.failures)} failed (see the report)" if fmap.failures else ""
    counts = ", ".join(f"{c} {v}" for v, c in fmap.verdict_counts.items() if c)
    click.echo(f"wrote {out}/feasibility.csv and report.html: {n_ok} of {len(fmap.rows)} grid points feasible{failed} "
               f"({fmap.mode} design); verdicts: {counts}")
    if fmap.auto is not None:
        won = [f"{c['label']} {c['picked_points']}" for c in fmap.auto["candidates"] if c["picked_points"]]
        click.echo(f"  picked: {', '.join(won) or 'none'}; {sum(r['better_than_local'] == 0 for r in fmap.rows)} "
                   "points no better than the nodes' local EKFs")


@cli.command("study")
@click.argument("study")
@click.argument("targets", nargs=-1, metavar="[SCENARIO|MODEL.py ...]")
@click.option("--out", required=True, help="output directory (results.json, table.md, figures, report)")
@click.option("--scenario", "scenarios", multiple=True,
              help="a scenario or model file to run on (repeatable; the same as the positional arguments) "
                   "[default: the study's own]")
@click.option("--runs", type=int, default=None, help="Monte Carlo runs [default: the study's]")
@click.option("--particles", type=int, default=None,
              help="particles M of the particle filters [default: the study's]")
@click.option("--seed", type=int, default=0, show_default=True, help="random seed")
@_runner_options
@_design_options
@click.option("--engine", type=click.Choice(["fast", "numpy"]), default=None,
              help="particle-filter studies: fused numba kernels or the NumPy reference [default: fast]")
@click.option("--schedule", default=None, help="consensus-robot: replay the gains of this design directory")
@click.option("--filters", "filters", default=None, metavar="NAME,...",
              help="comparison: run only these filters (names as cfdesign filter --filter takes them, e.g. "
                   "kcf,hcmci,local,centralized-ekf) [default: every filter]")
@click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE", help=_SET_HELP)
def study_cmd(study, targets, out, scenarios, runs, particles, seed, workers, dask, dask_security, force, quiet,
              engine, schedule, filters, assignments, **kw) -> None:
    """Run the Monte Carlo study STUDY (on its scenarios or on SCENARIO / MODEL.py) and write its results.

    STUDY is one of: comparison (every filter family on the same runs and attacks; any model with a
    NETWORK), consensus-robot (seed 003's consensus study; any model with a NETWORK), rrp-deception,
    encrypted-switching, binary-multi-attack, fdi-four-tank (seeds 000, 001, 002, 004; a model that
    declares the paper's CHANNEL).
    """
    from designer.design import DesignOptions

    from .api import study as run_study

    extra = {k: v for k, v in (("engine", engine), ("schedule", schedule), ("filters", filters)) if v is not None}
    chosen = list(targets) + list(scenarios)
    res = run_study(study, chosen or None, out=out, runs=runs, particles=particles, seed=seed, workers=workers,
                    dask=dask, dask_security=dask_security, force=force, quiet=quiet,
                    options=DesignOptions(**_options(kw)),
                    assignments=assignments, **extra)
    r = res.results
    runner = r.get("runner", {})
    blocks = runner.values() if runner and all(isinstance(v, dict) and "chunks_computed" in v
                                               for v in runner.values()) else [runner]
    done = sum(b.get("chunks_computed", 0) for b in blocks)
    reused = sum(b.get("chunks_reused", 0) for b in blocks)
    m = "" if r.get("particles") is None else f", M = {r['particles']}"
    click.echo(f"wrote {out}/results.json, table.md, report.html and figures ({r['runs']} runs{m}, "
               f"{r['wall_time_s']:.1f} s; {done} chunks computed, {reused} reused)")
    for name, f in r["filters"].items():
        click.echo(f"  {name}: {_summary(f)}")
    for name, why in (r.get("left_out") or {}).items():  # not run, and why: said here, not in the report alone
        click.echo(f"  {name}: left out: {why}")


def _summary(f: dict) -> str:
    """One filter's line: its accuracy, cost and (consensus) bound check; a design that could not start says why."""
    if f.get("infeasible"):
        return f"infeasible, not run: {f['infeasible']}"
    parts = []
    for key, label in (("rmse_region", "RMSE_region"), ("rmse_position", "RMSE_p"), ("rmse", "RMSE")):
        if key in f:
            if f[key] is None:
                parts.append("every run diverged")
            else:
                parts.append(f"{label} {f[key]:.4g}")
                if f.get(f"{key}_median_run") is not None:
                    parts[-1] += f" (median run {f[f'{key}_median_run']:.4g})"
            break
    else:
        if "rmse_state" in f:
            parts.append("RMSE per state " + ", ".join(f"{v:.4g}" for v in f["rmse_state"]))
    if f.get("rmse_velocity") is not None:
        parts.append(f"RMSE_v {f['rmse_velocity']:.4g}")
    if f.get("rmse_truth") is not None:
        parts.append(f"{f['rmse_truth']:.4g} against the truth")
    if f.get("degenerate"):
        parts.append(f"degenerate: its weight on {f['weights_ess']:.3g} of {f['particles']} particles (typical "
                     "effective sample size), so it does not track this state and its error is no measure of a "
                     "particle filter's")
    if f.get("time_per_step_s") is not None:
        parts.append(f"{f['time_per_step_s'] * 1e3:.3g} ms/step")
    msgs = f.get("messages_per_step", f.get("communications"))
    if msgs is not None:
        parts.append(f"{msgs} {'messages/step' if 'messages_per_step' in f else 'communications'}")
    bc = f.get("bound_check")
    if bc:
        frac = "n/a" if bc["fraction_exceeding"] is None else f"{bc['fraction_exceeding']:.3f}"
        parts.append(f"bound checked at {bc['pairs_checked']}/{bc['pairs_total']} (node, step) pairs, exceeded at "
                     f"{frac}" + (f", verdict: {bc['verdict']}" if bc.get("verdict") else "")
                     + (_held_how(bc) if bc.get("verdict") == "holds" else "")
                     + (f", informative in {bc['informative']}/{bc['runs']} runs" if bc.get("informative") is not None
                        else "")
                     + (f", filled to {bc['fill']:.2g} over steps {bc['fill_steps'][0]}..{bc['fill_steps'][1]}"
                        if bc.get("fill") is not None and bc.get("fill_steps") else ""))
    if isinstance(f.get("feasibility"), dict):
        parts.append(f"feasible runs {f['feasibility']['runs_feasible']}/{f['feasibility']['runs']}")
    if isinstance(f.get("verdicts"), dict):
        parts.append(f"certified runs {f['verdicts']['certified']}/{sum(f['verdicts'].values())}"
                     + (f", bounded runs {f['bounded_runs']}" if f.get("bounded_runs") is not None else ""))
    if f.get("better_than_local") is False:
        from .results import local_ratio_text

        parts.append(f"no better than the nodes alone (its RMSE over theirs on the same runs {local_ratio_text(f)}, "
                     "the 95 % paired interval not entirely below 1)")
    return ", ".join(parts)


@cli.command("report")
@click.argument("directory")
def report_cmd(directory: str) -> None:
    """Write DIRECTORY/report.html (self-contained) and report.md from a study's, design's or feasibility map's files."""
    from .api import report

    html, md = report(directory)
    click.echo(f"wrote {html} and {md}")


@cli.group("cache")
def cache_group() -> None:
    """The compiled numba kernels, cached per machine in $CFDESIGN_CACHE_DIR (default ~/.cache/cfdesign)."""


@cache_group.command("clear")
def cache_clear_cmd() -> None:
    """Remove the compiled kernels; the next run compiles them again."""
    from designer.jitcache import cache_dir, clear_cache  # imports numba: only for this command

    removed = clear_cache()
    for path in removed:
        click.echo(f"removed {path}")
    if not removed:
        click.echo(f"nothing to remove in {cache_dir()}")


def _with_debug(command: click.Command) -> None:
    """Give ``command`` and every command under it the ``--debug`` flag, so that it is accepted before and after a
    command's name; click parses it, so a ``--debug`` that is an option's value (``--set --debug``) or an argument
    after ``--`` stays what it is."""
    command.params.append(click.Option(["--debug"], is_flag=True, expose_value=False, callback=_debug,
                                       help=_DEBUG_HELP))
    for sub in getattr(command, "commands", {}).values():
        _with_debug(sub)


_with_debug(cli)


def main(argv=None) -> int:
    """Entry point of the console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    obj = {}  # the commands' context object: --debug, anywhere on the line, sets obj["debug"]
    with warnings.catch_warnings():  # restored on return (main is also called in-process, by the tests)
        warnings.simplefilter("ignore", RuntimeWarning)  # overflow and the like: results are checked for finiteness
        warnings.showwarning = _one_line_warnings(warnings.showwarning)
        from designer.progress import showing

        with showing():  # a progress line on stderr every few seconds of a long command (designer.progress)
            return _main(argv, obj)


def _one_line_warnings(show):
    """A ``warnings.showwarning`` that prints cfdesign's own warnings as one line each on stderr (a text once, however
    often the model is built), and passes the others to ``show``."""
    shown = set()

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if not issubclass(category, CfdesignWarning):
            return show(message, category, filename, lineno, file, line)
        if str(message) not in shown:
            shown.add(str(message))
            click.echo(f"cfdesign: warning: {message}", err=True)

    return showwarning


def _main(argv: list, obj: dict) -> int:
    from .interrupts import Interrupts

    try:
        # make_context and invoke rather than cli.main: click.main answers a KeyboardInterrupt with an empty line
        # on stderr before ours, and the model layer is imported inside the commands (a Ctrl-C there is start-up)
        with Interrupts() as interrupts:
            try:
                with cli.make_context("cfdesign", argv, obj=obj) as ctx:
                    cli.invoke(ctx)
            finally:  # a Ctrl-C that a library swallowed ends the command as interrupted, whatever it did next
                interrupts.check()
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        click.echo(f"cfdesign: error: {exc.format_message()}", err=True)
        return 2
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("cfdesign: interrupted", err=True)
        return 130
    except InputError as exc:
        if obj.get("debug"):
            traceback.print_exc()
        click.echo(f"cfdesign: error: {exc}", err=True)
        return 2
    except ComputationError as exc:
        if obj.get("debug"):
            traceback.print_exc()
        click.echo(f"cfdesign: failed: {exc}", err=True)
        return 1
    except OSError as exc:  # a path that cannot be made or used is bad input (2); a full disk is a failure (1)
        if obj.get("debug"):
            traceback.print_exc()
        where = f" {exc.filename!r}" if exc.filename else ""
        bad_path = exc.errno in (errno.ENOENT, errno.EACCES, errno.EPERM, errno.ENOTDIR, errno.EISDIR, errno.EROFS,
                                 errno.ENAMETOOLONG, errno.EEXIST)
        click.echo(f"cfdesign: {'error' if bad_path else 'failed'}: cannot write or read{where}: "
                   f"{exc.strerror or exc}", err=True)
        return 2 if bad_path else 1
    except Exception as exc:  # noqa: BLE001 - the CLI contract is one line, no traceback
        if obj.get("debug"):
            traceback.print_exc()
        msg = str(exc).splitlines()[0] if str(exc) else ""
        click.echo(f"cfdesign: internal error: {type(exc).__name__}: {msg} (rerun with --debug)", err=True)
        return 1
    return 0
