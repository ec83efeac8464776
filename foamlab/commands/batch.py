"""`foamlab batch PATH...`: an archive of runs fitted and diagnosed on Dask distributed."""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from foamlab import FoamlabError

HELP = "fit and diagnose every run under the paths on Dask (local processes or a cluster)"

EXAMPLES = """\
examples:
  foamlab batch archive/ --out results.parquet           # one row per run; summary in results.summary.html
  foamlab batch archive/ --out results.csv --workers 8   # a LocalCluster of 8 processes
  foamlab batch /shared/archive --scheduler tcp://head:8786 --out results.parquet   # a running cluster
  foamlab batch a.csv b.csv > table.csv                  # no --out: the table on stdout

Run it again with the same --out to go on: runs whose content (SHA-256) already has a result
are skipped. Results are journalled as they arrive (<out>.journal.jsonl), so a batch that is
interrupted, or whose worker dies, loses nothing already done. See docs/batch.md.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help=HELP,
        description=("Every run under the paths (folders are searched for .csv, .txt and .tsv files; "
                     "any format foamlab reads) is fitted and diagnosed by the same pipeline as "
                     "`foamlab run`, one Dask task per run, on a LocalCluster of worker processes or "
                     "on the cluster at --scheduler. One row per run (file, SHA-256, format, cycles, "
                     "samples, orders, RMSE, noise, verdict, gain, time, error); a file that cannot be "
                     "read is a row with its error. Runs are also indexed in the SQLite catalog."),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", metavar="PATH", help="run files or folders of them")
    p.add_argument("--out", metavar="FILE", help="the table: FILE.parquet or FILE.csv (default: CSV on stdout)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--summary", metavar="OUT.html",
                   help="the archive summary page (default with --out: <out>.summary.html beside it)")
    p.add_argument("--catalog", metavar="FILE",
                   help="catalog of runs that are not foamlab run files (default: catalog.sqlite beside --out)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (there is none on a pipe)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from foamlab.batch import process, write_summary  # noqa: PLC0415 (keep `foamlab --help` fast)

    if args.workers is not None and args.workers < 1:
        raise FoamlabError(f"--workers {args.workers}: need at least 1")
    if args.workers is not None and args.scheduler:
        raise FoamlabError("--workers sizes the local cluster; the cluster at --scheduler has its own workers")
    summary = Path(args.summary) if args.summary else None
    if summary is None and args.out:
        summary = Path(args.out).with_name(Path(args.out).stem + ".summary.html")
    with _progress(not args.quiet and sys.stderr.isatty()) as on_row:
        table = process(args.paths, out=args.out, catalog=args.catalog, scheduler=args.scheduler,
                        workers=args.workers, on_row=on_row)
    if summary is not None:
        write_summary(table, summary, title=f"foamlab batch: {', '.join(args.paths)}")
    errors = int((table["error"] != "").sum()) if len(table) else 0
    ok = len(table) - errors
    lines = [f"{len(table)} runs: {ok} result{'s' * (ok != 1)}, {errors} error row{'s' * (errors != 1)}"]
    lines += [f"{what}: {p}" for what, p in (("table", args.out), ("summary", summary)) if p]
    if args.out:
        print("\n".join(lines))
    else:
        table.to_csv(sys.stdout, index=False)
        print("\n".join(lines), file=sys.stderr)
    return 0


@contextlib.contextmanager
def _progress(show: bool):
    """on_row for process(): a rich progress bar on a terminal, nothing otherwise."""
    if not show:
        yield None
        return
    from rich.console import Console  # noqa: PLC0415
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn  # noqa: PLC0415

    with Progress(TextColumn("batch"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  TextColumn("{task.description}"), console=Console(stderr=True), transient=False) as bar:
        task = bar.add_task("", total=None)

        def on_row(row, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total, description=row.verdict or row.error_kind or "")
        yield on_row
