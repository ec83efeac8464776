"""The report's sections, in the order a lab reads them: run file and its SHA-256, specimen,
method, machine, curves, results, fit, diagnosis, schedule - and a series' table."""

from __future__ import annotations

import math
from pathlib import Path

from foamlab.reporting.content import ReportContent
from foamlab.reporting.pdf import Document, text
from foamlab.reporting.series import SpecimenSeries, readable_name, unit_text

#: Warnings of the fit listed in the report (all of them are in the fit sidecar).
FIT_WARNINGS = 5
VERDICT_MEANING = {
    "none": "the model explains the data down to the noise: white residuals, no cause passes the tests",
    "unexplained": "the residuals have structure that no candidate cause explains",
}


def num(v, fmt: str = ".4g", missing: str = "-") -> str:
    if v is None:
        return missing
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return format(f, fmt) if math.isfinite(f) else missing


def _meta(run, word: str) -> str:
    """A metadata value whose key mentions `word` (foamlab's meta.operator, a vendor header's)."""
    sources = [run.metadata, run.metadata.get("header") or {}]
    for source in sources:
        for key, value in source.items() if isinstance(source, dict) else ():
            if word in str(key).lower() and value not in (None, ""):
                return str(value)
    return ""


def run_file(doc: Document, c: ReportContent) -> None:
    run = c.run
    doc.heading("Run file")
    doc.fields([
        ("file", c.path.name), ("folder", str(c.path.resolve().parent)),
        ("format", str(run.metadata.get("format", ""))),
        ("SHA-256", c.sha256),
        ("status", run.status + (f" ({run.abort_reason})" if run.abort_reason else "")),
        ("started", run.started_at or "-"), ("finished", run.finished_at or "-"),
    ], mono=("SHA-256",))


def _mm(v) -> str:
    return f"{num(v)} mm" if v else "- (not recorded)"


def specimen(doc: Document, c: ReportContent) -> None:
    s = c.run.specimen
    doc.heading("Specimen")
    doc.fields([
        ("label", s.label or "-"),
        ("height", _mm(s.height_mm)), ("width", _mm(s.width_mm)), ("depth", _mm(s.depth_mm)),
        ("area", f"{num(s.area_mm2, '.6g')} mm²" if s.area_mm2 else "- (width and depth unknown)"),
        ("operator", _meta(c.run, "operator") or "-"),
        ("date", c.run.started_at or _meta(c.run, "date") or "-"),
    ])


def steps_text(method) -> list[str]:
    """The method's steps, consecutive cycles that do the same grouped."""
    per_cycle: list[tuple[int, str]] = []
    for k in range(1, method.n_cycles + 1):
        per_cycle.append((k, ", ".join(s.describe() for s in method.steps if s.cycle == k)))
    lines, i = [], 0
    while i < len(per_cycle):
        j = i
        while j + 1 < len(per_cycle) and per_cycle[j + 1][1] == per_cycle[i][1]:
            j += 1
        first, last = per_cycle[i][0], per_cycle[j][0]
        lines.append(f"cycle{'s' if last > first else ''} {first}{f'-{last}' if last > first else ''}: "
                     f"{per_cycle[i][1]}")
        i = j + 1
    return lines


def method(doc: Document, c: ReportContent) -> None:
    doc.heading("Method")
    m = c.method
    if m is None:
        why = c.analysis.method_error or "no test method recorded with the run"
        doc.fields([("method", c.run.method or "-"), ("note", why)])
        return
    items = [("method", f"{m.name}: {m.title}")]
    if m.reference:
        items.append(("reference", m.reference))
    items += [("sampling", f"{m.sampling_hz:g} Hz"),
              ("contact search", f"preload {m.contact.preload_N:g} N at {m.contact.search_speed_mm_min:g} mm/min")]
    items += [("steps" if i == 0 else "", line) for i, line in enumerate(steps_text(m))]
    doc.fields(items)


def machine(doc: Document, c: ReportContent) -> None:
    md = c.run.metadata
    doc.heading("Machine profile")
    items = [("machine", c.run.machine or "- (not recorded in the file)")]
    for key, label in (("limits", "safety limits"), ("scheduling", "scheduling"), ("speedup", "clock speedup")):
        if md.get(key) not in (None, ""):
            items.append((label, f"{md[key]}x" if key == "speedup" else str(md[key])))
    items.append(("recorded by", str(md.get("software") or md.get("format") or "-")))
    doc.fields(items)


def curves(doc: Document, png: Path | None) -> None:
    doc.heading("Curves")
    doc.figure(png, "Force against displacement per cycle (loading solid, unloading dashed) and force "
                    "and displacement in time; displacement from the contact point, compression positive.")


