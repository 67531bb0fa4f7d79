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
