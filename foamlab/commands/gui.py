"""`foamlab gui`: the technician's window (PySide6 + pyqtgraph)."""

from __future__ import annotations

import argparse

EXAMPLES = """\
examples:
  foamlab gui                         # built-in simulated machine, real time
  foamlab gui --speedup 20            # the simulated machine's clock runs 20x faster
  foamlab gui --machine sim-serial    # preselect a machine profile (configs/machines/)
  foamlab gui --open run.csv          # show a measured file (Bluehill, testXpert, plain CSV)
  foamlab gui --speedup 8 --effect cycle_softening=0.1   # a specimen the live prediction catches
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "gui",
        help="open the technician's window: connect, run a test, watch it, see the fit",
        description=("Open the desktop window: choose the machine (the built-in simulated machine needs no "
                     "setup), connect, pick a method, enter the specimen, Start, watch the curves grow, "
                     "then see the fitted model, its statistics and the diagnosis. Past runs and measured "
                     "files can be opened too."),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--speedup", type=float, default=1.0, metavar="S",
                   help="the machine clock's rate, as `foamlab run --speedup` (default 1: real time, as a "
                        "real machine runs): the built-in simulated machine runs this fast, and a profile "
                        "served by `foamlab sim --speedup S` needs the same S")
    p.add_argument("--machine", metavar="PROFILE", help="machine profile preselected in the window")
    p.add_argument("--method", metavar="METHOD", help="test method preselected (configs/methods/)")
    p.add_argument("--out", metavar="DIR", help="data folder (default $FOAMLAB_DATA or ~/foamlab-data)")
    p.add_argument("--open", metavar="FILE", dest="open_path", help="measured file to show at start")
    p.add_argument("--effect", action="append", default=[], metavar="NAME=MAG",
                   help="hide an effect in the built-in simulated machine's specimen (repeatable), "
                        "e.g. cycle_softening=0.1")
    p.add_argument("--seed", type=int, default=0, help="seed of the built-in machine's noise (default 0)")
    p.set_defaults(func=run)


def run(args) -> int:
    from foamlab.commands.run import data_dir
    from foamlab.commands.sim import parse_effects
    from foamlab.gui.app import run_gui

    simulator = {"seed": args.seed, "effects": parse_effects(args.effect) or None}
    return run_gui(speedup=args.speedup, out_dir=data_dir(args.out), profile=args.machine,
                   method=args.method, open_path=args.open_path, simulator=simulator)
