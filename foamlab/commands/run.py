"""`foamlab run`: run a test method on a machine (by default the built-in simulated one)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import sys
import threading
import tomllib
from pathlib import Path

from foamlab import CONFIG_DIR, FoamlabError

SIM_TRANSPORTS = ("modbus-tcp", "modbus-rtu", "modbus-rtu-pty", "serial")
#: The built-in machine's specimen when none is given: its dimensions come from here too.
SIM_SPECIMEN = CONFIG_DIR / "specimens" / "default.toml"

EXAMPLES = """\
examples:
  foamlab run --speedup 20                    # the paper's protocol on the built-in simulated machine
  foamlab run --transport serial --speedup 20 # same, through the ASCII serial driver on a pty
  foamlab run --method iso3386-1 --speedup 20 --width 100 --depth 100
  foamlab run --machine my-instron.toml --method paper-3cycle --specimen-height 72.5 --specimen-label B7

Without --machine the built-in simulated machine is started on 127.0.0.1 (free port) and
driven through the real drivers; --speedup S runs its clock S times faster. The run file
(one line per sample, written as it is acquired), the fit and the results go to --out
(default $FOAMLAB_DATA or ~/foamlab-data). Ctrl-C stops the machine and keeps the data.
Exit status: 0 finished, 1 aborted (reason on one line), 2 bad input, 130 interrupted.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "run",
        help="run a test (default: the paper's protocol on the built-in simulated machine)",
        description=("Run a compression test method on a testing machine: contact search, tare, the "
                     "method's cycles sampled on a fixed schedule and streamed to disk, safety limits, "
                     "then the method's results and the model fit."),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--machine", metavar="PROFILE",
                   help="machine profile (name in configs/machines or a .toml path); default: start the "
                        "built-in simulated machine")
    p.add_argument("--method", default="paper-3cycle", metavar="METHOD",
                   help="test method (name in configs/methods or a .toml path; default paper-3cycle)")
    p.add_argument("--specimen-height", type=float, metavar="MM",
                   help="measured specimen height in mm (required with --machine; default for the "
                        "built-in machine: its specimen's height)")
    p.add_argument("--specimen-label", default="", metavar="L", help="specimen label (in the file name)")
    p.add_argument("--width", type=float, metavar="MM", help="specimen width in mm (for stresses, kPa)")
    p.add_argument("--depth", type=float, metavar="MM", help="specimen depth in mm (for stresses, kPa)")
    p.add_argument("--out", metavar="DIR", help="data folder (default $FOAMLAB_DATA or ~/foamlab-data)")
    p.add_argument("--speedup", type=float, default=1.0, metavar="S",
                   help="the machine's clock runs S times faster than real time (simulated machines "
                        "only; default 1)")
    p.add_argument("--transport", choices=SIM_TRANSPORTS, default="modbus-tcp",
                   help="wire protocol of the built-in simulated machine (default modbus-tcp)")
    p.add_argument("--host", help="override the profile's host (Modbus TCP)")
    p.add_argument("--port", type=int, help="override the profile's TCP port")
    p.add_argument("--port-url", metavar="URL", help="override the profile's serial port (device path or pyserial URL)")
    sim = p.add_argument_group("built-in simulated machine")
    sim.add_argument("--sim-specimen", metavar="FILE",
                     help="its specimen: a fit result (JSON) or parameter TOML (default configs/specimens/default.toml)")
    sim.add_argument("--effect", action="append", default=[], metavar="NAME=MAG",
                     help="hide an effect in its specimen/machine (repeatable), e.g. cycle_softening=0.1")
    sim.add_argument("--fault", action="append", default=[], metavar="SPEC",
                     help="inject a fault (repeatable): NAME@T, NAME@T+D, NAME:p=P (see foamlab sim --help)")
    sim.add_argument("--seed", type=int, default=0, help="seed of its noise and random faults (default 0)")
    p.add_argument("--unprobed-ok", action="store_true",
                   help="run a --machine profile that has not passed `foamlab probe` on this computer without "
                        "asking (scripts; the built-in simulated machine never asks)")
    p.add_argument("--no-predict", action="store_true",
                   help="no live prediction (from cycle 3 on: the rest of the run predicted from the cycles "
                        "measured, and a line when the specimen leaves the prediction)")
    p.add_argument("--no-fit", action="store_true", help="do not fit the model after the run")
    p.add_argument("--no-diagnose", action="store_true",
                   help="do not diagnose the fitted run (the diagnosis takes ~20 s; Ctrl-C skips it too)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--full", action="store_true",
                   help="also print the acquisition's thresholds the run obeys (docs/settings.md)")
    p.add_argument("--verbose", action="store_true",
                   help="also print the engine's warnings (retries, failed reads) as they happen")
    p.set_defaults(func=run)



