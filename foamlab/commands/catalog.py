"""`foamlab catalog [list|rebuild]`: the index of runs, fits and diagnoses."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "list the runs of a data folder, or rebuild its catalog from the files"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "catalog", help=HELP,
        description="The run catalog (<data dir>/catalog.sqlite) indexes run files, fits "
                    "(<run>.fit.json) and diagnoses (<run>.diagnosis.json). 'list' shows the runs "
                    "(new or changed files are indexed first); 'rebuild' forgets the index and "
                    "re-reads every file. The data dir is --data, else $FOAMLAB_DATA, else "
                    "~/foamlab-data.")
    parser.add_argument("action", nargs="?", choices=("list", "rebuild"), default="list",
                        help="list (default) or rebuild")
    parser.add_argument("--data", metavar="DIR", help="data folder (default: $FOAMLAB_DATA or ~/foamlab-data)")
    parser.add_argument("--json", action="store_true", help="print the runs as JSON (list)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from foamlab import FoamlabError  # noqa: PLC0415
    from foamlab.storage.catalog import Catalog, data_dir  # noqa: PLC0415

    folder = Path(args.data).expanduser() if args.data else data_dir()
    if not folder.is_dir():
        raise FoamlabError(f"{folder}: no such data folder (set --data or $FOAMLAB_DATA)")
    with Catalog.for_folder(folder, sync=False) as catalog:
        report = catalog.rebuild(folder) if args.action == "rebuild" else catalog.sync(folder)
        for path, why in report.skipped:
            print(f"skipped {path}: {why}")
        if args.action == "rebuild":
            print(f"catalog {catalog.path}: {report.runs} runs, {report.fits} fits, "
                  f"{report.diagnoses} diagnoses indexed"
                  + (f", {len(report.skipped)} files skipped" if report.skipped else ""))
            return 0
        runs = catalog.runs()
    if args.json:
        print(json.dumps([r.__dict__ for r in runs], ensure_ascii=False))
        return 0
    if not runs:
        print(f"no runs in {folder}")
        return 0
    header = f"{'started':25s} {'specimen':16s} {'method':16s} {'status':9s} {'samples':>8s} " \
             f"{'rmse':>8s} {'verdict':18s} file"
    print(header)
    for r in runs:
        rmse = f"{r.rmse:.4g}" if r.rmse is not None else "-"
        print(f"{r.started_at[:25]:25s} {r.specimen[:16]:16s} {r.method[:16]:16s} {r.status:9s} "
              f"{r.n_samples:>8d} {rmse:>8s} {(r.verdict or '-')[:18]:18s} {r.path}")
    return 0
