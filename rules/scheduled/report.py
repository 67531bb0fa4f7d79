"""The scheduled rule's words in the design report (its hooks :meth:`designer.rule.GainRule.report_settings` and
:meth:`designer.rule.GainRule.report_margins`), from ``schedule.json``'s record, read as data."""
from __future__ import annotations

from typing import Mapping

__all__ = ["settings"]


def settings(meta: Mapping, fmt) -> list[str]:
    """How the tables were designed, the stationary certificate, the robustness margin, the bank, the trade-off of
    exchange rounds against accuracy."""
    out: list[str] = []
    st = meta.get("stationary") if isinstance(meta.get("stationary"), dict) else {}
    carry = ("prediction and its measurement" if meta.get("exchange") == "measurements" else
             "prediction alone, as in (7)")
    out += ["Scheduled mode: the per-link gains are designed offline for the channels' DoS and FDI probabilities "
            "from the expected joint error covariance of all nodes along the nominal trajectory "
            "(`rules.scheduled.design`); every node applies them on any run with its own estimate, covariance and "
            f"Jacobians and the packets that arrived; a packet carries the sender's {carry}. "
            + ((("Every step uses" if not meta.get("tables_own_steps") else
                 f"The first {meta.get('tables_own_steps')} steps use their own tables, and the later ones")
                + " the stationary tables"
                + (" (chosen by the tables' size: per-step tables for every step would hold more than "
                   f"{st.get('budget', 'the budget of')} numbers, and the nominal keeps the operating point's "
                   "linearisation)"
                   if meta.get("table_kind") is None else " (`--table-kind stationary`)")
                + ": the expected recursion's fixed point at the operating point, from the prior"
                + (f", reached after {st.get('extra_steps')} steps." if st.get("converged") else
                   ", which did not settle within the steps tried: the last tables computed.")
                + " The expected covariance and the bound are those of the tables used; from the prior they "
                "settle more slowly than with each step's own (`--table-kind per-step`), and until they settle a "
                "node's own covariance is what the stationary tables say of its links, not its expected one "
                "(on a linear 5-node ring up to 20 % below it).")
               if meta.get("tables_kind") not in (None, "per-step") else
               ((f"The default's stationary tables were not used: "
                 f"{fmt.md_escape(str(st['held_failed']))}. " if st.get("held_failed") else "")
                + "The tables beyond the horizon are the recursion continued at the last nominal point"
                + (f", stationary after {st.get('extra_steps')} more steps." if st.get("converged") else
                   ", which did not settle within the steps tried: beyond the horizon the gains are the last ones "
                   "computed.")))
            + " The bound is the expected one over the attacks, for the nominal gains and linearisation with the "
            "remainders U, V_i: study consensus-robot validates it on runs the design never saw.", ""]
    sc_ = meta.get("stationary_certificate") if isinstance(meta.get("stationary_certificate"), dict) else None
    if sc_:
        lmi = sc_.get("lmi") if isinstance(sc_.get("lmi"), dict) else {}
        if sc_.get("converged"):
            tr = sc_.get("trace") or []
            what = (f"reaches a fixed point after {sc_.get('iterations')} iterations (largest node trace "
                    f"{fmt.fmt_num(max(tr)) if tr else '—'})")
            if lmi.get("trace") is not None:
                what += (f"; the LMI (cvxpy + Clarabel, σ and β of the fixed point) gives a total trace of "
                         f"{fmt.fmt_num(lmi['trace'])}, its own recursion step exceeding it by "
                         f"{fmt.fmt_num(lmi.get('relative_residual'))} of its largest eigenvalue")
            elif lmi.get("status"):
                what += (f"; the LMI was {fmt.md_escape(str(lmi.get('status')))} "
                         f"({fmt.md_escape(str(lmi.get('reason')))})")
        else:
            what = f"does not: {fmt.md_escape(str(sc_.get('reason')))}"
        out += [f"**Stationary certificate** (verdict: {fmt.md_escape(str(sc_.get('verdict')))}): the bound's "
                "recursion at the operating point with the stationary gains " + what + ".", ""]
    out += [f"Robustness margin δ = {fmt.fmt_num(meta.get('robustness'))}: each link's gains are chosen as if the "
            "neighbour's difference carried an extra independent error δ P_ii (a node never leans on its "
            "neighbours by more than tr P⁻ / δ).", ""]
    bank = meta.get("bank_record") if isinstance(meta.get("bank_record"), dict) else None
    if bank:
        out += [f"**Bank of operating points** ({bank.get('axes')} axes, spread {fmt.fmt_num(bank.get('spread'))} "
                f"open-loop standard deviations): stationary tables at {bank.get('points')} points off the "
                f"nominal trajectory ({bank.get('skipped')} left out: the same Jacobians as the nominal's); "
                "each node uses, at every step, the tables of the point nearest its own prediction. They are "
                "not covered by the certificate.", ""]
    trade = meta.get("rounds_tradeoff") if isinstance(meta.get("rounds_tradeoff"), dict) else None
    if trade and trade.get("rows"):
        out += [f"**Accuracy and messages** ({meta.get('rounds')} exchange round(s) per step designed; the "
                f"expected RMSE of the nodes at step {trade.get('step', meta.get('steps'))}, from the design's "
                "expected covariance; for L > 1 the rounds' packet losses are taken as fresh draws and no "
                "certificate is computed):", "",
                "| rounds L | messages per step | expected RMSE |", "|---:|---:|---:|"]
        out += [f"| {r['rounds']}{' (designed)' if r.get('designed') else ''} | {r['messages_per_step']} | "
                f"{fmt.fmt_num(r['expected_rmse'])} |" for r in trade["rows"]]
        out += [""] + ([fmt.md_escape(str(trade["note"])), ""] if trade.get("note") else [])
    return out
