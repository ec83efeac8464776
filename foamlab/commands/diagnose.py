"""`foamlab diagnose PATH...`: what the simulation gets wrong, the likely cause, the gain."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace

from foamlab import FoamlabError
from foamlab.commands.progress import terminal_progress

HELP = "find what the model gets wrong on measured data, name the likely cause, measure the gain"

EXAMPLES = """\
examples:
  foamlab diagnose run.csv                          # verdict, findings with their gains, where the model misses
  foamlab diagnose Specimen_RawData_6.csv --json    # {"verdict": ..., "findings": [{"effect", "gain": {...}}, ...]}
  foamlab diagnose slow.csv fast.csv                # runs of one specimen at two speeds (rate_dependence)
  foamlab diagnose run.csv --report out/            # out/index.html with the figures
  foamlab diagnose run.csv --full                   # ...and the thresholds it decided by
  foamlab diagnose run.csv --linearised-limits      # the verdict sooner; limits not checked by refits, marked so
  foamlab diagnose run.csv --suggest                # a close call? the next test, as ./suggested-run.toml
  foamlab diagnose run.csv --suggest next.toml      # ...written to next.toml; then: foamlab run --method next.toml

verdict: a cause of the catalogue (cycle_softening, damping_cycle_change, channel_lag,
force_zero_drift, machine_compliance, direction_friction, memory_lag, rate_dependence), 'none' (the
model explains the data down to the noise) or 'unexplained' (structure no cause explains).
gain: RMSE before/after the extension, on all data and on held-out blocks, and delta BIC.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose", help=HELP,
        description=("Fit the paper's model to the run(s), simulate them, study the residuals (by "
                     "cycle, half-cycle, displacement and time, against the noise level of the data "
                     "itself), fit each candidate cause as an extension of the model, and name the "
                     "one that explains the residuals -- only if it passes a nested-model test "
                     "(prewhitened delta BIC) and predicts held-out blocks of the run better. "
                     "PATH is a foamlab run file, a plain CSV (time_s,displacement_mm,force_N), an "
                     "Instron Bluehill or a ZwickRoell testXpert export; several PATHs are runs of "
                     "one specimen (e.g. at different speeds, the first is the reference)."),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", metavar="PATH", help="data file(s) of the run(s)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object: verdict and findings (best first; effect, gain)")
    p.add_argument("--full", action="store_true",
                   help="also print the thresholds the diagnosis decided by (docs/settings.md)")
    p.add_argument("--report", metavar="DIR", help="write an HTML report with figures into DIR")
    p.add_argument("--causes", metavar="NAME[,NAME...]",
                   help="test only these causes (default: all, as listed under 'verdict' below)")
    p.add_argument("--no-store", action="store_true",
                   help="do not write <run>.diagnosis.json beside a foamlab run file or index it")
    p.add_argument("--form", choices=("auto", "causal", "paper"), default="auto",
                   help="the base model's residual form (see foamlab fit --form); a form named here is "
                        "checked against the other, which is a finding of its own when the data follow it")
    p.add_argument("--out", metavar="DIR",
                   help="keep <run>.diagnosis.json in this folder (for an imported export nothing is "
                        "written unless --out is given)")
    p.add_argument("--suggest", nargs="?", const="", metavar="FILE",
                   help="when two causes are close (Delta BIC within 10, or both partial) or one needs another "
                        "run (rate_dependence), rank the tests that would tell them apart and write the best "
                        "as a method file for `foamlab run --method` (default ./suggested-<run>.toml, never "
                        "overwriting: numbered instead)")
    p.add_argument("--linearised-limits", action="store_true",
                   help="report what the run could have seen from the slope at the base alone, without the "
                        "identification refits that check it where nothing is named (most of a clean run's "
                        "diagnosis); the limits of causes the base can hold are then marked unchecked")
    p.add_argument("--workers", type=_workers, default=0, metavar="N",
                   help="processes the search's fits run on (default 0: every core; 1: this process only). "
                        "The verdict and its figures are the same at any N")
    p.set_defaults(func=run)


def _workers(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of processes (0: every core)")
    return n


def _causes(text: str | None) -> list[str] | None:
    from foamlab.diagnosis.causes import CAUSES  # noqa: PLC0415

    if not text:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in CAUSES]
    if unknown or not names:
        raise FoamlabError(f"--causes: unknown cause(s) {', '.join(unknown) or '(none given)'} "
                           f"(known: {', '.join(CAUSES)})")
    return names