def results(doc: Document, c: ReportContent) -> None:
    doc.heading("Results of the method")
    r = c.analysis.method_results
    if r is None or not len(r):
        if c.analysis.method_error:
            why = c.analysis.method_error
        elif c.method is None:
            why = "no test method recorded with the run (foamlab report --method gives one)"
        elif not c.run.specimen.height_mm:
            why = "the specimen height is not recorded in the file (the results are fractions of it)"
        else:
            why = "the run reached none of the method's cycles"
        doc.paragraph(text(f"not available: {why}"))
        return
    rows = [[readable_name(v), num(v.value), unit_text(v.unit), v.note or v.description] for v in r]
    doc.table(["quantity", "value", "unit", "note"], rows, [0.34, 0.14, 0.1, 0.42])


def fit(doc: Document, c: ReportContent, png: Path | None) -> None:
    doc.heading("Fit of the model")
    f = c.analysis.fit
    if f is None:
        doc.paragraph(text(f"not fitted: {c.analysis.fit_error or ' '.join(c.notes) or 'not asked for'}"))
        return
    ratio = f.rmse / f.noise_N if f.noise_N > 0 else float("nan")
    dropped = f"; {f.dropped} of {f.run_samples} samples dropped (off the sampling schedule)" if f.dropped else ""
    doc.paragraph(text(f"orders {f.orders}; {f.n_obs} samples fitted, {f.n_params} free parameters{dropped}; RMSE "
                       f"{num(f.rmse)} N on all {f.rmse_count} recorded samples = {num(ratio, '.2f')} x the load "
                       f"cell's noise ({num(f.noise_N, '.3g')} N); optimizer {f.convergence}. "
                       "Statistics per step of the paper's identification (Table 5) and of the joint refinement:"))
    rows = []
    for step in ("damping", "residual", "elastic", "joint"):
        st = f.statistics.get(step)
        rows.append([step] + (["(skipped)", "", "", "", "", ""] if st is None else
                              [num(st.sse, ".5g"), num(st.r2, ".5f"), num(st.adj_r2, ".5f"),
                               f"{num(st.rmse)} N", str(st.n), str(st.p)]))
    doc.table(["step", "SSE (N²)", "R²", "adjusted R²", "RMSE", "n", "p"], rows,
              [0.16, 0.16, 0.14, 0.14, 0.16, 0.12, 0.12])
    choice = f.form_choice
    if choice is not None and len(choice.scores) > 1:
        mine = choice.score(choice.chosen)
        doc.paragraph(text(f"Residual force: {choice.reason()}. Both forms (docs/model.md):"))
        doc.table(["residual form", "RMSE", "held-out RMSE", "dBIC", "kept"],
                  [[sc.form, f"{num(sc.rmse)} N", f"{num(sc.heldout_rmse)} N", num(sc.bic - mine.bic, ".1f"),
                    "yes" if sc.form == choice.chosen else ""] for sc in choice.scores],
                  [0.28, 0.18, 0.18, 0.18, 0.18])
    elif choice is not None and choice.settled:
        doc.paragraph(text(f"Residual force: {choice.reason()}."))
    params = [p for p in f.parameters.values() if p.determined]
    doc.paragraph(text(f"Parameters the data determine ({len(params)} of {len(f.names)}: varied, with a "
                       "standard error, 95 % interval excluding zero):"))
    doc.table(["parameter", "value", "standard error", "unit"],
              [[p.name, num(p.value, ".6g"), num(p.stderr, ".3g"), p.unit or "-"] for p in params]
              or [["(none)", "", "", ""]], [0.25, 0.25, 0.25, 0.25])
    failed = [k for k, ok in f.constraints.items() if not ok]
    if failed:
        doc.paragraph(text("Thermodynamic checks failed (Eqs. 23-25): " + ", ".join(failed)))
    if f.warnings:
        shown = f.warnings[:FIT_WARNINGS]
        doc.paragraph(text(f"Warnings ({len(f.warnings)}; the first {len(shown)}): ") +
                      "; ".join(text(w) for w in shown), "small")
    doc.figure(png, "Measured (grey) and fitted force per cycle; measured - fitted below.")


def forecast(doc: Document, c: ReportContent) -> None:
    """Each cycle as predicted from the cycles before it, against what was measured."""
    doc.heading("Forecast of each cycle from the earlier ones")
    a = c.analysis
    scores = a.forecast
    if scores is None:
        doc.paragraph(text(f"not made: {a.forecast_error or a.fit_error or 'the run was not fitted'}"))
        return
    when = ("during the run (live prediction)" if scores.live else
            "after the run, from the run file (the live prediction's rule)")
    doc.paragraph(text(f"The model identified on cycles 1..k-1 alone, run on the displacement of cycle k and "
                       f"compared with its measured force: how well the first cycles predict the next, made "
                       f"{when}. 1 x noise is as good as the load cell allows."))
    rows = [[str(s.cycle), f"1-{s.from_cycles}", num(s.rmse_N), num(s.ratio, ".3g"), num(s.bias_N, "+.3g"),
             str(s.n_samples)] for s in scores.scores]
    doc.table(["cycle", "predicted from cycles", "RMSE (N)", "x noise", "mean (N)", "samples"],
              rows or [["(none)", "", "", "", "", ""]], [0.12, 0.22, 0.16, 0.14, 0.18, 0.18])
    if scores.note:
        doc.paragraph(text(scores.note), "small")


