"""`foamlab probe`: commission a machine profile on the real device before its first run."""

from __future__ import annotations

import argparse
import sys

from foamlab import FoamlabError

EXAMPLES = """\
examples:
  foamlab probe --machine my-stand.toml                    # read every channel, check formats and units
  foamlab probe --machine my-stand.toml --move             # ...and, when you confirm, 1 mm up and back
  foamlab probe --machine dad141-cs2rs-rtu --port-url /dev/ttyUSB0 --move --yes   # a script, no question

Exit status: 0 every check passed (remembered on this computer: `foamlab run` then needs no
confirmation for this profile), 1 a check failed (each said on its own line), 2 bad input.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "probe",
        help="commission a machine profile: identify the device, read every channel, check units and limits",
        description=("Connect to the machine a profile describes, let the device identify itself where its "
                     "protocol can, read every channel once, check reply formats, units and settings against "
                     "the profile, write the travel limits and read them back, and - with --move and your "
                     "confirmation - move the crosshead 1 mm up and back while watching force and position."),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--machine", required=True, metavar="PROFILE",
                   help="machine profile (name in configs/machines or a .toml path)")
    p.add_argument("--host", help="override the profile's host (Modbus TCP)")
    p.add_argument("--port", type=int, help="override the profile's TCP port")
    p.add_argument("--port-url", metavar="URL", help="override the profile's serial port (device path or pyserial URL)")
    p.add_argument("--move", action="store_true", help="also move the crosshead 1 mm up and back (asks first)")
    p.add_argument("--yes", action="store_true", help="do not ask before moving (scripts; you are at the machine)")
    p.set_defaults(func=run)


def _confirm(question: str) -> bool:
    if not sys.stdin.isatty():
        raise FoamlabError("--move needs a confirmation: answer at a terminal, or add --yes")
    answer = input(f"{question} [y/N] ").strip().lower()
    return answer in ("y", "yes")


def run(args) -> int:
    from drivers.profile import ProfileError, load_profile, open_machine
    from foamlab.acquisition.commissioning import probe
    from foamlab.acquisition.safety import Limits
    from foamlab.storage.probes import record_passed

    try:
        profile = load_profile(args.machine)
        machine = open_machine(profile, connect=False, host=args.host, port=args.port, port_url=args.port_url)
    except ProfileError as exc:
        raise FoamlabError(str(exc)) from None
    confirm = None
    if args.move:
        confirm = (lambda question: True) if args.yes else _confirm
    try:
        report = probe(machine, machine.profile, Limits.from_profile(profile), confirm_move=confirm)
    finally:
        machine.close()
    print(report.text())
    if not report.passed:
        return 1
    where = record_passed(profile)
    print(f"remembered in {where}: `foamlab run --machine {args.machine}` will not ask again until the profile changes")
    return 0
