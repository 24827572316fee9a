"""The Markdown report of ``afmctl diagnose`` (``report.md``): the verdict, its evidence, what
would tell more, the candidate table and the residuals of the paper's model. Pure text from a
:class:`afmctl.fit.diagnosis.Diagnosis`: no I/O."""

from __future__ import annotations

from afmctl.fit import diagnosis as dg
from afmctl.fit.verdict import ratio, required_gain


def _suggestion_lines(d: dg.Diagnosis) -> list[str]:
    if not d.suggestions():
        return []
    return ["", "What the residual shows, and what would tell more:", ""] + [
        f"- {s['reading']}: {s['measure']}." for s in d.suggestions()]


_HEADER = ["| candidate | parameters added | held-out RMS (um) | x noise | gain | needed | fitted |",
           "|---|---:|---:|---:|---:|---:|---|"]


def _rows(table: dict[str, dg.Judged], noise_um: float, refused: dict[str, str] | None = None
          ) -> list[str]:
    """One row per judged model, best first; gains against the table's own ``none``."""
    base, out = table["none"].heldout_rms_um, []
    for name, j in sorted(table.items(), key=lambda kv: kv[1].heldout_rms_um):
        fitted = dg.fitted_text(j.fitted.parameters)
        why = f" (refused: {refused[name]})" if refused and name in refused else ""
        out.append(f"| {name} | {j.n_params} | {j.heldout_rms_um:.4f} | "
                   f"{ratio(j.heldout_rms_um, noise_um):.2f} | "
                   f"{ratio(base, j.heldout_rms_um):.2f} | "
                   f"{required_gain(j.n_params):.2f} | {fitted}{why} |")
    return out


def report(d: dg.Diagnosis, figure: str) -> str:
    """A short Markdown report: the cause, its evidence, the candidate table, the residuals."""
    lines = [f"# afmctl diagnose: {d.cause}", "", d.explanation + ".", "",
             d.evidence() + ".",
             *_suggestion_lines(d),
             "", "Held-out RMS: each candidate fitted on the first half of every sweep and judged "
             "on the second half.", "", *_HEADER, *_rows(d.table, d.noise_um)]
    if d.held is not None:
        lines += ["", f"The same causes on {dg.HELD_BASE} (identify's model on the first halves; "
                  "judged on the second halves):", "", *_HEADER,
                  *_rows(d.held.table, d.noise_um, d.held.refused)]
    if d.grid is not None:
        g = d.grid
        lines += ["", "The Preisach grid (identify's representation off the paper's family), judged "
                  "on held-out blocks as identify judges it:", "",
                  "| model | held-out RMS (um) | x noise | per sweep (um) |", "|---|---:|---:|---|"]
        for name, rms, per in ((g.plain.name, g.plain_rms_um, g.plain_per_sweep_um),
                               (g.crept.name, g.crept_rms_um, g.crept_per_sweep_um)):
            lines.append(f"| {name} | {rms:.4f} | {ratio(rms, d.noise_um):.2f} | "
                         + " / ".join(f"{r:.4f}" for r in per) + " |")
        lines += ["", f"The grid: {g.text()}."]
    sig = d.signature
    lines += ["", "## Residuals of the paper's model", "",
              "| sweep | frequency (Hz) | RMS (um) | mean (um) | corr. field | corr. field rate "
              "| RMS after turning points (um) | elsewhere (um) |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for p in sig["sweeps"]:
        lines.append(f"| {p['file']} | {p['frequency_hz'] or ''} | {p['rms_um']:.4f} | "
                     f"{p['mean_um']:.4f} | {p['corr_field']:.2f} | {p['corr_field_rate']:.2f} | "
                     f"{p['rms_after_turning_points_um']:.4f} | {p['rms_elsewhere_um']:.4f} |")
    lines += ["", f"All sweeps: correlation with field {sig['corr_field']:.2f}, with field squared "
              f"{sig['corr_field_squared']:.2f}, with field rate {sig['corr_field_rate']:.2f}; "
              f"spread of the per-sweep mean residual {sig['between_sweeps_mean_spread_um']:.4f} um.",
              "", f"![residuals before and after]({figure})", ""]
    return "\n".join(lines)
