"""`foamlab fit PATH`: identify the model's parameters from a measured run."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from foamlab import FoamlabError
from foamlab.commands.progress import terminal_progress

HELP = "identify the model's parameters from a run (paper's three steps + joint refinement)"

EXAMPLES = """\
examples:
  foamlab fit run.csv                         # short: fit quality, determined parameters, main warnings
  foamlab fit run.csv --full                  # the whole report: Table-5 statistics, every parameter, checks, warnings
  foamlab fit Specimen_RawData_6.csv --json   # one JSON object (parameters, statistics, rmse, constraints)
  foamlab fit run.csv --plot fit.png          # measured vs fitted per cycle, residuals below
  foamlab fit run.csv --orders 2,3,7          # force N damping modes, M residual terms per cycle, P elastic order
  foamlab fit run.csv --orders paper          # the paper's table: 3,3,7, every cycle its own terms
  foamlab fit run.csv --orders auto           # the structure the data determine (no cancelling terms)
  foamlab fit run.csv --compare 1,1,7 2,2,7 3,3,7   # AIC/BIC of several orders
  foamlab fit run.csv --form paper            # the residual as the paper prints it (Eqs. 20b-f)

The fit of a foamlab run file is stored beside it as <run>.fit.json (loadable as a simulator
specimen: foamlab sim --specimen <run>.fit.json) and indexed in the run catalog; --no-store
skips that. Nothing is written beside an imported export unless --out DIR names a folder.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit", help=HELP,
        description=("Fit the combined model (elastic polynomial, hereditary damping, fractional "
                     "residual force) to a run: the paper's three-step identification for start "
                     "values and its Table-5 statistics, then a joint refinement of all parameters on "
                     "the raw signal, with standard errors, correlations, warnings for parameters the "
                     "data do not determine, and the thermodynamic checks. PATH is a foamlab run file, "
                     "a plain CSV (time_s,displacement_mm,force_N), an Instron Bluehill or a "
                     "ZwickRoell testXpert export."),
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("path", metavar="PATH", help="data file of the run")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object: parameters (value, stderr), statistics per step "
                        "(sse, r2, adj_r2, rmse), rmse of the whole run, constraints")
    p.add_argument("--full", action="store_true",
                   help="print the whole report (Table-5 statistics, every parameter, checks, all warnings)")
    p.add_argument("--plot", metavar="OUT.png", help="draw measured vs fitted force per cycle, residuals below")
    p.add_argument("--orders", metavar="N,M,P[,C][,shared]|auto|paper", default=None,
                   help="the structure (default 3,3,7,3): damping modes N, residual terms per cycle M, elastic "
                        "order P, C cycles with residual terms of their own (later ones reuse the last's), "
                        "',shared': one order per term for every cycle; 'auto': the structure the data "
                        "determine (chosen from 3,3,7,3 down by BIC, every parameter determined, no cancelling "
                        "terms; several fits: 3-10 x the time); 'paper': 3,3,7 with every cycle's own terms "
                        "(the paper's table, any run length)")
    p.add_argument("--form", choices=("auto", "causal", "paper"), default="auto",
                   help="the residual force: 'causal' (Eq. 10, a memory of the history), 'paper' (each "
                        "cycle's Eq. 11 in x, in every later half-cycle, as Eqs. 20b-f print it) or "
                        "'auto' (default: both fitted, the one that predicts held-out blocks better kept)")
    p.add_argument("--free-orders", action="store_true",
                   help="fit every residual order free: do not hold orders whose terms coalesce apart (by "
                        "default they are held where that costs at most 10 in BIC; --full shows both fits)")
    p.add_argument("--compare", nargs="+", metavar="N,M,P",
                   help="fit each of these orders too and print their AIC/BIC (lower is better)")
    p.add_argument("--no-store", action="store_true",
                   help="do not write <run>.fit.json beside the run or index it in the catalog")
    p.add_argument("--out", metavar="DIR",
                   help="keep <run>.fit.json in this folder (for an imported export nothing is written "
                        "unless --out is given; a foamlab run file keeps its fit beside it)")
    p.set_defaults(func=run)



def run(args: argparse.Namespace) -> int:
    from foamlab.identification import Orders, fit_run  # noqa: PLC0415 (keep `foamlab --help` fast)
    from foamlab.importers import load_run  # noqa: PLC0415

    orders = None if not args.orders else (
        "auto" if args.orders.strip().lower() == "auto" else Orders.parse(args.orders))
    compare = [Orders.parse(o) for o in args.compare or []]
    run_data = load_run(args.path)
    with terminal_progress("fit", quiet=args.json) as report:
        result = fit_run(run_data, orders, progress=report, form=args.form, hold=not args.free_orders)
    notes: list[str] = []
    if not args.no_store:
        from foamlab.identification.store import store_fit  # noqa: PLC0415
        try:
            stored = store_fit(result, args.path, args.out)
            if stored.path is None:
                notes.append(f"not stored: {stored.note}")
            else:
                notes.append(f"stored: {stored.path}" + (f" (catalog {stored.catalog})" if stored.catalog
                                                          else f" ({stored.note})"))
        except FoamlabError as exc:       # the fit itself is fine: say so, do not fail
            notes.append(f"not stored: {exc}")
    if args.plot:
        from foamlab.identification.plot import plot_fit  # noqa: PLC0415
        plot_fit(result, Path(args.plot))
        notes.append(f"plot: {args.plot}")
    if args.json:
        print(result.to_json())
        for note in notes:
            print(f"foamlab fit: {note}", file=sys.stderr)
    else:
        print(result.summary() if args.full else result.brief())
        if args.full:
            from foamlab.identification.settings import DEFAULT  # noqa: PLC0415
            print("[[Settings]] (identification.settings)")
            print("\n".join(f"    {line}" for line in DEFAULT.lines()))
        for note in notes:
            print(note)
    if compare:
        first = result.orders
        _print_comparison(run_data, [first] + [o for o in compare if o != first], result,
                          sys.stderr if args.json else sys.stdout)
    return 0


def _print_comparison(run_data, orders_list, first, stream) -> None:
    from foamlab.identification.compare import compare_orders  # noqa: PLC0415

    rows = compare_orders(run_data, orders_list, known={orders_list[0]: first})
    print("[[Orders]] (information criteria on the raw signal; lower is better)", file=stream)
    print(f"    {'orders':<16}{'params':>7}{'RMSE':>10}{'AIC':>12}{'BIC':>12}", file=stream)
    for row in rows:
        print(f"    {str(row.orders):<16}{row.n_params:>7d}{row.rmse:>10.4g}{row.aic:>12.1f}{row.bic:>12.1f}"
              + ("   <- best BIC" if row.best else ""), file=stream)
