"""The test report a lab archives (a PDF) and the specimen series (statistics, CSV).

    from foamlab.reporting import write_report, specimen_series, write_series_report
    write_report("run.csv", "run.report.pdf")                 # the pipeline runs what is missing
    write_report(path, out, analysis=window_analysis)          # the window's Analysis, completed
    s = specimen_series(["a.csv", "b.csv"]); s.write_csv("series.csv"); write_series_report(s, "s.pdf")

Sections: run file (with its SHA-256, also in every page's footer), specimen, method, machine
profile, curves (F-x, F-t), the method's results, the fit (Table-5 statistics, the parameters
the data determine, figure), the forecast of each cycle from the earlier ones, the diagnosis
(verdict, gain table, figure), schedule statistics.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from foamlab import FoamlabError
from foamlab.reporting import figures, sections
from foamlab.reporting.content import ReportContent, ScheduleSummary, gather
from foamlab.reporting.pdf import Document, text
from foamlab.reporting.series import SpecimenSeries, series_from_runs, specimen_series

__all__ = ["ReportContent", "ScheduleSummary", "SpecimenSeries", "default_report_path", "gather",
           "series_from_runs", "specimen_series", "write_report", "write_series_report"]

SUFFIX = ".report.pdf"


def default_report_path(path: str | Path, run_file: bool) -> Path:
    """Beside a foamlab run file; for any other file (a vendor export) the current folder:
    a report is never written beside files that are not foamlab's."""
    path = Path(path)
    name = f"{path.stem}{SUFFIX}"
    return path.with_name(name) if run_file else Path.cwd() / name


def _check_out(out: Path) -> Path:
    if out.suffix.lower() != ".pdf":
        raise FoamlabError(f"{out}: the report is a PDF; give a file name ending in .pdf")
    if out.is_dir():
        raise FoamlabError(f"{out}: is a folder; give a file name ending in .pdf")
    if not out.parent.is_dir():
        raise FoamlabError(f"{out.parent}: no such folder")
    return out


def write_report(path: str | Path, out: str | Path, analysis=None, *, method=None, fit: bool = True,
                 diagnose: bool = True, store: bool = True, series: SpecimenSeries | None = None,
                 progress=None) -> Path:
    """Write the test report of the run in `path` to the PDF `out`; returns `out`.

    analysis: the pipeline's Analysis of this run when the caller has one (the window): its
    stages are used and the missing ones completed; else the run is read and analysed here.
    method: overrides the run's own (a name in configs/methods or a .toml path). fit / diagnose:
    False leaves those sections saying so. store: write new sidecars beside a foamlab run file.
    series: a SpecimenSeries this run belongs to, shown as a table at the end.
    progress: the pipeline's progress(stage, fraction). A window whose diagnosis is still running
    passes diagnose=False (else the run is diagnosed here, in the caller's thread).
    """
    out = _check_out(Path(out))
    content = gather(path, analysis, method=method, fit=fit, diagnose=diagnose, store=store, progress=progress)
    if not fit:
        content.analysis.fit_error = content.analysis.fit_error or "not asked for (--no-fit)"
    if fit and not diagnose and content.analysis.diagnosis is None:
        content.analysis.diagnosis_error = content.analysis.diagnosis_error or "not asked for (--no-diagnose)"
    with tempfile.TemporaryDirectory(prefix="foamlab-report-") as tmp:
        folder = Path(tmp)
        doc = _document(content)
        _story(doc, content, folder)
        if series is not None:
            sections.series_table(doc, series)
        return doc.write(out)


def _document(c: ReportContent) -> Document:
    label = c.run.specimen.label
    return Document(title=f"foamlab test report: {c.path.name}",
                    footer=f"{c.path.name}  SHA-256 {c.sha256}",
                    subject=f"compression test of {label or c.path.name}; run file SHA-256 {c.sha256}")


def _story(doc: Document, c: ReportContent, folder: Path) -> None:
    label = c.run.specimen.label
    doc.paragraph(text(f"Compression test report{': ' + label if label else ''}"), "title")
    doc.paragraph(text(f"{c.path.name}, made by {c.software}; the SHA-256 below ties this report to the "
                       "run file (sha256sum FILE prints it)."), "small")
    sections.run_file(doc, c)
    sections.specimen(doc, c)
    sections.method(doc, c)
    sections.machine(doc, c)
    sections.curves(doc, figures.curves(c.run, folder, c.notes))
    sections.results(doc, c)
    f = c.analysis.fit
    sections.fit(doc, c, figures.fit(f, folder, c.notes) if f is not None else None)
    sections.forecast(doc, c)
    d = c.diagnosis_dict
    png, caption = (figures.diagnosis(c.analysis.diagnosis, f, d.get("verdict", ""), folder, c.notes)
                    if d is not None else (None, ""))
    sections.diagnosis(doc, c, png, caption)
    sections.schedule(doc, c)
    sections.notes(doc, c)


def write_series_report(series: SpecimenSeries, out: str | Path) -> Path:
    """A PDF of the series: the method, each specimen's file and SHA-256, the results table
    with the series statistics, the specimens' curves."""
    from foamlab.reporting.content import sha256_of  # noqa: PLC0415

    out = _check_out(Path(out))
    m = series.method
    doc = Document(title=f"foamlab specimen series: {m.name}", footer=f"specimen series, method {m.name}",
                   subject=f"{len(series)} specimens tested with {m.name}")
    doc.paragraph(text(f"Specimen series: {m.title}"), "title")
    doc.heading("Method")
    doc.fields([("method", f"{m.name}: {m.title}")] + ([("reference", m.reference)] if m.reference else [])
               + [("steps" if i == 0 else "", line) for i, line in enumerate(sections.steps_text(m))])
    doc.heading("Files")
    doc.table(["", "specimen", "file", "started", "SHA-256"],
              [[str(i), s.label, s.path.name, (s.run.started_at or "-")[:16].replace("T", " "), sha256_of(s.path)]
               for i, s in enumerate(series.specimens, 1)], [0.04, 0.1, 0.2, 0.15, 0.51], mono=(4,))
    sections.series_table(doc, series, list_files=False)
    with tempfile.TemporaryDirectory(prefix="foamlab-series-") as tmp:
        png = Path(tmp) / "series.png"
        doc.figure(figures.series_curves(series, png), "Force against displacement of every specimen.")
        return doc.write(out)
