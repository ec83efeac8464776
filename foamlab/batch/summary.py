"""An archive at a glance: one HTML page (PNG figures inside it) from a batch's table.

Verdict counts, the distributions of the fit's quality and of the model's parameters, the
parameters against the test date (or against the specimen series when the files carry no
date), and the runs whose verdict differs from the verdict most runs of their series got.

A run's series is its specimen label without the trailing run number ("PU45-03" -> "PU45");
a file without a label is in the series of its folder.
"""

from __future__ import annotations

import base64
import html
import io
import re
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from foamlab import FoamlabError
from foamlab.batch.rows import PARAMETER_PREFIX

#: Parameters shown first when the runs have them (elastic stiffness, first damping mode, first
#: residual term of cycle 1); others follow up to MAX_PARAMETERS.
PREFERRED = ("k1", "k2", "a1", "alpha1_re", "r1_1", "beta1_1")
MAX_PARAMETERS = 6
_RUN_NUMBER = re.compile(r"^(.*?)[\s_\-#./]*\d+$")


def series_of(table: pd.DataFrame) -> pd.Series:
    """The specimen series of each row (see the module docstring)."""
    def one(label, file) -> str:
        label = "" if not isinstance(label, str) else label.strip()
        if label:
            m = _RUN_NUMBER.match(label)
            return m.group(1) if m and m.group(1) else label
        return Path(str(file)).parent.name or "(no series)"
    return pd.Series([one(s, f) for s, f in zip(table["specimen"], table["file"])], index=table.index)


def odd_ones_out(table: pd.DataFrame) -> pd.DataFrame:
    """Diagnosed runs whose verdict is not their series' usual one: the verdict of more than
    half of the series' diagnosed runs (series of >= 3 such runs; no majority, no usual verdict)."""
    done = table[table["verdict"].fillna("").astype(str) != ""].copy()
    done["series"] = series_of(done) if len(done) else []
    usual = done.groupby("series")["verdict"].agg(_majority)
    done["series_verdict"] = done["series"].map(usual) if len(done) else []
    keep = (done["series_verdict"] != "") & (done["verdict"] != done["series_verdict"])
    return done[keep]


def _majority(verdicts: pd.Series) -> str:
    counts = verdicts.value_counts()
    return str(counts.index[0]) if len(verdicts) >= 3 and counts.iloc[0] > len(verdicts) / 2 else ""


def write_summary(table: pd.DataFrame, path: str | Path, title: str = "foamlab batch") -> Path:
    """Write the page; returns its path."""
    path = Path(path)
    figures = [("Verdicts", _verdicts(table)), ("Fit quality and parameters", _distributions(table)),
               ("Parameters over the archive", _trends(table))]
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", _counts_html(table)]
    for heading, fig in figures:
        if fig is not None:
            parts.append(f"<h2>{heading}</h2><img alt='{heading}' src='data:image/png;base64,{_png(fig)}'>")
    parts.append(_odd_html(odd_ones_out(table)))
    parts.append(_errors_html(table))
    parts.append("</body></html>")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(parts), encoding="utf-8")
    except OSError as exc:
        raise FoamlabError(f"{path}: cannot write the summary ({exc.strerror or exc})") from None
    return path