@contextlib.contextmanager
def _engine_logging(verbose: bool):
    """Quiet by default, so an aborted run ends in exactly one line (its reason); restored after."""
    logger = logging.getLogger("foamlab")
    level, handler = logger.level, None
    if verbose:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("foamlab run: %(levelname)s: %(message)s"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
    else:
        logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)
        if handler is not None:
            logger.removeHandler(handler)


def _check_probed(profile: dict, name: str, unprobed_ok: bool) -> None:
    """A profile that never passed `foamlab probe` here: warn, and ask (a terminal) or refuse (a script)."""
    from foamlab.storage.probes import passed_probe

    if passed_probe(profile) is not None:
        return
    warning = (f"machine profile {name!r} has not passed `foamlab probe --machine {name}` on this computer "
               "(or was edited since): its units, scales and limits are unchecked against the device")
    if unprobed_ok:
        print(f"foamlab run: warning: {warning}", file=sys.stderr)
        return
    if not sys.stdin.isatty():
        raise FoamlabError(f"{warning}; probe it first, or add --unprobed-ok")
    answer = input(f"foamlab run: {warning}. Run anyway? [y/N] ").strip().lower()
    if answer not in ("y", "yes"):
        raise FoamlabError("not run: probe the machine first (foamlab probe)")


def _positive(name: str, value: float | None) -> None:
    if value is not None and not (value > 0 and math.isfinite(value)):
        raise FoamlabError(f"{name} must be a positive number, got {value:g}")


def data_dir(out: str | None) -> Path:
    """--out, else the data folder the catalog and the GUI use ($FOAMLAB_DATA or ~/foamlab-data)."""
    if out:
        return Path(out)
    from foamlab.storage.catalog import data_dir as default_data_dir

    return default_data_dir()


