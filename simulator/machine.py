"""The simulated testing machine: crosshead + specimen + load cell on a virtual clock.

Physics, in the units of drivers/base.py (mm positive down, N compression positive):

- Crosshead: a time-optimal trapezoidal velocity profile (acceleration limit,
  commanded speed up to max speed), planned analytically when a command arrives,
  so positions are exact whatever the physics step. Soft travel limits: a move or
  jog beyond a limit stops AT the limit (limit bit set, a normal stop as on an
  ESM303); a crosshead found moving past a limit (limits moved in front of it)
  stops at once with fault 4. Controlled stop decelerates; emergency stop is
  immediate and latches fault 3 + the e-stop bit. Watchdog: while moving, a host
  silent longer than watchdog_ms (0 = off) triggers a controlled stop and fault 2.
  A latched fault ignores motion commands (they return False) until reset_fault().
- Stall (fault plan `stall@T`, `stall@T+D`, `stall:p=P`): the crosshead jams,
  the position freezes while motion is commanded; after following_error_s the
  drive latches fault 1 and drops the move.
- Specimen: top surface at specimen_top_mm (machine coordinates at start, default
  5 mm below zero, so a contact search is needed). The crosshead compression
  x = max(position - top, 0), through the hidden effects (foamlab.model.effects),
  drives foamlab.model.SpecimenState (a fitted specimen from where its elastic force
  is zero: surface_offset_mm); the plate cannot pull: force = max(total, 0)
  while x > 0, else 0. Steps are cut at every corner of the motion plan and at the
  contact instant, so the specimen sees the crosshead's piecewise-linear path
  exactly (the model's operators are exact for it) and large steps cost no accuracy.
- Load cell: capacity, ADC range (full_scale_ratio x capacity), Gaussian noise
  (seeded), quantisation to resolution_N, zero / tare / peak, over- and
  under-range flags, no-motion flag (noise-free signal within motion_band_N over
  motion_window_s). Fault `overload` forces the reading to the ADC full scale.

Timing: the physics advances lazily to clock.now() whenever anything reads or
commands (reads to within READ_STALENESS_S of now, commands exactly to now), and
from a background ticker thread, so motion, watchdog and faults progress when
nobody asks. One lock guards everything; every public method is thread-safe.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from foamlab.model import ModelParameters, SpecimenState
from foamlab.model.effects import EffectChain, make_effects
from simulator.clock import ManualClock, VirtualClock
from simulator.faults import FaultPlan

# The simulated machine's own reasons for a latched fault; each device's server says them in
# its protocol's words (the CS2RS's alarm codes, the ESM303's status and error replies).
FAULT_CODES: dict[str, int] = {"none": 0, "stall": 1, "watchdog": 2, "emergency": 3, "limit": 4}
FAULT_NONE = FAULT_CODES["none"]
FAULT_STALL = FAULT_CODES["stall"]
FAULT_WATCHDOG = FAULT_CODES["watchdog"]
FAULT_EMERGENCY = FAULT_CODES["emergency"]
FAULT_LIMIT = FAULT_CODES["limit"]

_POS_TOL_MM = 1e-6              # "at the limit" / "at the target"
TICK_REAL_S = 0.005             # background ticker period (wall clock)
TICK_IDLE_S = 0.025             # the ticker steps only when no request did for this long (wall)
TICK_CHUNK_STEPS = 2            # physics steps per lock hold in the ticker
MAX_STEPS_PER_ADVANCE = 200     # beyond this backlog, steps grow (bounded lock time, no runaway)
RANDOM_OVERLOAD_S = 1.0         # duration of one random overload event (virtual s)
MIN_STEP_S = 1e-6               # shorter steps would differentiate rounding errors (rates ~ dx/h)
# Every read brings the physics to its instant, in steps of at most max_step_s; a finer
# step costs the host latency in every reply (docs/simulator_wire.md#the-physics-step).
# Coarse steps lose nothing: the crosshead's path is piecewise linear between breakpoints,
# on which the model's operators are exact, and the effects' loops are stable at any step
# (tests/test_effects.py).
MIN_AUTO_STEP_S = 0.02
READ_STALENESS_S = 1e-3         # a read sees the machine at most this long ago (virtual s; a 1 kHz indicator)
SPECIMEN_T_MAX_S = 1e6          # memory operators stay accurate over this much virtual time


@dataclass(frozen=True)
class LoadCellReading:
    gross_N: float
    net_N: float
    peak_N: float
    under_range: bool
    over_range: bool
    no_motion: bool
    tare_set: bool


@dataclass(frozen=True)
class CrossheadState:
    fault: bool
    enabled: bool
    moving: bool
    in_position: bool
    upper_limit: bool
    lower_limit: bool
    emergency_stop: bool
    fault_code: int


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


# ----------------------------------------------------------------------------- motion planning

@dataclass(frozen=True)
class _Segment:
    """Constant acceleration from (t0, p0, v0) for dur seconds."""

    t0: float
    p0: float
    v0: float
    a: float
    dur: float

    @property
    def t1(self) -> float:
        return self.t0 + self.dur

    def at(self, t: float) -> tuple[float, float]:
        tau = min(max(t - self.t0, 0.0), self.dur)
        return self.p0 + self.v0 * tau + 0.5 * self.a * tau * tau, self.v0 + self.a * tau

    def crossing(self, level: float) -> list[float]:
        """Times within the segment where the position equals `level`."""
        c = self.p0 - level
        if self.a == 0.0:
            roots = [-c / self.v0] if self.v0 != 0 else []
        else:
            disc = self.v0 * self.v0 - 2.0 * self.a * c
            if disc < 0:
                return []
            sq = math.sqrt(disc)
            roots = [(-self.v0 - sq) / self.a, (-self.v0 + sq) / self.a]
        return [self.t0 + r for r in roots if 0.0 < r < self.dur]


@dataclass
class _Motion:
    kind: str                      # "move" | "stop"
    segments: list[_Segment]
    target: float                  # physical mm (final position of the plan)
    speed: float                   # mm/s (cruise), to replan after a jam
    end: float = field(init=False)

    def __post_init__(self):
        self.end = self.segments[-1].t1 if self.segments else -math.inf

    def at(self, t: float) -> tuple[float, float]:
        for seg in self.segments:
            if t <= seg.t1:
                return seg.at(t)
        return self.target, 0.0


def plan_move(t0: float, p: float, v: float, target: float, v_max: float, acc: float) -> list[_Segment]:
    """Time-optimal trapezoidal (or triangular) profile from (p, v) to rest at target.

    Hand-written because it must start from any state (moving, even away from the
    target) and be exact at every instant; ~20 lines of kinematics.
    """
    segs: list[_Segment] = []
    state = [t0, p, v]

    def add(a: float, dur: float) -> None:
        if dur <= 0:
            return
        t, p_, v_ = state
        segs.append(_Segment(t, p_, v_, a, dur))
        state[:] = [t + dur, p_ + v_ * dur + 0.5 * a * dur * dur, v_ + a * dur]

    d = target - p
    if v != 0.0 and (v * d <= 0 or v * v / (2 * acc) > abs(d) + 1e-12):
        add(-math.copysign(acc, v), abs(v) / acc)        # brake to rest first
        state[2] = 0.0
        d = target - state[1]
    if abs(d) <= 1e-12:
        return segs
    s = math.copysign(1.0, d)
    u, D = abs(state[2]), abs(d)
    vp = v_max if u > v_max else min(v_max, math.sqrt(acc * D + 0.5 * u * u))
    t_a = abs(vp - u) / acc
    d_a = 0.5 * (vp + u) * t_a
    d_d = vp * vp / (2 * acc)
    add(s * math.copysign(acc, vp - u), t_a)
    add(0.0, max(D - d_a - d_d, 0.0) / vp)
    add(-s * acc, vp / acc)
    return segs


def plan_stop(t0: float, p: float, v: float, acc: float) -> list[_Segment]:
    return [_Segment(t0, p, v, -math.copysign(acc, v), abs(v) / acc)] if v != 0 else []


# ----------------------------------------------------------------------------- the machine

def surface_offset_mm(params: ModelParameters) -> float:
    """Where the specimen's elastic force is zero, in its model's displacement (<= 0).

    A fitted specimen measures displacement from where the run's contact search reached
    its preload, so its elastic force at 0 is k0 ~ the preload: its top lies before 0.
    The plate touching the top is therefore at this displacement of the model (the largest
    root of the elastic polynomial below 0); 0 for a specimen whose force starts at zero
    (the default). Without it a fitted specimen would push back with k0 the instant it is
    touched, and every fit -> simulate -> fit would move the zero by the preload's travel.
    """
    k = np.asarray(params.elastic_k, float)
    if not k[0] > 0:
        return 0.0
    roots = np.roots(k[::-1]) * params.x_scale_mm          # in x / x_scale, highest power first
    real = roots[np.abs(roots.imag) <= 1e-9 * params.x_scale_mm].real
    below = real[(real < 0) & (real > -params.x_scale_mm)]
    return float(below.max()) if len(below) else 0.0


def _load_specimen(specimen) -> ModelParameters:
    if specimen is None:
        return ModelParameters.default()
    if isinstance(specimen, ModelParameters):
        return specimen
    return ModelParameters.load(Path(specimen))


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
        self.settings = MachineSettings.from_profile(profile, **settings)
        self.clock = clock if clock is not None else VirtualClock(speedup)
        self.params = _load_specimen(specimen)
        self.effects: EffectChain = make_effects(effects)
        self.faults = faults if isinstance(faults, FaultPlan) else FaultPlan(faults, seed=seed)
        self.faults.clock = self.clock.now
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._error: BaseException | None = None
        st = self.settings
        sp = self.clock.speedup
        if st.max_step_s is not None:
            self.max_step_s = float(st.max_step_s)
        else:   # <= 1000 physics steps per wall-clock second, never coarser than 0.5 s
            self.max_step_s = 0.01 if math.isinf(sp) else min(0.5, max(MIN_AUTO_STEP_S, sp / 1000.0))
        self._faults_breaks = self.faults.scheduled_times(("stall", "overload"))
        self.events: collections.deque[tuple[float, str]] = collections.deque(maxlen=1000)
        self._trace: list[tuple] | None = None
        self.physics_steps = 0          # steps taken so far (benchmarks, diagnostics)

        # crosshead (physical coordinates: machine zero at start; user = physical - zero)
        self._t = self.clock.now()
        self._p = 0.0
        self._v = 0.0
        self._zero = 0.0
        self._upper, self._lower = st.travel_upper_mm, st.travel_lower_mm   # user coordinates
        self._acc = st.acceleration_mm_s2
        self._watchdog_s = self._watchdog_machine_s(st.watchdog_ms)
        self._last_activity = self._t
        self._motion: _Motion | None = None
        self._target: float | None = None     # physical target of the last completed move
        self._fault = FAULT_NONE
        self._estop = False
        self._jam_latched = False
        self._jam_time = 0.0
        self._overload_until = -math.inf

        # specimen and load cell
        self._specimen = SpecimenState(self.params, t_max=SPECIMEN_T_MAX_S)
        self._surface_mm = surface_offset_mm(self.params)
        self._online = self.effects.online()
        self._x_cross = 0.0
        self._x_spec = 0.0
        self._contact = 0.0
        self._sensor = 0.0
        self._comps = None
        self._zero_counts = 0.0
        self._tare = 0.0
        self._tare_set = False
        self._peak = -math.inf
        self._history: collections.deque[tuple[float, float]] = collections.deque()
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

    def _breakpoints(self, t: float) -> list[float]:
        out = list(self._faults_breaks)
        m = self._motion
        if m is not None and not self._jammed_now():
            levels = (self.settings.specimen_top_mm, self._upper + self._zero, self._lower + self._zero)
            for seg in m.segments:
                out.append(seg.t0)
                out.append(seg.t1)
                for level in levels:    # contact instant, travel limits
                    out.extend(seg.crossing(level))
        if m is not None and self._watchdog_s > 0:
            out.append(self._last_activity + self._watchdog_s)
        return out

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
            for b in self._breakpoints(self._t):
                if self._t + MIN_STEP_S <= b < nxt:
                    nxt = b
            if t_end - nxt < MIN_STEP_S:
                nxt = t_end
            self._physics_step(nxt)
            n += 1
        return True

    def _jammed_now(self) -> bool:
        return self._jam_latched or self.faults.in_window("stall", self._t)

    def _physics_step(self, t: float, first: bool = False) -> None:
        self.physics_steps += 1
        t_prev = self._t
        if not first:
            self._crosshead_step(t_prev, t)
        self._t = t
        st = self.settings
        x_cross = max(self._p - st.specimen_top_mm, 0.0)
        x_s = self._online.specimen_x(t, x_cross)
        comps = self._specimen.step(t, x_s + self._surface_mm)
        contact = self._online.contact_force(t, x_cross, x_s, comps, self._v)
        sensor = self._online.sensor(t, contact)
        self._x_cross, self._x_spec, self._contact, self._sensor, self._comps = x_cross, x_s, contact, sensor, comps
        # load cell: overload faults, no-motion window, peak
        if not first and self.faults.fires_during("overload", t_prev, t, windows=False):
            if any(s.name == "overload" and s.is_random for s in self.faults.specs):
                self._overload_until = t + RANDOM_OVERLOAD_S
        self._history.append((t, self._raw_noise_free()))
        while self._history and self._history[0][0] < t - st.motion_window_s:
            self._history.popleft()
        self._peak = max(self._peak, self._quantize(self._raw_noise_free() - self._zero_counts) - self._tare)
        if self._trace is not None:
            s = self._snapshot()
            self._trace.append((s.t, s.position_mm, s.velocity_mm_s, s.x_crosshead_mm, s.x_specimen_mm,
                                s.contact_force_N, s.sensor_force_N, s.cycle, s.direction))

    def _crosshead_step(self, t0: float, t1: float) -> None:
        m = self._motion
        if self.faults.fires_during("stall", t0, t1, windows=False):
            self._jam_latched = True
            self.events.append((t1, "stall: crosshead jammed"))
        if m is None:
            return
        if self._jammed_now() and m.kind == "stop":   # a jammed axis is already at rest
            self._v = 0.0
            self._motion = None
            return
        if self._jammed_now() and m.kind == "move":
            # position frozen while the drive keeps commanding the move
            self._v = 0.0
            self._jam_time += t1 - t0
            if self._jam_time >= self.settings.following_error_s:
                self._latch_fault(FAULT_STALL, t1, "stall: following error")
                self._motion = None
            return
        if self._jam_time > 0:   # the jam cleared before the following error: resume from rest
            self._jam_time = 0.0
            self._motion = _Motion("move", plan_move(t0, self._p, 0.0, m.target, m.speed, self._acc),
                                   m.target, m.speed)
            m = self._motion
        self._p, self._v = m.at(t1)
        if t1 >= m.end - MIN_STEP_S:
            self._p, self._v = m.target, 0.0
            self._motion = None
            if m.kind == "move":
                self._target = m.target
            self.events.append((t1, f"{m.kind} done at {self._p - self._zero:.4f} mm"))
            return
        # reaching a soft limit while still heading past it (limits moved in front of the
        # crosshead, or a reversal overshooting): immediate stop (the limit crossing is a step)
        # (a move that ends at the limit arrives there at rest, in the branch above)
        # Only a motion whose end lies beyond the limit overtravels: one that ends AT the
        # limit (the ASCII stand moves to a target by setting that limit) may come within
        # the tolerance of it a step before it arrives.
        pos = self._p - self._zero
        end = m.target - self._zero
        # at rest within the tolerance band: arriving, not crossing
        arriving = self._v * self._v <= 2.0 * self._acc * 2.0 * _POS_TOL_MM
        beyond_lower = end > self._lower + _POS_TOL_MM or not arriving
        beyond_upper = end < self._upper - _POS_TOL_MM or not arriving
        if ((self._v > 0 and pos >= self._lower - _POS_TOL_MM and beyond_lower)
                or (self._v < 0 and pos <= self._upper + _POS_TOL_MM and beyond_upper)):
            self._v = 0.0
            self._motion = None
            self._latch_fault(FAULT_LIMIT, t1, f"overtravel at {pos:.4f} mm")
            return
        # watchdog: host silent too long while moving -> controlled stop + fault
        if (self._watchdog_s > 0 and m.kind == "move"
                and t1 - self._last_activity >= self._watchdog_s - 1e-12):
            self._latch_fault(FAULT_WATCHDOG, t1, "watchdog: host silent")
            self._start_stop(t1)

    def _latch_fault(self, code: int, t: float, why: str) -> None:
        if self._fault == FAULT_NONE:
            self._fault = code
        self.events.append((t, why))

    def _start_stop(self, t: float) -> None:
        segs = plan_stop(t, self._p, self._v, self._acc)
        self._target = None
        self._motion = _Motion("stop", segs, self._p + (0.5 * self._v * abs(self._v) / self._acc), 0.0) \
            if segs else None

    # ------------------------------------------------------------------ load cell
    def _quantize(self, value: float) -> float:
        r = self.settings.resolution_N
        return round(round(value / r) * r, 9)

    def _raw_noise_free(self) -> float:
        st = self.settings
        full = st.capacity_N * st.full_scale_ratio
        if self.faults.active("overload", self._t) or self._t < self._overload_until:
            return full
        return min(max(self._sensor + st.load_cell_offset_N, -full), full)

    def read_load_cell(self) -> LoadCellReading:
        with self._lock:
            self._sync()
            st = self.settings
            full = st.capacity_N * st.full_scale_ratio
            raw = self._raw_noise_free()
            noisy = raw + (self._rng.normal(0.0, st.noise_sigma_N) if st.noise_sigma_N > 0 else 0.0)
            counts = self._quantize(min(max(noisy, -full), full))
            gross = round(counts - self._zero_counts, 9)
            net = round(gross - self._tare, 9)
            self._peak = max(self._peak, net)
            values = [f for _, f in self._history]
            return LoadCellReading(
                gross_N=gross, net_N=net, peak_N=self._peak,
                under_range=counts < -st.capacity_N, over_range=counts > st.capacity_N,
                no_motion=bool(values) and max(values) - min(values) <= st.motion_band_N,
                tare_set=self._tare_set,
            )

    def read_sample(self) -> tuple[LoadCellReading, float]:
        """The load cell's reading and the crosshead's position at one physics instant."""
        with self._lock:
            reading = self.read_load_cell()
            return reading, self._p - self._zero

    def zero_load_cell(self) -> None:
        """Gross := 0 at the present load (the indicator averages, i.e. noise-free)."""
        with self._lock:
            self._sync(exact=True)
            self._zero_counts = self._quantize(self._raw_noise_free())
            self._peak = self._quantize(self._raw_noise_free() - self._zero_counts) - self._tare

    def reset_load_cell_zero(self) -> None:
        """Gross zero back to the calibration zero (an indicator's "reset zero")."""
        with self._lock:
            self._sync(exact=True)
            self._zero_counts = 0.0

    def tare(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._tare = self._quantize(self._raw_noise_free() - self._zero_counts)
            self._tare_set = True
            self._peak = 0.0

    def clear_tare(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._tare = 0.0
            self._tare_set = False

    def reset_peak(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._peak = self._quantize(self._raw_noise_free() - self._zero_counts) - self._tare

    # ------------------------------------------------------------------ crosshead queries
    def position_mm(self) -> float:
        with self._lock:
            self._sync()
            return self._p - self._zero

    def speed_mm_min(self) -> float:
        """Signed actual speed (positive down)."""
        with self._lock:
            self._sync()
            return self._v * 60.0

    def crosshead_status(self) -> CrossheadState:
        with self._lock:
            self._sync()
            pos = self._p - self._zero
            moving = self._motion is not None
            return CrossheadState(
                fault=self._fault != FAULT_NONE,
                enabled=self._fault == FAULT_NONE,
                moving=moving,
                in_position=(not moving and self._target is not None
                             and abs(self._p - self._target) <= _POS_TOL_MM),
                upper_limit=pos <= self._upper + _POS_TOL_MM,
                lower_limit=pos >= self._lower - _POS_TOL_MM,
                emergency_stop=self._estop,
                fault_code=self._fault,
            )

    # ------------------------------------------------------------------ crosshead commands
    def _speed_mm_s(self, speed_mm_min: float) -> float:
        if not (isinstance(speed_mm_min, (int, float)) and math.isfinite(speed_mm_min) and speed_mm_min > 0):
            raise ValueError(f"speed must be a positive number of mm/min, got {speed_mm_min!r}")
        return min(float(speed_mm_min), self.settings.max_speed_mm_min) / 60.0

    def _start_move(self, target_user: float, speed: float, what: str, jog: int = 0) -> bool:
        """Plan a move (target clipped to the travel limits). Caller holds the lock, synced."""
        if self._fault != FAULT_NONE:
            self.events.append((self._t, f"{what} refused: fault {self._fault} latched"))
            return False
        pos = self._p - self._zero
        clipped = min(max(target_user, self._upper), self._lower)
        if clipped != target_user or jog:
            at_lower, at_upper = pos >= self._lower - _POS_TOL_MM, pos <= self._upper + _POS_TOL_MM
            beyond_lower = at_lower and (target_user > self._lower or jog > 0)
            beyond_upper = at_upper and (target_user < self._upper or jog < 0)
            if beyond_lower or beyond_upper:
                self.events.append((self._t, f"{what} refused: at the travel limit"))
                return False
        target = clipped + self._zero
        self._jam_time = 0.0
        self._target = None
        segs = plan_move(self._t, self._p, self._v, target, speed, self._acc)
        self._motion = _Motion("move", segs, target, speed) if segs else None
        if not segs:
            self._p, self._v, self._target = target, 0.0, target
        self.events.append((self._t, f"{what}: to {clipped:.4f} mm at {speed * 60:.3f} mm/min"))
        return True

    def move_to(self, target_mm: float, speed_mm_min: float) -> bool:
        """Absolute move (user coordinates). False if refused (fault latched, at the limit)."""
        if not math.isfinite(target_mm):
            raise ValueError(f"target must be a finite position in mm, got {target_mm!r}")
        with self._lock:
            speed = self._speed_mm_s(speed_mm_min)
            self._sync(exact=True)
            return self._start_move(float(target_mm), speed, "move_to")

    def jog(self, direction: int, speed_mm_min: float) -> bool:
        """Move down (+1) or up (-1) until stop() or the travel limit."""
        if direction not in (1, -1):
            raise ValueError(f"jog direction must be +1 (down) or -1 (up), got {direction!r}")
        with self._lock:
            speed = self._speed_mm_s(speed_mm_min)
            self._sync(exact=True)
            return self._start_move(self._lower if direction > 0 else self._upper, speed,
                                    "jog down" if direction > 0 else "jog up", jog=direction)

    def stop(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._jam_time = 0.0
            self._start_stop(self._t)
            self.events.append((self._t, "stop"))

    def emergency_stop(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._motion = None
            self._v = 0.0
            self._target = None
            self._estop = True
            self._fault = FAULT_EMERGENCY
            self.events.append((self._t, "emergency stop"))

    def reset_fault(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._fault = FAULT_NONE
            self._estop = False
            self._jam_latched = False
            self._jam_time = 0.0
            if self._motion is not None and self._motion.kind == "move":
                self._motion = None     # a faulted drive does not resume a move by itself
                self._v = 0.0
            self.events.append((self._t, "reset fault"))

    def set_zero(self) -> None:
        with self._lock:
            self._sync(exact=True)
            self._zero = self._p
            self.events.append((self._t, "set zero"))

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        if not (math.isfinite(upper_mm) and math.isfinite(lower_mm) and upper_mm < lower_mm):
            raise ValueError(f"travel limits need upper < lower (finite mm), got {upper_mm!r}, {lower_mm!r}")
        with self._lock:
            self._sync(exact=True)
            self._upper, self._lower = float(upper_mm), float(lower_mm)
            m = self._motion
            if m is not None and m.kind == "move":   # re-aim the running move inside the new limits
                target_user = m.target - self._zero
                clipped = min(max(target_user, self._upper), self._lower)
                if clipped != target_user:
                    self._start_move(clipped, m.speed, "re-aim at new limit")

    def set_watchdog_ms(self, ms: int) -> None:
        if not (isinstance(ms, (int, float)) and math.isfinite(ms) and ms >= 0):
            raise ValueError(f"watchdog must be >= 0 ms, got {ms!r}")
        with self._lock:
            self._sync(exact=True)
            self._watchdog_s = self._watchdog_machine_s(ms)
            self._last_activity = self._t

    def _watchdog_machine_s(self, ms: float) -> float:
        """The watchdog guards against a silent host, and a host's silences happen in wall
        time (it cannot think faster because the machine's clock runs S times faster):
        at speedup S the timeout is ms of wall time, i.e. S x ms of machine time."""
        speedup = float(getattr(self.clock, "speedup", 1.0))
        return float(ms) / 1000.0 * (speedup if math.isfinite(speedup) else 1.0)

    def host_activity(self) -> None:
        """The host said something (any request): feeds the watchdog."""
        with self._lock:
            self._sync(exact=True)
            self._last_activity = self._t

    def set_acceleration(self, mm_s2: float) -> None:
        """Acceleration for the next move (mm/s^2)."""
        if not (isinstance(mm_s2, (int, float)) and math.isfinite(mm_s2) and mm_s2 > 0):
            raise ValueError(f"acceleration must be a positive number of mm/s^2, got {mm_s2!r}")
        with self._lock:
            self._acc = float(mm_s2)

    # ------------------------------------------------------------------ inspection
    def _snapshot(self) -> MachineSnapshot:
        c = self._comps
        return MachineSnapshot(self._t, self._p - self._zero, self._v, self._x_cross, self._x_spec,
                               self._contact, self._sensor, c.cycle if c else 0, c.direction if c else 0)

    def snapshot(self) -> MachineSnapshot:
        """Noise-free state now (what the registers would show without noise and quantisation)."""
        with self._lock:
            self._sync()
            return self._snapshot()

    def motion_eta(self) -> float | None:
        """Virtual time at which the running motion will end (None when idle)."""
        with self._lock:
            self._sync()
            return None if self._motion is None else self._motion.end

    def start_trace(self) -> None:
        """Record every physics step from now on (tests, benchmarks); the first row is now."""
        with self._lock:
            self._sync(exact=True)
            s = self._snapshot()
            self._trace = [(s.t, s.position_mm, s.velocity_mm_s, s.x_crosshead_mm, s.x_specimen_mm,
                            s.contact_force_N, s.sensor_force_N, s.cycle, s.direction)]

    def trace(self) -> dict[str, np.ndarray]:
        with self._lock:
            rows = list(self._trace or [])
        names = ("t", "position_mm", "velocity_mm_s", "x_crosshead_mm", "x_specimen_mm",
                 "contact_force_N", "sensor_force_N", "cycle", "direction")
        cols = list(zip(*rows)) if rows else [()] * len(names)
        return {n: np.asarray(c, dtype=float) for n, c in zip(names, cols)}
