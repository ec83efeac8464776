"""`foamlab sim`: serve the simulated testing machine on a real wire protocol until stopped."""

from __future__ import annotations

import argparse
import math
import signal
import threading

from foamlab import FoamlabError

EXAMPLES = """\
examples:
  foamlab sim --transport modbus-tcp                 # Modbus TCP on 127.0.0.1:5020 (profile sim-modbus-tcp)
  foamlab sim --transport modbus-rtu --pty           # Modbus RTU on a pty; prints the device path
  foamlab sim --device mark10-esm303 --speedup 20    # Mark-10 ESM303 + Series 5 on a pty, 20x real time
  foamlab sim --transport modbus-tcp --port 0 --effect cycle_softening=0.1 --fault crc:p=0.01 --seed 3

faults (--fault, repeatable): NAME@T (once at virtual time T s), NAME@T+D (window of D s),
NAME:p=P (at random, probability P per request; physics faults per virtual second).
Wire faults: drop, timeout, crc, exception, garbage. Physics faults: stall, overload.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sim",
        help="serve the simulated machine (Modbus TCP/RTU or ASCII serial) until Ctrl-C",
        description=("Start the simulated testing machine (crosshead, foam specimen, load cell) behind a "
                     "real wire protocol and print where to connect and which machine profile to use. "
                     "Runs until Ctrl-C or SIGTERM."),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--transport", choices=("modbus-tcp", "modbus-rtu", "serial"),
                   help="wire protocol: Modbus TCP, Modbus RTU (TCP socket, or a pty with --pty), "
                        "or serial (the Mark-10 ESM303, always a pty)")
    p.add_argument("--device", metavar="NAME",
                   help="the simulated machine by its devices (configs/devices): mark10-esm303, "
                        "dad141-cs2rs (Modbus RTU) or dad141-cs2rs-tcp (behind a Modbus TCP gateway); "
                        "instead of --transport")
    p.add_argument("--host", default=None, help="address to bind (default 127.0.0.1; TCP transports only)")
    p.add_argument("--port", type=int, default=None, metavar="N",
                   help="TCP port (default: the profile's, 5020/5021; 0 picks a free one)")
    p.add_argument("--pty", action="store_true",
                   help="Modbus RTU on a pseudo-terminal instead of a TCP socket (serial always uses one)")
    p.add_argument("--speedup", type=float, default=1.0, metavar="S",
                   help="virtual time runs S times faster than the wall clock (default 1)")
    p.add_argument("--specimen", default=None, metavar="FILE",
                   help="specimen parameters: a fit result (JSON) or a TOML parameter set "
                        "(default: the default specimen in configs/)")
    p.add_argument("--effect", action="append", default=[], metavar="NAME=MAG",
                   help="switch on a hidden effect with a magnitude (repeatable), e.g. channel_lag=0.2")
    p.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="inject a fault (repeatable), see below")
    p.add_argument("--seed", type=int, default=0, help="seed for noise and random faults (default 0)")
    p.set_defaults(func=run)



def parse_effects(items: list[str]) -> dict[str, float]:
    """--effect NAME=MAGNITUDE options as {name: magnitude}; FoamlabError on a bad one."""
    from foamlab.model.effects import parse_effect_option  # keep `foamlab --help` fast

    effects: dict[str, float] = {}
    for item in items:
        try:
            name, value = parse_effect_option(item)
        except ValueError as exc:
            raise FoamlabError(f"--{exc}") from None
        effects[name] = value
    return effects


def _server_transport(args) -> str:
    from simulator.launch import DEVICES

    if bool(args.device) == bool(args.transport):
        raise FoamlabError("name the simulated machine with --device or --transport (one of them)")
    if args.device:
        if args.device not in DEVICES:
            raise FoamlabError(f"unknown device {args.device!r} (simulated: {', '.join(DEVICES)})")
        args.transport = DEVICES[args.device]
    if args.transport == "serial":
        return "serial"
    if args.pty:
        if args.transport != "modbus-rtu":
            raise FoamlabError("--pty works with --transport modbus-rtu (serial always uses a pty)")
        return "modbus-rtu-pty"
    return args.transport


def _default_port(profile: dict) -> int:
    connection = profile["connection"]
    if "port" in connection:
        return int(connection["port"])
    url = str(connection.get("port_url", ""))
    try:
        return int(url.rsplit(":", 1)[1]) if url.startswith("socket://") else 0
    except (IndexError, ValueError):
        return 0


def run(args) -> int:
    from drivers.profile import ProfileError, load_profile
    from simulator.launch import TRANSPORTS, start_simulator

    transport = _server_transport(args)
    on_pty = transport in ("modbus-rtu-pty", "serial")
    if on_pty and (args.port is not None or args.host is not None):
        raise FoamlabError(f"--host/--port do not apply to {transport} (it serves a pty)")
    if args.port is not None and not 0 <= args.port <= 65535:
        raise FoamlabError(f"--port must be 0..65535, got {args.port}")
    if not (args.speedup > 0 and math.isfinite(args.speedup)):
        raise FoamlabError(f"--speedup must be a positive number, got {args.speedup}")
    effects = parse_effects(args.effect)
    try:
        profile = load_profile(TRANSPORTS[transport].profile)
    except ProfileError as exc:
        raise FoamlabError(str(exc)) from None
    host = args.host or "127.0.0.1"
    port = args.port if args.port is not None else _default_port(profile)

    try:
        sim = start_simulator(transport, host=host, port=port, speedup=args.speedup,
                              specimen=args.specimen, effects=effects or None,
                              faults=args.fault or None, seed=args.seed, profile=profile)
    except (ValueError, FileNotFoundError) as exc:  # bad specimen file, effect name, fault spec
        raise FoamlabError(str(exc)) from None
    except OSError as exc:
        raise FoamlabError(f"cannot start the {transport} server: {exc}") from None

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        _announce(sim, args)
        while not stop.wait(0.5):
            if not sim.running:
                raise FoamlabError("the simulator stopped unexpectedly")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sim.stop()
    print("foamlab sim: stopped", flush=True)
    return 0


def _announce(sim, args) -> None:
    overrides = " ".join(f"{k}={v}" for k, v in sim.profile_overrides.items())
    p = sim.profile
    lines = [f"foamlab sim: {sim.transport} serving at {sim.address}"]
    commands = getattr(sim.server, "commands", None)
    if p["protocol"] == "ascii" and commands is not None:
        lines.append(f"  device {commands.name}: commands and formats from configs/devices/{commands.name}.toml")
    if p["protocol"] == "modbus":
        lines.append(f"  load cell {p['load_cell']['device']} at unit {p['load_cell']['unit_id']}, "
                     f"crosshead {p['crosshead']['device']} at unit {p['crosshead']['unit_id']}")
    run_flags = " ".join(f"--{k.replace('_', '-')} {v}" for k, v in sim.profile_overrides.items())
    run_flags += f" --specimen-height {sim.machine.settings.specimen_height_mm:g}"
    if args.speedup != 1:
        run_flags += f" --speedup {args.speedup:g}"
    lines += [
        f"  profile: {sim.profile_name}   connection: {overrides}",
        f"  run a test on it: foamlab run --machine {sim.profile_name} {run_flags}",
        f"  speedup {args.speedup:g}x, seed {args.seed}, "
        f"effects: {', '.join(args.effect) or 'none'}, faults: {', '.join(args.fault) or 'none'}",
        "  Ctrl-C to stop",
    ]
    print("\n".join(lines), flush=True)