def _sim_specimen_dimensions(path: str | None) -> dict:
    """Height/width/depth of the simulated specimen (its TOML), when it states them."""
    source = Path(path) if path else SIM_SPECIMEN
    if source.suffix.lower() != ".toml" or not source.is_file():
        return {}
    try:
        data = tomllib.loads(source.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return {}
    return {k: float(data[k]) for k in ("height_mm", "width_mm", "depth_mm") if isinstance(data.get(k), (int, float))}


class ProgressLine:
    """One progress line on a terminal (rewritten with \\r); one line per cycle otherwise."""

    def __init__(self, stream=sys.stdout, enabled: bool = True):
        self.stream = stream
        self.enabled = enabled
        self.tty = enabled and stream.isatty()
        self._cycle = -1
        self._width = 0
        self._lock = threading.Lock()      # the engine's thread and the live prediction's both write

    def say(self, text: str) -> None:
        """A line of its own, at once (on a terminal it replaces the progress line, which follows)."""
        with self._lock:
            if self.tty and self._width:
                text = "\r" + text + " " * max(self._width - len(text), 0)
                self._width = 0
            self.stream.write(text + "\n")
            self.stream.flush()

    def on_progress(self, p) -> None:
        if not self.enabled:
            return
        left = f"{int(p.time_left_s // 60)}:{int(p.time_left_s % 60):02d}"
        cycle = f"cycle {p.cycle}/{p.n_cycles}" if p.cycle else "contact search"
        text = (f"{cycle}  x {p.displacement_mm:7.2f} mm  F {p.force_N:7.1f} N  "
                f"{p.fraction * 100:5.1f} %  {left} left")
        with self._lock:
            if self.tty:
                pad = max(self._width - len(text), 0)
                self.stream.write("\r" + text + " " * pad)
                self.stream.flush()
                self._width = len(text)
            elif p.cycle != self._cycle:
                self.stream.write(text + "\n")
                self.stream.flush()
            self._cycle = p.cycle

    def close(self) -> None:
        if self.tty and self._width:
            self.stream.write("\n")
            self.stream.flush()


def run(args) -> int:
    from drivers.profile import ProfileError, load_profile
    from foamlab.session import MachineSession, start_prediction
    from foamlab.methods import load_method
    from foamlab.rundata import Specimen
    from foamlab.storage.recorder import Recorder

    for name in ("specimen_height", "width", "depth"):
        _positive("--" + name.replace("_", "-"), getattr(args, name))
    if (args.width is None) != (args.depth is None):
        raise FoamlabError("give both --width and --depth (or neither)")
    method = load_method(args.method)
    choice = _machine_choice(args)
    if not choice.builtin:
        try:
            choice = dataclasses.replace(choice, profile=load_profile(args.machine))
        except ProfileError as exc:
            raise FoamlabError(str(exc)) from None
        _check_probed(choice.profile, args.machine, args.unprobed_ok)

    height, width, depth = args.specimen_height, args.width, args.depth
    if choice.builtin:
        dims = _sim_specimen_dimensions(args.sim_specimen)
        height = height or dims.get("height_mm")
        if width is None:
            width, depth = dims.get("width_mm"), dims.get("depth_mm")
    if not height:
        raise FoamlabError("--specimen-height is required (the measured specimen height, mm)")
    specimen = Specimen(args.specimen_label, height, width, depth)
    out_dir = data_dir(args.out)
    Recorder(out_dir).check_folder()     # before the simulator starts; the engine checks again

    predictor = scores = None
    # not connected here: the engine connects, and lets go of the link when the run ends
    with MachineSession.open(choice, connect=False) as session:
        try:
            engine = session.engine(method, specimen, out_dir)
            if not args.quiet:
                print(f"foamlab run: {method.describe()} on {session.name}; specimen {height:g} mm"
                      f"{f', {width:g} x {depth:g} mm' if width else ''}; speedup {session.speedup:g}x",
                      flush=True)
            if args.full:
                print("settings (foamlab.acquisition.settings; why each: docs/settings.md):")
                print("\n".join("  " + line for line in engine.settings.lines()), flush=True)
            progress = ProgressLine(enabled=not args.quiet)
            engine.add_listener(progress)
            # the prediction's lines are said even with --quiet: they matter
            predictor = None if args.no_predict else start_prediction(engine, method, PredictionLines(progress))
            with _engine_logging(args.verbose):
                result = _wait(engine)
                scores = predictor.finish(PREDICTION_WAIT_S) if predictor is not None else None
            progress.close()
        finally:
            if predictor is not None:
                predictor.close()
    return _report(result, method, out_dir, fit=not args.no_fit, diagnose=not args.no_diagnose, forecast=scores)


def _machine_choice(args):
    """The machine the options name (foamlab.session: the window's assembly too)."""
    from foamlab.session import MachineChoice

    builtin = args.machine is None
    if not builtin and (args.fault or args.effect or args.sim_specimen):
        raise FoamlabError("--fault, --effect and --sim-specimen apply to the built-in simulated machine only")
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port), ("port_url", args.port_url))
                 if v is not None}
    simulator = {}
    if builtin:
        from foamlab.commands.sim import parse_effects

        simulator = {"specimen": args.sim_specimen, "effects": parse_effects(args.effect) or None,
                     "faults": args.fault or None, "seed": args.seed}
    return MachineChoice(profile=args.machine, speedup=args.speedup, transport=args.transport,
                         overrides=overrides, simulator=simulator)


#: After the run, how long `foamlab run` waits for the live prediction's last forecast score (s).
PREDICTION_WAIT_S = 60.0


class PredictionLines:
    """What the live prediction says, each a line at once (foamlab.prediction.LivePredictor)."""

    def __init__(self, out: ProgressLine) -> None:
        self.out = out

    def on_forecast(self, forecast) -> None:
        self.out.say(f"prediction: {forecast.describe()}")

    def on_departure(self, departure) -> None:
        self.out.say(f"prediction: {departure.message}")

    def on_note(self, text: str) -> None:
        self.out.say(f"prediction: {text}")


def _wait(engine):
    """Run the engine; Ctrl-C asks it to stop (data kept), a second Ctrl-C e-stops."""
    engine.start()
    interrupts = 0
    while True:
        try:
            result = engine.wait(0.2)
            if result is not None:
                return result
        except KeyboardInterrupt:
            interrupts += 1
            if interrupts == 1:
                engine.request_stop("interrupted by the operator (Ctrl-C)")
            else:
                engine.emergency_stop()


