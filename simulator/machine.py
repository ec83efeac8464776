"""The simulated testing machine: crosshead + specimen + load cell on a virtual clock.

Physics, in the units of drivers/base.py (mm positive down, N compression positive), in three
parts composed here, as ophyd-async's sim devices are small:

- simulator.crosshead: motion (simulator.motion: trapezoidal plans, exact at every instant),
  soft travel limits, stop / emergency stop, faults (stall, limit, watchdog), the host watchdog;
- simulator.specimen: the model's force for the compression the crosshead imposes, through the
  hidden effects (foamlab.model.effects);
- simulator.load_cell: noise, quantisation, zero / tare / peak, over-range, overload.

Steps are cut at every corner of the motion plan and at the contact instant, so the specimen
sees the crosshead's piecewise-linear path exactly (the model's operators are exact for it)
and large steps cost no accuracy.

Timing: the physics advances lazily to clock.now() whenever anything reads or
commands (reads to within READ_STALENESS_S of now, commands exactly to now), and
from a background ticker thread, so motion, watchdog and faults progress when
nobody asks. One lock guards everything; every public method is thread-safe.
simulator.inprocess serves the machine through drivers.base.Machine without a wire.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from foamlab.model.effects import EffectChain, make_effects
from simulator.clock import ManualClock, VirtualClock
from simulator.crosshead import (FAULT_CODES, FAULT_EMERGENCY, FAULT_LIMIT, FAULT_NONE, FAULT_STALL,  # noqa: F401
                                 FAULT_WATCHDOG, CrossheadState, SimCrosshead)
from simulator.faults import FaultPlan
from simulator.load_cell import LoadCellReading, SimLoadCell  # noqa: F401  (the machine's reading type)
from simulator.motion import MIN_STEP_S, plan_move  # noqa: F401  (plan_move: tests of the kinematics)
from simulator.specimen import SPECIMEN_T_MAX_S, SimSpecimen, load_specimen, surface_offset_mm  # noqa: F401

TICK_REAL_S = 0.005             # background ticker period (wall clock)
TICK_IDLE_S = 0.025             # the ticker steps only when no request did for this long (wall)
TICK_CHUNK_STEPS = 2            # physics steps per lock hold in the ticker
MAX_STEPS_PER_ADVANCE = 200     # beyond this backlog, steps grow (bounded lock time, no runaway)
# Every read brings the physics to its instant, in steps of at most max_step_s; a finer
# step costs the host latency in every reply (docs/simulator_wire.md#the-physics-step).
# Coarse steps lose nothing: the crosshead's path is piecewise linear between breakpoints,
# on which the model's operators are exact, and the effects' loops are stable at any step
# (tests/test_effects.py).
MIN_AUTO_STEP_S = 0.02
READ_STALENESS_S = 1e-3         # a read sees the machine at most this long ago (virtual s; a 1 kHz indicator)
_TRACE_FIELDS = ("t", "position_mm", "velocity_mm_s", "x_crosshead_mm", "x_specimen_mm",
                 "contact_force_N", "sensor_force_N", "cycle", "direction")


@dataclass(frozen=True)
class MachineSnapshot:
    """Noise-free state at one physics time (tests, mbpoll comparisons, traces)."""

    t: float                  # virtual s
    position_mm: float        # user coordinates (after set_zero)
    velocity_mm_s: float
    x_crosshead_mm: float     # compression the crosshead imposes (>= 0)
    x_specimen_mm: float      # compression the specimen sees (after compliance)
    contact_force_N: float    # plate <-> specimen
    sensor_force_N: float     # what the load cell senses (after lag/drift), before zero/noise
    cycle: int
    direction: int


@dataclass
class MachineSettings:
    # load cell
    capacity_N: float = 500.0
    full_scale_ratio: float = 1.25      # ADC range beyond the rated capacity
    resolution_N: float = 0.01          # one count
    noise_sigma_N: float = 0.05
    load_cell_offset_N: float = 0.0     # raw signal at no load before zeroing
    motion_band_N: float = 0.5
    motion_window_s: float = 0.5
    # crosshead
    max_speed_mm_min: float = 500.0
    acceleration_mm_s2: float = 50.0
    travel_upper_mm: float = -50.0
    travel_lower_mm: float = 75.0
    following_error_s: float = 0.25
    watchdog_ms: int = 0
    # specimen
    specimen_top_mm: float = 5.0
    specimen_height_mm: float = 72.5
    # physics step (virtual s); None = from the speedup (see SimulatedMachine)
    max_step_s: float | None = None

    @classmethod
    def from_profile(cls, profile: Mapping[str, Any] | None, **overrides) -> "MachineSettings":
        s = cls()
        if profile:
            lc, ch, lim = (profile.get(k, {}) for k in ("load_cell", "crosshead", "limits"))
            for key, section, name in (("capacity_N", lc, "capacity_N"),
                                       ("max_speed_mm_min", ch, "max_speed_mm_min"),
                                       ("acceleration_mm_s2", ch, "acceleration_mm_s2"),
                                       ("travel_upper_mm", lim, "travel_upper_mm"),
                                       ("travel_lower_mm", lim, "travel_lower_mm")):
                if name in section:
                    setattr(s, key, float(section[name]))
        known = {f.name for f in fields(cls)}
        for k, v in overrides.items():
            if k not in known:
                raise ValueError(f"unknown machine setting {k!r}")
            setattr(s, k, v)
        if not s.travel_upper_mm < s.travel_lower_mm:
            raise ValueError("travel_upper_mm must be smaller than travel_lower_mm")
        for k in ("capacity_N", "resolution_N", "max_speed_mm_min", "acceleration_mm_s2"):
            if not getattr(s, k) > 0:
                raise ValueError(f"machine setting {k} must be positive")
        return s


class SimulatedMachine:
    """Crosshead + specimen + load cell. See the module docstring for the physics.

    profile: a machine profile dict (drivers.profile.load_profile) for capacity, speeds,
    acceleration and travel limits; specimen: ModelParameters, a fit/TOML path or None
    (the default specimen); effects: {"name": magnitude} or an EffectChain; faults:
    a FaultPlan or fault specs; seed: noise and random faults; clock: a ManualClock for
    reproducible stepping (no ticker thread), else a VirtualClock(speedup) is made.
    Other keyword arguments override MachineSettings fields.
    """

    def __init__(self, profile: Mapping[str, Any] | None = None, *, speedup: float = 1.0,
                 specimen=None, effects=None, faults=None, seed: int = 0,
                 clock: VirtualClock | ManualClock | None = None, **settings) -> None:
        self.settings = st = MachineSettings.from_profile(profile, **settings)
        self.clock = clock if clock is not None else VirtualClock(speedup)
        self.params = load_specimen(specimen)
        self.effects: EffectChain = make_effects(effects)
        self.faults = faults if isinstance(faults, FaultPlan) else FaultPlan(faults, seed=seed)
        self.faults.clock = self.clock.now
        self._lock = threading.RLock()
        self._error: BaseException | None = None
        sp = self.clock.speedup
        if st.max_step_s is not None:
            self.max_step_s = float(st.max_step_s)
        else:   # <= 1000 physics steps per wall-clock second, never coarser than 0.5 s
            self.max_step_s = 0.01 if math.isinf(sp) else min(0.5, max(MIN_AUTO_STEP_S, sp / 1000.0))
        self._faults_breaks = self.faults.scheduled_times(("stall", "overload"))
        self.events: collections.deque[tuple[float, str]] = collections.deque(maxlen=1000)
        self._trace: list[tuple] | None = None
        self.physics_steps = 0          # steps taken so far (benchmarks, diagnostics)

        self._t = self.clock.now()
        self.crosshead = SimCrosshead(st, self.faults, self.events, self._t, sp)
        self.specimen = SimSpecimen(self.params, self.effects, st.specimen_top_mm)
        self.load_cell = SimLoadCell(st, self.faults, seed)
        self._physics_step(self._t, first=True)

        self._realtime = isinstance(self.clock, VirtualClock)
        self._stop_event = threading.Event()
        self._ticker: threading.Thread | None = None
        if self._realtime:
            self._ticker = threading.Thread(target=self._tick_loop, name="foamlab-sim-physics", daemon=True)
            self._ticker.start()

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Stop the physics ticker (idempotent)."""
        self._stop_event.set()
        if self._ticker is not None and self._ticker is not threading.current_thread():
            self._ticker.join(5.0)

    def __enter__(self) -> "SimulatedMachine":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _tick_loop(self) -> None:
        # Small chunks under the lock, so host requests interleave with the background work.
        while not self._stop_event.wait(TICK_REAL_S):
            try:
                # Requests advance the physics themselves; the ticker only steps in when nobody
                # has asked for a whole tick (a polling host then never waits behind it).
                # (A host polling at 16 Hz x speedup keeps it idle: its requests never wait
                # behind a chunk of the ticker's steps.)
                done = self.clock.now() - self._t < self.clock.to_virtual(TICK_IDLE_S)
                while not done and not self._stop_event.is_set():
                    with self._lock:
                        done = self._advance(self.clock.now(), exact=False, max_steps=TICK_CHUNK_STEPS)
                    time.sleep(0)   # let a waiting request thread take the lock
            except BaseException as exc:   # surfaced to the next caller, never silent
                self._error = exc
                return

    @property
    def speedup(self) -> float:
        return self.clock.speedup

    # ------------------------------------------------------------------ time stepping
    def _check_error(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"simulator physics failed: {self._error!r}") from self._error

    def advance(self) -> None:
        """Bring the physics exactly to clock.now() (tests with a ManualClock call this)."""
        with self._lock:
            self._check_error()
            self._advance(self.clock.now(), exact=True)

    def _sync(self, exact: bool = False) -> None:
        # Reads need not step for every request (the ticker keeps the physics within a step
        # of now), but a value older than READ_STALENESS_S is brought to now: the step grows
        # with the speedup (S/1000 s), and a stale reading S times faster is a wrong instant
        # for the host, whose samples the model then sees at the wrong time.
        self._check_error()
        now = self.clock.now()
        self._advance(now, exact=exact or now - self._t > READ_STALENESS_S)

    def _advance(self, t_end: float, exact: bool, max_steps: int | None = None) -> bool:
        """Step the physics towards t_end; True when there (or less than one step behind)."""
        if t_end <= self._t + MIN_STEP_S:     # within a microsecond: that is now
            return True
        step = self.max_step_s
        backlog = t_end - self._t
        if not exact and backlog < step:
            return True
        if self._realtime and backlog > step * MAX_STEPS_PER_ADVANCE:
            step = backlog / MAX_STEPS_PER_ADVANCE     # behind the wall clock: coarser, never runaway
        n = 0
        while self._t < t_end:
            if max_steps is not None and n >= max_steps:
                return False
            nxt = min(self._t + step, t_end)
            for b in self._faults_breaks + self.crosshead.breakpoints(self.settings.specimen_top_mm):
                if self._t + MIN_STEP_S <= b < nxt:
                    nxt = b
            if t_end - nxt < MIN_STEP_S:
                nxt = t_end
            self._physics_step(nxt)
            n += 1
        return True

    def _physics_step(self, t: float, first: bool = False) -> None:
        self.physics_steps += 1
        t_prev = self._t
        if not first:
            self.crosshead.step(t_prev, t)
        self._t = t
        sensor = self.specimen.step(t, self.crosshead.p, self.crosshead.v)
        self.load_cell.step(t_prev, t, sensor, first)
        if self._trace is not None:
            self._trace.append(self._trace_row())

    # ------------------------------------------------------------------ load cell
    def read_load_cell(self) -> LoadCellReading:
        with self._lock:
            self._sync()
            return self.load_cell.read()

    def read_sample(self) -> tuple[LoadCellReading, float]:
        """The load cell's reading and the crosshead's position at one physics instant."""
        with self._lock:
            self._sync()
            return self.load_cell.read(), self.crosshead.position_mm

    def zero_load_cell(self) -> None:
        """Gross := 0 at the present load (the indicator averages, i.e. noise-free)."""
        self._command(self.load_cell.zero)

    def reset_load_cell_zero(self) -> None:
        """Gross zero back to the calibration zero (an indicator's "reset zero")."""
        self._command(self.load_cell.reset_zero)

    def tare(self) -> None:
        self._command(self.load_cell.tare)

    def clear_tare(self) -> None:
        self._command(self.load_cell.clear_tare)

    def reset_peak(self) -> None:
        self._command(self.load_cell.reset_peak)

    # ------------------------------------------------------------------ crosshead
    def _command(self, action, *args):
        """`action(*args)` on a part, with the physics exactly at now."""
        with self._lock:
            self._sync(exact=True)
            return action(*args)

    def position_mm(self) -> float:
        with self._lock:
            self._sync()
            return self.crosshead.position_mm

    def speed_mm_min(self) -> float:
        """Signed actual speed (positive down)."""
        with self._lock:
            self._sync()
            return self.crosshead.v * 60.0

    def crosshead_status(self) -> CrossheadState:
        with self._lock:
            self._sync()
            return self.crosshead.status()

    def move_to(self, target_mm: float, speed_mm_min: float) -> bool:
        """Absolute move (user coordinates). False if refused (fault latched, at the limit)."""
        if not math.isfinite(target_mm):
            raise ValueError(f"target must be a finite position in mm, got {target_mm!r}")
        speed = self.crosshead.speed_mm_s(speed_mm_min)
        return self._command(self.crosshead.start_move, float(target_mm), speed, "move_to")

    def jog(self, direction: int, speed_mm_min: float) -> bool:
        """Move down (+1) or up (-1) until stop() or the travel limit."""
        if direction not in (1, -1):
            raise ValueError(f"jog direction must be +1 (down) or -1 (up), got {direction!r}")
        return self._command(self.crosshead.jog, direction, self.crosshead.speed_mm_s(speed_mm_min))

    def stop(self) -> None:
        self._command(self.crosshead.stop)

    def emergency_stop(self) -> None:
        self._command(self.crosshead.emergency_stop)

    def reset_fault(self) -> None:
        self._command(self.crosshead.reset_fault)

    def set_zero(self) -> None:
        self._command(self.crosshead.set_zero)

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        if not (math.isfinite(upper_mm) and math.isfinite(lower_mm) and upper_mm < lower_mm):
            raise ValueError(f"travel limits need upper < lower (finite mm), got {upper_mm!r}, {lower_mm!r}")
        self._command(self.crosshead.set_travel_limits, upper_mm, lower_mm)

    def set_watchdog_ms(self, ms: int) -> None:
        if not (isinstance(ms, (int, float)) and math.isfinite(ms) and ms >= 0):
            raise ValueError(f"watchdog must be >= 0 ms, got {ms!r}")
        self._command(self.crosshead.set_watchdog_ms, ms)

    def host_activity(self) -> None:
        """The host said something (any request): feeds the watchdog."""
        self._command(self.crosshead.host_activity)

    def set_acceleration(self, mm_s2: float) -> None:
        """Acceleration for the next move (mm/s^2)."""
        if not (isinstance(mm_s2, (int, float)) and math.isfinite(mm_s2) and mm_s2 > 0):
            raise ValueError(f"acceleration must be a positive number of mm/s^2, got {mm_s2!r}")
        with self._lock:
            self.crosshead.acc = float(mm_s2)

    # ------------------------------------------------------------------ inspection
    def _snapshot(self) -> MachineSnapshot:
        c, s = self.crosshead, self.specimen
        return MachineSnapshot(self._t, c.position_mm, c.v, s.x_crosshead_mm, s.x_specimen_mm,
                               s.contact_force_N, s.sensor_force_N, s.cycle, s.direction)

    def _trace_row(self) -> tuple:
        s = self._snapshot()
        return tuple(getattr(s, name) for name in _TRACE_FIELDS)

    def snapshot(self) -> MachineSnapshot:
        """Noise-free state now (what the registers would show without noise and quantisation)."""
        with self._lock:
            self._sync()
            return self._snapshot()

    def motion_eta(self) -> float | None:
        """Virtual time at which the running motion will end (None when idle)."""
        with self._lock:
            self._sync()
            m = self.crosshead.motion
            return None if m is None else m.end

    def start_trace(self) -> None:
        """Record every physics step from now on (tests, benchmarks); the first row is now."""
        with self._lock:
            self._sync(exact=True)
            self._trace = [self._trace_row()]

    def trace(self) -> dict[str, np.ndarray]:
        with self._lock:
            rows = list(self._trace or [])
        cols = list(zip(*rows)) if rows else [()] * len(_TRACE_FIELDS)
        return {n: np.asarray(c, dtype=float) for n, c in zip(_TRACE_FIELDS, cols)}
