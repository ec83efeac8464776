"""`foamlab series PATH...`: specimens tested with one method, their results and statistics."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "results of several specimens tested with one method, with mean, sd and cv (CSV, PDF)"

EXAMPLES = """\
examples:
  foamlab series A1.csv A2.csv A3.csv                    # the table (one line per result) on the terminal
  foamlab series data/*_iso3386-1.csv --out series.csv   # one row per specimen + n, mean, sd, cv rows
  foamlab series A*.csv --pdf series.pdf                 # the table and the specimens' curves as a PDF
  foamlab series export1.csv export2.csv --method paper-3cycle

Every file must have been tested with one method (the run files record it); exports record
none: give it with --method. sd is the sample standard deviation (n - 1), cv = sd / |mean|.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "series", help=HELP,
        description=("A specimen series, as Bluehill and testXpert keep one: the method's results of "
                     "each specimen (hysteresis loss, energies, residual strain, CV40, CFD, ...) and "
                     "per result the series' mean, standard deviation and coefficient of variation. "
                     "PATH is a foamlab run file, a plain CSV, a Bluehill or a testXpert export."),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", metavar="PATH", help="data files, one per specimen")
    p.add_argument("--method", metavar="METHOD",
                   help="test method (name in configs/methods or a .toml path; default: the files' own)")
    p.add_argument("--out", metavar="FILE.csv", help="write the series as CSV (units in the header)")
    p.add_argument("--pdf", metavar="FILE.pdf", help="write the series report as PDF")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from foamlab.reporting import specimen_series, write_series_report  # noqa: PLC0415

    series = specimen_series(args.paths, args.method)
    print(format_table(series))
    if args.out:
        print(f"series: {series.write_csv(Path(args.out)).resolve()}")
    if args.pdf:
        print(f"report: {write_series_report(series, args.pdf).resolve()}")
    for s in series.specimens:
        if s.error:
            print(f"foamlab series: {s.path.name}: no results: {s.error}")
    return 0


def format_table(series) -> str:
    """One line per result (a method has a dozen; specimens are columns), then the statistics."""
    from foamlab.reporting.series import unit_text  # noqa: PLC0415

    head = ["result", "unit"] + [s.label for s in series.specimens] + ["n", "mean", "sd", "cv %"]
    rows = [head]
    for st in series.statistics:
        c = st.column
        rows.append([c.title, unit_text(c.unit)] + [_cell(s.value(c)) for s in series.specimens]
                    + [str(st.n), _cell(st.mean), _cell(st.sd), _cell(st.cv_percent)])
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = [f"method {series.method.name}: {len(series)} specimens ("
             + ", ".join(f"{s.label}: {s.path.name}" for s in series.specimens) + ")"]
    for row in rows:
        cells = [cell.ljust(w) if i < 2 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths, strict=True))]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines)


def _cell(v) -> str:
    return "-" if v is None else f"{v:.4g}"