def _report(result, method, out_dir: Path, fit: bool = True, diagnose: bool = True, forecast=None) -> int:
    """Say how the run went, then analyse it (foamlab.pipeline: the window's stages too)."""
    from foamlab import pipeline

    plan = pipeline.AfterRun.of(result)         # what the window does after a run too
    analysis = pipeline.Analysis(result.run, result.path) if result.run is not None else None
    if analysis is not None:
        analysis.forecast = forecast
    if result.safety:
        print(f"foamlab run: SAFETY: {result.safety}", file=sys.stderr)
    if result.status != "finished":
        kept = f"; {result.n_samples} samples kept in {result.path}" if result.path else ""
        print(f"foamlab run: aborted: {result.reason}{kept}", file=sys.stderr)
        if analysis is not None:
            _warn_catalog(pipeline.catalog_stage(analysis, out_dir))
        return 130 if "Ctrl-C" in result.reason else 1
    _print_acquisition(result, method, plan)
    pipeline.method_stage(analysis, method)
    if analysis.method_results is not None and len(analysis.method_results):
        print("results:")
        for value in analysis.method_results:
            print(f"  {value.format()}")
    elif analysis.method_error:
        print(f"results: not available: {analysis.method_error}")
    if fit and plan.fit:
        try:
            pipeline.fit_stage(analysis)
        except KeyboardInterrupt:   # the run is saved; the fit can be made later (foamlab fit)
            analysis.fit_error = "skipped (Ctrl-C)"
        if analysis.fit is not None:
            print("fit:")
            # the short summary, as `foamlab fit` prints it; the whole report is in the fit file
            print("  " + analysis.fit.brief().replace("\n", "\n  "))
        else:
            print(f"fit: not available: {analysis.fit_error}")
    _print_forecast(forecast)
    pipeline.files_stage(analysis)      # the fit file now: a skipped diagnosis does not hold it up
    if analysis.fit_path:
        print(f"  fit file: {analysis.fit_path}")
    if fit and diagnose and analysis.fit is not None:
        print("diagnosing the run (Ctrl-C skips it)...", flush=True)
        try:
            pipeline.diagnose_stage(analysis)
        except KeyboardInterrupt:
            analysis.diagnosis_error = "skipped (Ctrl-C)"
        pipeline.files_stage(analysis)
    if analysis.diagnosis is not None:
        where = f" ({analysis.diagnosis_path})" if analysis.diagnosis_path else ""
        print(f"diagnosis: {analysis.verdict}{where}")
    elif analysis.diagnosis_error:
        print(f"diagnosis: {analysis.diagnosis_error}")
    if analysis.files_error:
        print(f"foamlab run: warning: {analysis.files_error}", file=sys.stderr)
    _warn_catalog(pipeline.catalog_stage(analysis, out_dir))
    return 0


def _print_forecast(scores) -> None:
    """Each cycle's forecast from the earlier ones, as the live prediction scored it."""
    if scores is None:
        return
    if scores.scores:
        print("forecast (each cycle predicted from the earlier ones, during the run):")
        for s in scores.scores:
            print(f"  {s.describe()}")
    if scores.note:
        print(f"forecast: {scores.note}")


def _print_acquisition(result, method, plan) -> None:
    timing = result.timing
    waiting = f", {timing.missed_waiting_device} of them waiting for replies" if result.missed else ""
    print(f"foamlab run: finished: {result.n_samples} samples, {result.missed} missed{waiting} "
          f"({method.sampling_hz:g} Hz; deadline lateness p99 {timing.lateness_p99_ms:.2f} ms, "
          f"request p99 {timing.rtt_p99_ms:.2f} ms)")
    if plan.gaps:
        print(f"  note: {plan.missed_share:.1%} of the deadlines were missed: the machine "
              f"answered in {timing.rtt_p99_ms:.1f} ms (p99) for a {timing.period_s * 1e3:.2f} ms period; "
              f"a lower --speedup keeps every sample")
    print(f"  run file: {result.path}")


def _warn_catalog(analysis) -> None:
    if analysis.catalog_error:   # the run file is the record; `foamlab catalog rebuild` recovers
        print(f"foamlab run: warning: run {analysis.catalog_error}", file=sys.stderr)
