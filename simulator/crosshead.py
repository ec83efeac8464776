"""The simulated crosshead: motion, soft travel limits, stops, faults and the host watchdog.

A time-optimal trapezoidal velocity profile (simulator.motion; acceleration limit, commanded
speed up to max speed), planned analytically when a command arrives. Soft travel limits: a
move or jog beyond a limit stops AT the limit (limit bit set, a normal stop as on an ESM303);
a crosshead found moving past a limit (limits moved in front of it) stops at once with fault
4. Controlled stop decelerates; emergency stop is immediate and latches fault 3 + the e-stop
bit. Watchdog: while moving, a host silent longer than watchdog_ms (0 = off) triggers a
controlled stop and fault 2. A latched fault ignores motion commands (they return False)
until reset_fault(). Stall (fault plan `stall@T`, `stall@T+D`, `stall:p=P`): the crosshead
jams, the position freezes while motion is commanded; after following_error_s the drive
latches fault 1 and drops the move.

Positions are physical (machine zero at start); the user's are physical - zero.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from simulator.faults import FaultPlan
from simulator.motion import MIN_STEP_S, Motion, plan_move, plan_stop

if TYPE_CHECKING:
    from simulator.machine import MachineSettings

# The simulated machine's own reasons for a latched fault; each device's server says them in
# its protocol's words (the CS2RS's alarm codes, the ESM303's status and error replies).
FAULT_CODES: dict[str, int] = {"none": 0, "stall": 1, "watchdog": 2, "emergency": 3, "limit": 4}
FAULT_NONE = FAULT_CODES["none"]
FAULT_STALL = FAULT_CODES["stall"]
FAULT_WATCHDOG = FAULT_CODES["watchdog"]
FAULT_EMERGENCY = FAULT_CODES["emergency"]
FAULT_LIMIT = FAULT_CODES["limit"]

POS_TOL_MM = 1e-6               # "at the limit" / "at the target"


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


class SimCrosshead:
    """The crosshead at the machine's physics time `t` (see the module docstring).

    step(t0, t1) follows the physics; the commands act at `t` (the machine brings the
    physics to now first). `events` collects (t, what happened) for tests and the console.
    """

    def __init__(self, settings: "MachineSettings", faults: FaultPlan, events: collections.deque,
                 t: float, speedup: float):
        self.faults, self.events = faults, events
        self.following_error_s = settings.following_error_s
        self.speedup = speedup
        self.max_speed_mm_min = settings.max_speed_mm_min
        self.t = t
        self.p = 0.0                  # physical position
        self.v = 0.0
        self.zero = 0.0
        self.upper, self.lower = settings.travel_upper_mm, settings.travel_lower_mm   # user coordinates
        self.acc = settings.acceleration_mm_s2
        self.watchdog_s = self._watchdog_machine_s(settings.watchdog_ms)
        self.last_activity = t
        self.motion: Motion | None = None
        self._target: float | None = None     # physical target of the last completed move
        self.fault = FAULT_NONE
        self.estop = False
        self._jam_latched = False
        self._jam_time = 0.0

    @property
    def position_mm(self) -> float:
        """User coordinates."""
        return self.p - self.zero

    def jammed(self) -> bool:
        return self._jam_latched or self.faults.in_window("stall", self.t)

    def breakpoints(self, specimen_top_mm: float) -> list[float]:
        """Instants the physics must step to exactly: the plan's corners, the contact instant,
        the limit crossings, the watchdog's deadline."""
        out: list[float] = []
        m = self.motion
        if m is not None and not self.jammed():
            levels = (specimen_top_mm, self.upper + self.zero, self.lower + self.zero)
            for seg in m.segments:
                out.append(seg.t0)
                out.append(seg.t1)
                for level in levels:    # contact instant, travel limits
                    out.extend(seg.crossing(level))
        if m is not None and self.watchdog_s > 0:
            out.append(self.last_activity + self.watchdog_s)
        return out

    # ------------------------------------------------------------------ physics
    def step(self, t0: float, t1: float) -> None:
        self._step(t0, t1)
        self.t = t1

    def _step(self, t0: float, t1: float) -> None:
        m = self.motion
        if self.faults.fires_during("stall", t0, t1, windows=False):
            self._jam_latched = True
            self.events.append((t1, "stall: crosshead jammed"))
        if m is None:
            return
        if self.jammed() and m.kind == "stop":   # a jammed axis is already at rest
            self.v = 0.0
            self.motion = None
            return
        if self.jammed() and m.kind == "move":
            # position frozen while the drive keeps commanding the move
            self.v = 0.0
            self._jam_time += t1 - t0
            if self._jam_time >= self.following_error_s:
                self._latch_fault(FAULT_STALL, t1, "stall: following error")
                self.motion = None
            return
        if self._jam_time > 0:   # the jam cleared before the following error: resume from rest
            self._jam_time = 0.0
            self.motion = Motion("move", plan_move(t0, self.p, 0.0, m.target, m.speed, self.acc), m.target, m.speed)
            m = self.motion
        self.p, self.v = m.at(t1)
        if t1 >= m.end - MIN_STEP_S:
            self.p, self.v = m.target, 0.0
            self.motion = None
            if m.kind == "move":
                self._target = m.target
            self.events.append((t1, f"{m.kind} done at {self.p - self.zero:.4f} mm"))
            return
        if self._overtravels(m):
            self.v = 0.0
            self.motion = None
            self._latch_fault(FAULT_LIMIT, t1, f"overtravel at {self.p - self.zero:.4f} mm")
            return
        # watchdog: host silent too long while moving -> controlled stop + fault
        if self.watchdog_s > 0 and m.kind == "move" and t1 - self.last_activity >= self.watchdog_s - 1e-12:
            self._latch_fault(FAULT_WATCHDOG, t1, "watchdog: host silent")
            self._start_stop(t1)

    def _overtravels(self, m: Motion) -> bool:
        """Reaching a soft limit while still heading past it (limits moved in front of the
        crosshead, or a reversal overshooting): an immediate stop (the crossing is a step).

        A move that ends at the limit arrives there at rest (the plan's end). Only a motion
        whose end lies beyond the limit overtravels: one that ends AT the limit (the ASCII
        stand moves to a target by setting that limit) may come within the tolerance of it a
        step before it arrives.
        """
        pos = self.p - self.zero
        end = m.target - self.zero
        # at rest within the tolerance band: arriving, not crossing
        arriving = self.v * self.v <= 2.0 * self.acc * 2.0 * POS_TOL_MM
        beyond_lower = end > self.lower + POS_TOL_MM or not arriving
        beyond_upper = end < self.upper - POS_TOL_MM or not arriving
        return ((self.v > 0 and pos >= self.lower - POS_TOL_MM and beyond_lower)
                or (self.v < 0 and pos <= self.upper + POS_TOL_MM and beyond_upper))

    def _latch_fault(self, code: int, t: float, why: str) -> None:
        if self.fault == FAULT_NONE:
            self.fault = code
        self.events.append((t, why))

    def _start_stop(self, t: float) -> None:
        segs = plan_stop(t, self.p, self.v, self.acc)
        self._target = None
        self.motion = Motion("stop", segs, self.p + (0.5 * self.v * abs(self.v) / self.acc), 0.0) if segs else None

    # ------------------------------------------------------------------ queries
    def status(self) -> CrossheadState:
        pos = self.p - self.zero
        moving = self.motion is not None
        return CrossheadState(
            fault=self.fault != FAULT_NONE,
            enabled=self.fault == FAULT_NONE,
            moving=moving,
            in_position=(not moving and self._target is not None and abs(self.p - self._target) <= POS_TOL_MM),
            upper_limit=pos <= self.upper + POS_TOL_MM,
            lower_limit=pos >= self.lower - POS_TOL_MM,
            emergency_stop=self.estop,
            fault_code=self.fault,
        )

    # ------------------------------------------------------------------ commands (at t)
    def speed_mm_s(self, speed_mm_min: float) -> float:
        """A commanded speed, checked and capped at the maximum, in mm/s."""
        if not (isinstance(speed_mm_min, (int, float)) and math.isfinite(speed_mm_min) and speed_mm_min > 0):
            raise ValueError(f"speed must be a positive number of mm/min, got {speed_mm_min!r}")
        return min(float(speed_mm_min), self.max_speed_mm_min) / 60.0

    def start_move(self, target_user: float, speed: float, what: str, jog: int = 0) -> bool:
        """Plan a move (target clipped to the travel limits); False when refused."""
        if self.fault != FAULT_NONE:
            self.events.append((self.t, f"{what} refused: fault {self.fault} latched"))
            return False
        pos = self.p - self.zero
        clipped = min(max(target_user, self.upper), self.lower)
        if clipped != target_user or jog:
            at_lower, at_upper = pos >= self.lower - POS_TOL_MM, pos <= self.upper + POS_TOL_MM
            beyond_lower = at_lower and (target_user > self.lower or jog > 0)
            beyond_upper = at_upper and (target_user < self.upper or jog < 0)
            if beyond_lower or beyond_upper:
                self.events.append((self.t, f"{what} refused: at the travel limit"))
                return False
        target = clipped + self.zero
        self._jam_time = 0.0
        self._target = None
        segs = plan_move(self.t, self.p, self.v, target, speed, self.acc)
        self.motion = Motion("move", segs, target, speed) if segs else None
        if not segs:
            self.p, self.v, self._target = target, 0.0, target
        self.events.append((self.t, f"{what}: to {clipped:.4f} mm at {speed * 60:.3f} mm/min"))
        return True

    def jog(self, direction: int, speed: float) -> bool:
        return self.start_move(self.lower if direction > 0 else self.upper, speed,
                               "jog down" if direction > 0 else "jog up", jog=direction)

    def stop(self) -> None:
        self._jam_time = 0.0
        self._start_stop(self.t)
        self.events.append((self.t, "stop"))

    def emergency_stop(self) -> None:
        self.motion = None
        self.v = 0.0
        self._target = None
        self.estop = True
        self.fault = FAULT_EMERGENCY
        self.events.append((self.t, "emergency stop"))

    def reset_fault(self) -> None:
        self.fault = FAULT_NONE
        self.estop = False
        self._jam_latched = False
        self._jam_time = 0.0
        if self.motion is not None and self.motion.kind == "move":
            self.motion = None     # a faulted drive does not resume a move by itself
            self.v = 0.0
        self.events.append((self.t, "reset fault"))

    def set_zero(self) -> None:
        self.zero = self.p
        self.events.append((self.t, "set zero"))

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        self.upper, self.lower = float(upper_mm), float(lower_mm)
        m = self.motion
        if m is not None and m.kind == "move":   # re-aim the running move inside the new limits
            target_user = m.target - self.zero
            clipped = min(max(target_user, self.upper), self.lower)
            if clipped != target_user:
                self.start_move(clipped, m.speed, "re-aim at new limit")

    def set_watchdog_ms(self, ms: float) -> None:
        self.watchdog_s = self._watchdog_machine_s(ms)
        self.last_activity = self.t

    def _watchdog_machine_s(self, ms: float) -> float:
        """The watchdog guards against a silent host, and a host's silences happen in wall
        time (it cannot think faster because the machine's clock runs S times faster):
        at speedup S the timeout is ms of wall time, i.e. S x ms of machine time."""
        speedup = float(self.speedup)
        return float(ms) / 1000.0 * (speedup if math.isfinite(speedup) else 1.0)

    def host_activity(self) -> None:
        self.last_activity = self.t