def diagnosis(doc: Document, c: ReportContent, png: Path | None, caption: str) -> None:
    doc.heading("Diagnosis")
    d = c.diagnosis_dict
    if d is None:
        doc.paragraph(text(f"not diagnosed: {c.analysis.diagnosis_error or 'not asked for'}"))
        return
    verdict = d.get("verdict", "")
    named = next((f for f in d.get("findings", []) if f.get("effect") == verdict), None)
    meaning = VERDICT_MEANING.get(verdict) or (named or {}).get("meaning", "")
    origin = (f"stored with the run ({c.stored_diagnosis.path.name}, {c.stored_diagnosis.data.get('created', '')})"
              if c.stored_diagnosis else "made now, on the fit above")
    doc.paragraph(f"<b>verdict: {text(verdict)}</b>" + (f" - {text(meaning)}" if meaning else "")
                  + text(f". Diagnosis {origin}."))
    if named and named.get("description"):
        doc.paragraph(text(f"fitted: {named['description']}"))
    rows = []
    for f in d.get("findings", []):
        g = f.get("gain", {})
        rows.append([f.get("effect", ""), num(g.get("rmse_before")), num(g.get("rmse_after")),
                     num(g.get("heldout_rmse_before")), num(g.get("heldout_rmse_after")),
                     num(g.get("delta_bic"), ".1f"), "yes" if f.get("effect") == verdict else ""])
    doc.paragraph(text("Gain of each extension of the model (RMSE in N on the diagnosis's evidence samples - "
                       "the samples at turns the samples cannot place left out, unlike the fit's RMSE above - "
                       "and on held-out blocks; dBIC: drop of the Bayesian information criterion):"))
    doc.table(["finding", "RMSE before", "RMSE after", "held-out before", "held-out after", "dBIC", "named"],
              rows or [["no extension passed", "", "", "", "", "", ""]],
              [0.22, 0.13, 0.13, 0.14, 0.14, 0.12, 0.12])
    for f in d.get("findings", []):
        if f.get("where"):
            doc.paragraph(text("structure left: " + "; ".join(map(str, f["where"]))), "small")
    limits = [item["text"] for item in d.get("detection_limits") or [] if item.get("text")]
    if limits:
        doc.paragraph(text("What this run could have seen (the smallest size of each cause named in 90 % of "
                           "runs like it): " + "; ".join(limits) + "."), "small")
    doc.figure(png, caption)


def schedule(doc: Document, c: ReportContent) -> None:
    s = c.schedule
    doc.heading("Schedule statistics")
    items = [("samples", str(s.samples)),
             ("sampling rate", f"{num(s.sampling_hz, '.4g')} Hz"),
             ("duration", f"{num(s.duration_s, '.2f')} s (machine time)")]
    if s.expected_samples is not None:
        items.append(("planned samples", f"{s.expected_samples} (the method's steps for this specimen; "
                                         "contact search and park are not recorded)"))
    if s.missed is not None:
        pct = f" ({num(s.missed_percent, '.2f')} % of the deadlines)" if s.missed_percent is not None else ""
        items.append(("missed deadlines", f"{s.missed}{pct}, {s.missed_source}"))
    if s.speedup:
        items.append(("speedup", f"{s.speedup:g}x (simulated machine)"))
    doc.fields(items)


def notes(doc: Document, c: ReportContent) -> None:
    if c.notes:
        doc.heading("Notes")
        for n in c.notes:
            doc.paragraph(text(n), "small")


def series_table(doc: Document, series: SpecimenSeries, list_files: bool = True) -> None:
    """Each specimen's results and the series statistics (mean, sd, cv), one column per specimen
    (results as rows: a method may have a dozen of them)."""
    doc.heading(f"Specimen series ({len(series)} specimens, method {series.method.name})")
    if list_files:
        doc.fields([(f"{i}. {s.label}", f"{s.path.name}") for i, s in enumerate(series.specimens, 1)])
    for s in series.specimens:
        if s.error:
            doc.paragraph(text(f"{s.label}: no results: {s.error}"), "small")
    header = ["quantity", "unit"] + [str(i) for i in range(1, len(series) + 1)] + ["n", "mean", "sd", "cv %"]
    rows = []
    for st in series.statistics:
        col = st.column
        rows.append([col.title, unit_text(col.unit)] + [num(s.value(col)) for s in series.specimens]
                    + [str(st.n), num(st.mean), num(st.sd, ".3g"), num(st.cv_percent, ".3g")])
    n = len(series)
    first = 0.21 if n <= 6 else 0.16
    rest = (1.0 - first - 0.08) / (n + 4)
    doc.table(header, rows, [first, 0.08] + [rest] * (n + 4))
    doc.paragraph(text("sd: sample standard deviation (n - 1); cv: sd / |mean|. Specimens without a value "
                       "(see the notes of their results) are left out of the statistics."), "small")
