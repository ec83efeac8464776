"""One assembly of a run for every front end: a machine choice -> a machine -> a run engine
-> its live prediction.

`foamlab run` and the window both call this, so what a run is given (the profile the
driver is built from, the built-in simulated machine's process and options, the clock
rate, the engine's connection handling and machine name, the live prediction) is decided
once:

    with MachineSession.open(MachineChoice(speedup=20)) as session:   # the built-in machine
        engine = session.engine(method, specimen, out_dir)
        predictor = start_prediction(engine, method, listener)         # before engine.start()
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from foamlab import FoamlabError

if TYPE_CHECKING:
    from drivers.base import Machine
    from foamlab.acquisition.engine import RunEngine
    from foamlab.acquisition.safety import Limits
    from foamlab.methods import Method
    from foamlab.prediction.live import LivePredictor
    from foamlab.rundata import Specimen

log = logging.getLogger(__name__)

#: The built-in simulated machine's wire protocol unless another is chosen.
BUILTIN_TRANSPORT = "modbus-tcp"


@dataclass(frozen=True)
class MachineChoice:
    """Which machine, and how: a profile (name, path or loaded), or the built-in simulated machine (None).

    `speedup` is the machine clock's rate against the wall clock: the built-in machine runs
    that fast, and a simulator started by `foamlab sim --speedup S` needs the same S; a real
    machine runs at 1. `overrides`: connection settings replacing the profile's (host, port,
    port_url). `simulator`: the built-in machine's options for simulator.launch (specimen,
    effects, faults, seed), unused with a profile.
    """

    profile: str | dict | None = None
    speedup: float = 1.0
    transport: str = BUILTIN_TRANSPORT
    overrides: Mapping[str, Any] = field(default_factory=dict)
    simulator: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (self.speedup > 0 and math.isfinite(self.speedup)):
            raise FoamlabError(f"--speedup must be a positive number, got {self.speedup:g}")
        if self.builtin and self.overrides:
            raise FoamlabError("--host/--port/--port-url apply with --machine only")

    @property
    def builtin(self) -> bool:
        return self.profile is None


@dataclass
class MachineSession:
    """A machine ready for runs, and the simulator process behind it when built in."""

    machine: Machine
    profile: dict                 # the loaded machine profile the driver was built from
    name: str                     # what a front end shows
    speedup: float                # the machine clock's rate (MachineChoice.speedup)
    simulator: Any = None         # simulator.process.SimulatorProcess when built in
    connected: bool = False       # the session holds the link (else each engine connects)

    @classmethod
    def open(cls, choice: MachineChoice, *, connect: bool = True) -> MachineSession:
        """Start the built-in machine or load the profile, build its driver, connect if asked.

        Raises FoamlabError (one line) for a bad profile or a simulator that cannot start.
        """
        from drivers.profile import ProfileError, load_profile, open_machine  # noqa: PLC0415

        sim = None
        try:
            if choice.builtin:
                sim = _start_builtin(choice)
                profile, overrides = sim.profile, dict(sim.profile_overrides)
                name = f"built-in simulated machine ({sim.transport} at {sim.address})"
            else:
                profile = choice.profile if isinstance(choice.profile, dict) else load_profile(choice.profile)
                overrides = dict(choice.overrides)
                name = profile["name"]
            machine = open_machine(profile, connect=connect, **overrides)
        except ProfileError as exc:
            if sim is not None:
                sim.stop()
            raise FoamlabError(str(exc)) from None
        except BaseException:
            if sim is not None:
                sim.stop()
            raise
        return cls(machine, profile, name, choice.speedup, sim, connected=connect)

    def engine(self, method: Method, specimen: Specimen, out_dir: str | Path,
               limits: Limits | None = None, **options: Any) -> RunEngine:
        """A RunEngine for one run on this machine (connecting itself when the session does not)."""
        from foamlab.acquisition.engine import RunEngine  # noqa: PLC0415

        return RunEngine(self.machine, method, specimen, out_dir, limits=limits, speedup=self.speedup,
                         connect=not self.connected, machine_name=self.profile.get("name"), **options)

    def close(self) -> None:
        """Leave the crosshead at rest and let go of the link (if held), then stop the simulator."""
        from foamlab.acquisition.safety import bring_to_rest  # noqa: PLC0415

        try:
            if self.connected:
                self.connected = False
                try:
                    bring_to_rest(self.machine)
                finally:
                    self.machine.close()
        finally:
            if self.simulator is not None:
                self.simulator.stop()

    def __enter__(self) -> MachineSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def start_prediction(engine: RunEngine, method: Method, listener: Any) -> LivePredictor:
    """The live prediction of `engine`'s run of `method`, telling `listener` (on_forecast,
    on_departure, on_note; from its own thread); started, so call it before engine.start()."""
    from foamlab.prediction.live import LivePredictor  # noqa: PLC0415

    predictor = LivePredictor(engine.plan, method.sampling_hz, method.n_cycles)
    predictor.add_listener(listener)
    engine.add_listener(predictor)
    predictor.start()
    return predictor


def _start_builtin(choice: MachineChoice):
    """The built-in machine on 127.0.0.1 (free port), in its own process like a real machine:
    in this one it would compete with the acquisition for the interpreter lock (simulator/process.py)."""
    from simulator.process import start_simulator_process  # noqa: PLC0415

    try:
        return start_simulator_process(choice.transport, host="127.0.0.1", port=0, speedup=choice.speedup,
                                       **choice.simulator)
    except (ValueError, TimeoutError) as exc:    # bad specimen file, effect or fault spec; no start
        raise FoamlabError(f"cannot start the simulated machine: {exc}") from None
