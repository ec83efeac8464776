"""`foamlab report RUN`: the test report a lab archives, as a PDF."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "write the test report of a run as a PDF (method, specimen, curves, results, fit, diagnosis, SHA-256)"

EXAMPLES = """\
examples:
  foamlab report ~/foamlab-data/20250101-101200_B7_paper-3cycle.csv     # -> ..._paper-3cycle.report.pdf beside it
  foamlab report Specimen_RawData_6.csv --out 22L3.pdf --method paper-3cycle
  foamlab report run.csv --no-diagnose                                 # fit only (a diagnosis takes ~10 s)

Where the PDF goes: --out, else beside a foamlab run file (<run>.report.pdf); for any other
file (a vendor export) in the current folder, never beside files foamlab did not write.
The fit and the diagnosis stored beside a run file are used when they are current (the
diagnosis is not made again); otherwise the run is fitted once and diagnosed with that fit,
and the new files are stored beside the run file (--no-store: not).
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help=HELP,
        description=("Write a PDF test report of a run: run file and its SHA-256 (on every page), "
                     "specimen, method, machine profile, force-displacement and force-time curves, the "
                     "method's results, the fitted model with its Table-5 statistics and the parameters "
                     "the data determine, the diagnosis with its gain table, the schedule statistics. "
                     "RUN is a foamlab run file, a plain CSV, an Instron Bluehill or a ZwickRoell "
                     "testXpert export. Several specimens of one method: foamlab series."),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("path", metavar="RUN", help="data file of the run")
    p.add_argument("--out", metavar="FILE.pdf", help="where to write the PDF (default: see below)")
    p.add_argument("--method", metavar="METHOD",
                   help="test method for the results (name in configs/methods or a .toml path; "
                        "default: the one the run file records)")
    p.add_argument("--no-fit", action="store_true", help="no fit and no diagnosis in the report")
    p.add_argument("--no-diagnose", action="store_true", help="no diagnosis in the report")
    p.add_argument("--no-store", action="store_true",
                   help="do not store a fit or diagnosis made now beside the run file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from foamlab import FoamlabError  # noqa: PLC0415
    from foamlab.reporting import default_report_path, write_report  # noqa: PLC0415 (keep --help fast)
    from foamlab.storage.runfile import is_run_file  # noqa: PLC0415

    path = Path(args.path)
    if not path.is_file():
        raise FoamlabError(f"{path}: {'is a folder' if path.is_dir() else 'no such file'}")
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            ours = is_run_file(fh.readline())
    except OSError as exc:
        raise FoamlabError(f"{path}: cannot read ({exc.strerror or exc})") from None
    out = Path(args.out) if args.out else default_report_path(path, ours)
    written = write_report(path, out, method=args.method, fit=not args.no_fit,
                           diagnose=not (args.no_fit or args.no_diagnose), store=not args.no_store,
                           progress=Stages())
    print(f"report: {written.resolve()}")
    return 0


class Stages:
    """Says which slow stage is under way (the fit: ~1 s; a diagnosis: ~10 s), once each."""

    SAY = {"fit": "fitting the model...", "diagnosis": "diagnosing the run (--no-diagnose skips it)..."}

    def __init__(self) -> None:
        self.said: set[str] = set()

    def __call__(self, stage: str, fraction: float) -> None:
        top = stage.split(":", 1)[0]
        if top in self.SAY and top not in self.said:
            self.said.add(top)
            print(self.SAY[top], flush=True)