def run(args: argparse.Namespace) -> int:
    from foamlab.diagnosis import diagnose  # noqa: PLC0415 (keep `foamlab --help` fast)
    from foamlab.diagnosis.settings import DEFAULT  # noqa: PLC0415
    from foamlab.importers import load_run  # noqa: PLC0415

    causes = _causes(args.causes)
    if args.suggest and not args.suggest.endswith(".toml"):
        # `--suggest data.csv` would overwrite the data: a method file is a .toml
        raise FoamlabError(f"--suggest {args.suggest}: the method file must end in .toml "
                           "(put --suggest after the data paths)")
    runs = [load_run(p) for p in args.paths]
    with terminal_progress("diagnose", quiet=args.json) as report:
        result = diagnose(runs, causes=causes, progress=report, form=args.form,
                          settings=replace(DEFAULT, workers=args.workers,
                                           limit_injections=0 if args.linearised_limits else DEFAULT.limit_injections))
    obj = result.to_dict()
    notes: list[str] = []
    suggestion = None
    if args.suggest is not None:
        suggestion = _suggest(result, runs, args.suggest)
        obj["suggestion"] = suggestion.to_dict()
    if args.report:
        from foamlab.diagnosis.report import write_report  # noqa: PLC0415
        page = write_report(result, args.report, title=", ".join(args.paths))
        notes.append(f"report: {page}")
    if not args.no_store and len(args.paths) == 1:
        from foamlab.diagnosis.store import store_diagnosis  # noqa: PLC0415
        try:
            stored = store_diagnosis(obj, args.paths[0], args.out)
            if stored.path is not None:
                notes.append(f"stored: {stored.path}" + (f" (catalog {stored.catalog})" if stored.catalog
                                                          else f" ({stored.note})"))
        except FoamlabError as exc:        # the diagnosis itself is fine: say so, do not fail
            notes.append(f"not stored: {exc}")
    if args.json:
        print(json.dumps(obj, indent=1))
        for note in notes:
            print(f"foamlab diagnose: {note}", file=sys.stderr)
    else:
        print(summary(result))
        if args.full:
            print("settings (foamlab.diagnosis.settings; why each: docs/settings.md):")
            print("\n".join("  " + line for line in result.settings.lines()))
        if suggestion is not None:
            print("\n".join(suggestion.lines()))
        for note in notes:
            print(note)
    return 0


def _suggest(result, runs, where: str):
    """The next test (foamlab.diagnosis.suggest), its method written to `where` ('' = the default)."""
    from foamlab.diagnosis.suggest import default_path, suggest

    s = suggest(result, runs[0].specimen.height_mm)
    if s.made:
        path = where or default_path(result.series[0].name)
        try:
            s.write(path)
        except OSError as exc:
            raise FoamlabError(f"--suggest: cannot write {path}: {exc.strerror or exc}") from None
    return s


def summary(d) -> str:
    lines = [f"verdict: {d.verdict}",
             f"noise level (from the data): {d.noise_sigma:.4g} N; base model RMSE {d.base.rmse:.4g} N",
             f"base model: {d.base_form_reason}",
             f"  {d.base_analysis.miss().sentence()}"]
    if d.form_finding is not None:
        lines.append(f"  {d.form_finding.description()}")
    if d.findings:
        lines.append("findings (best first):")
        lines.append(f"  {'effect':<22}{'RMSE':>17}{'held-out RMSE':>21}{'dBIC':>10}  fitted")
        for c in d.findings:
            g = c.gain()
            lines.append(f"  {c.name:<22}{g['rmse_before']:>8.4g} ->{g['rmse_after']:>7.4g}"
                         f"{g['heldout_rmse_before']:>11.4g} ->{g['heldout_rmse_after']:>7.4g}"
                         f"{g['delta_bic']:>10.1f}  {c.description()}")
        lines.append(f"  {d.findings[0].name}: {d.findings[0].cause.meaning}")
    elif d.verdict == "none":
        lines.append("the model explains the data down to the noise (white residuals, no cause passes)")
    if d.verdict == "unexplained" or (d.findings and d.final_analysis.where()):
        where = d.final_analysis.where()
        if where:
            lines.append("structure left:" if d.findings else "structure no cause explains:")
            lines += [f"  {w}" for w in where]
    if d.limits:
        lines.append("what this run could have seen (the smallest size named in 90 % of runs like it):")
        lines += [f"  {limit.text}" for limit in d.limits]
    if d.skipped:
        lines += [f"not tested: {name} ({why})" for name, why in d.skipped.items()]
    return "\n".join(lines)