def _png(fig: Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _verdicts(table: pd.DataFrame) -> Figure | None:
    counts = _verdict_counts(table)
    if counts.empty:
        return None
    fig = Figure(figsize=(7, 0.4 * len(counts) + 1.2), layout="constrained")
    ax = fig.add_subplot()
    ax.barh(counts.index[::-1], counts.values[::-1], color="tab:blue")
    ax.set_xlabel("runs")
    return fig


def _verdict_counts(table: pd.DataFrame) -> pd.Series:
    verdict = table["verdict"].fillna("").astype(str)
    verdict = verdict.where(verdict != "", "(error: " + table["error_kind"].fillna("").astype(str) + ")")
    return verdict.value_counts()


def _parameters(table: pd.DataFrame) -> list[str]:
    cols = [c for c in table.columns if c.startswith(PARAMETER_PREFIX)
            and table[c].notna().sum() >= 2 and np.nanstd(table[c].astype(float)) > 0]
    preferred = [PARAMETER_PREFIX + p for p in PREFERRED if PARAMETER_PREFIX + p in cols]
    return (preferred + [c for c in cols if c not in preferred])[:MAX_PARAMETERS]


def _quantities(table: pd.DataFrame) -> list[tuple[str, pd.Series]]:
    out = [("RMSE / noise", table["rmse"].astype(float) / table["noise"].astype(float)),
           ("gain of the top finding", table["gain"].astype(float))]
    out += [(c[len(PARAMETER_PREFIX):], table[c].astype(float)) for c in _parameters(table)]
    return [(name, v) for name, v in out if np.isfinite(v).sum() >= 1]


def _distributions(table: pd.DataFrame) -> Figure | None:
    items = _quantities(table)
    if not items:
        return None
    cols = 4
    rows = -(-len(items) // cols)
    fig = Figure(figsize=(12, 2.6 * rows), layout="constrained")
    for i, (name, values) in enumerate(items):
        ax = fig.add_subplot(rows, cols, i + 1)
        ax.hist(values[np.isfinite(values)], bins=min(20, max(5, int(np.isfinite(values).sum()))))
        ax.set_title(name, fontsize=9)
    return fig


def _trends(table: pd.DataFrame) -> Figure | None:
    items = [(n, v) for n, v in _quantities(table) if n != "gain of the top finding"]
    if not items or table.empty:
        return None
    dates = pd.to_datetime(table["started_at"].where(table["started_at"].astype(str) != ""),
                           errors="coerce", utc=True)
    by_date = dates.notna().sum() >= 2
    x = dates if by_date else series_of(table)
    series = series_of(table)
    groups = list(series[table["rmse"].notna()].value_counts().index[:10]) if by_date else [None]  # 10 largest
    cols = 3
    rows = -(-len(items) // cols)
    fig = Figure(figsize=(12, 2.8 * rows), layout="constrained")
    for i, (name, values) in enumerate(items):
        ax = fig.add_subplot(rows, cols, i + 1)
        for group in groups:
            keep = np.isfinite(values) & (x.notna() if by_date else True) & \
                (series == group if group is not None else True)
            ax.plot(x[keep], values[keep], "o", ms=4, alpha=0.7, label=group)
        ax.set_title(f"{name} against {'test date' if by_date else 'specimen series'}", fontsize=9)
        ax.tick_params(axis="x", labelrotation=30, labelsize=7)
        if by_date and i == 0:
            ax.legend(fontsize=7, title="series", title_fontsize=7)
    return fig


def _counts_html(table: pd.DataFrame) -> str:
    counts = _verdict_counts(table)
    rows = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{v}</td></tr>" for k, v in counts.items())
    return (f"<p>{len(table)} runs, {int((table['error'].fillna('') != '').sum())} with an error.</p>"
            f"<table><tr><th>verdict</th><th>runs</th></tr>{rows}</table>")


def _odd_html(odd: pd.DataFrame) -> str:
    if odd.empty:
        return "<h2>Runs unlike their series</h2><p>none: every run has its series' usual verdict.</p>"
    rows = "".join(f"<tr><td>{html.escape(str(r.file))}</td><td>{html.escape(str(r.series))}</td>"
                   f"<td>{html.escape(str(r.verdict))}</td><td>{html.escape(str(r.series_verdict))}</td></tr>"
                   for r in odd.itertuples())
    return ("<h2>Runs unlike their series</h2><table><tr><th>file</th><th>series</th><th>verdict</th>"
            f"<th>series' usual verdict</th></tr>{rows}</table>")


def _errors_html(table: pd.DataFrame) -> str:
    bad = table[table["error"].fillna("").astype(str) != ""]
    if bad.empty:
        return ""
    rows = "".join(f"<tr><td>{html.escape(str(r.file))}</td><td>{html.escape(str(r.error))}</td></tr>"
                   for r in bad.itertuples())
    return f"<h2>Runs with an error</h2><table><tr><th>file</th><th>error</th></tr>{rows}</table>"
