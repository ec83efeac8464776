"""Safety: the limits every sample is checked against, the crosshead's own alarms, and the
ways a run or a session leaves the machine - stop (else emergency stop), confirm at rest, park,
bring to rest before closing - and the
checks before anything moves or is zeroed, shared by the window and the run engine: the
travel a method needs (check_run_fits) and the tare refusal (check_safe_to_tare).

The shape of bluesky's suspenders (threshold watchdogs), without the resuming: a limit ends
the run, the data are kept and the reason recorded.

A tare (or a force zero) taken with the plate pressing on a specimen makes every later
force wrong by that load: issue 18's e-stop at 43 mm (~56 N), reset and Start tared on
the squeezed block, and the free crosshead then read -51 N. So a tare is refused, with
the reason in words, when

- the load cell does not read its unloaded level: |net force| above settings.unloaded_fraction
  of the cell's capacity (the net force is relative to the last tare, taken in air), or
- the crosshead stands below (positions grow downwards) the point where the plate last
  touched a specimen on this machine, when that point is known (remember_contact()).

The contact points are kept per machine object (weakly: a closed machine is forgotten);
the window records them from each run's result, so the engine's own tare at the start of
the next run is checked against them too.
"""

from __future__ import annotations

import collections
import logging
import threading
import weakref
from dataclasses import dataclass
from typing import Callable

from drivers.base import CrossheadStatus, DeviceConnectionLost, DeviceError, DeviceRefused, Machine
from foamlab import FoamlabError
from foamlab.acquisition.clock import WALL_CLOCK, RunClock
from foamlab.acquisition.events import END_ESTOP, END_FAULT, END_LIMIT, END_OVERLOAD, RunAborted
from foamlab.acquisition.settings import DEFAULT, AcquisitionSettings

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class Limits:
    """Safety limits in machine coordinates (positions positive down)."""

    force_N: float
    travel_upper_mm: float          # smallest position allowed
    travel_lower_mm: float          # largest position allowed
    max_speed_mm_min: float

    @classmethod
    def from_profile(cls, profile: dict) -> "Limits":
        """The profile's [limits]; the force limit defaults to 90 % of the load-cell capacity."""
        limits = profile.get("limits", {})
        capacity = float(profile.get("load_cell", {}).get("capacity_N", 0) or 0)
        force = limits.get("force_N", 0.9 * capacity if capacity else None)
        speed = limits.get("max_speed_mm_min", profile.get("crosshead", {}).get("max_speed_mm_min"))
        missing = [k for k, v in (("force_N", force), ("travel_upper_mm", limits.get("travel_upper_mm")),
                                  ("travel_lower_mm", limits.get("travel_lower_mm")),
                                  ("max_speed_mm_min", speed)) if v is None]
        if missing:
            raise FoamlabError(f"machine profile {profile.get('name', '')!r}: [limits] lacks {', '.join(missing)}")
        return cls(float(force), float(limits["travel_upper_mm"]), float(limits["travel_lower_mm"]), float(speed))

    def within(self, profile_limits: "Limits") -> None:
        """Raise FoamlabError unless these limits are inside the profile's (the GUI may only tighten)."""
        if (self.force_N > profile_limits.force_N or self.travel_upper_mm < profile_limits.travel_upper_mm
                or self.travel_lower_mm > profile_limits.travel_lower_mm
                or self.max_speed_mm_min > profile_limits.max_speed_mm_min):
            raise FoamlabError(f"limits {self} exceed the machine profile's {profile_limits}")

    def describe(self) -> str:
        return (f"force {self.force_N:g} N, travel [{self.travel_upper_mm:g}, {self.travel_lower_mm:g}] mm, "
                f"speed {self.max_speed_mm_min:g} mm/min")

    def check_sample(self, position: float, force: float, load_cell_status,
                     settings: AcquisitionSettings = DEFAULT) -> None:
        """Raise RunAborted when a sample is over a limit (or the load cell is over range)."""
        if load_cell_status is not None and load_cell_status.over_range:
            raise RunAborted(END_OVERLOAD, f"load cell overload (over-range) at {force:.1f} N")
        if force >= self.force_N:
            raise RunAborted(END_LIMIT, f"force limit {self.force_N:g} N reached ({force:.1f} N)")
        tolerance = settings.at_target_mm
        if position > self.travel_lower_mm + tolerance or position < self.travel_upper_mm - tolerance:
            raise RunAborted(END_LIMIT, f"travel limit: crosshead at {position:.3f} mm, outside "
                                        f"[{self.travel_upper_mm:g}, {self.travel_lower_mm:g}] mm")


class StallWatch:
    """A move's watchdog: the crosshead must follow its command (machine time throughout).

    Stalled: over settings.stall_window_s it moved less than settings.stall_fraction of the
    commanded travel.
    Timed out: the move took 1.25 x its nominal duration + 5 s without arriving.
    """

    def __init__(self, speed_mm_min: float, start_s: float, expected_s: float,
                 settings: AcquisitionSettings = DEFAULT):
        self.speed, self.start_s, self.expected_s = speed_mm_min, start_s, expected_s
        self.settings = settings
        self._window: collections.deque[tuple[float, float]] = collections.deque()

    def check(self, now_s: float, position: float, target: float) -> str:
        """"" when the move is on its way, else what went wrong (one line)."""
        window = self._window
        window.append((now_s, position))
        stall_s = self.settings.stall_window_s
        while window and window[0][0] < now_s - stall_s:
            window.popleft()
        elapsed = now_s - self.start_s
        span = window[-1][0] - window[0][0]
        if elapsed > 2 * stall_s and len(window) >= 3 and span >= 0.8 * stall_s:
            moved = abs(window[-1][1] - window[0][1])
            if moved < self.settings.stall_fraction * self.speed / 60.0 * span:
                return f"crosshead stalled: commanded {self.speed:g} mm/min, moved {moved:.3f} mm in {span:.1f} s"
        if elapsed > 1.25 * self.expected_s + 5.0:
            return (f"crosshead did not reach its target: {abs(position - target):.3f} mm short after "
                    f"{elapsed:.1f} s")
        return ""


def fault_name(machine: Machine) -> str:
    """The drive's fault, named when the driver can tell (Modbus fault code), else generic."""
    reason = getattr(machine.crosshead, "fault_reason", None)   # optional driver extra
    if reason is not None:
        try:
            return reason()
        except Exception:
            pass
    return "latched by the drive"


def check_crosshead_status(status: CrossheadStatus, machine: Machine) -> None:
    """Raise RunAborted for the drive's e-stop, fault and limit-switch bits."""
    if status.emergency_stopped:
        raise RunAborted(END_ESTOP, "emergency stop on the machine")
    if status.fault:
        raise RunAborted(END_FAULT, f"crosshead fault: {fault_name(machine)}")
    if status.lower_limit:
        raise RunAborted(END_LIMIT, "crosshead reached its lower travel limit")
    if status.upper_limit:
        raise RunAborted(END_LIMIT, "crosshead reached its upper travel limit")


class CrossheadWatch:
    """Reads the drive's status between samples and raises on its alarms (check_crosshead_status).

    Between samples only when the request fits before the next deadline (its round trip is
    tracked), at most every settings.status_interval_s, and at least every settings.status_forced_interval_s
    even without slack (that may cost a sample: counted as missed).
    """

    def __init__(self, machine: Machine, clock: RunClock = WALL_CLOCK, settings: AcquisitionSettings = DEFAULT):
        self.machine, self.clock, self.settings = machine, clock, settings
        self._last = 0.0
        self._rtt = 0.0
        self._in_a_row = 0
        self.failed: list[str] = []        # every failed poll, said in the run's safety note

    def maybe_read(self, schedule) -> None:
        since = self.clock.now() - self._last
        if since < self.settings.status_interval_s:
            return
        if since < self.settings.status_forced_interval_s and schedule.slack() < 1.5 * self._rtt + 1e-4:
            return
        self.read(schedule)

    def read(self, schedule=None) -> CrossheadStatus | None:
        """The drive's status; None when this poll failed (counted and said: the device's own
        error reply, or settings.max_failed_status_polls failures in a row, end the run)."""
        t = self.clock.now()
        try:
            status = self.machine.crosshead.status()
        except DeviceConnectionLost:
            raise
        except DeviceRefused as exc:
            raise RunAborted(END_FAULT, f"crosshead status refused: {exc}") from None
        except DeviceError as exc:
            self._last = self.clock.now()
            self._in_a_row += 1
            self.failed.append(str(exc))
            log.warning("crosshead status failed (%d in a row): %s", self._in_a_row, exc)
            if self._in_a_row >= self.settings.max_failed_status_polls:
                raise RunAborted(END_FAULT, f"crosshead status unreadable ({self._in_a_row} polls in a row): "
                                            f"{exc}") from None
            return None
        done = self.clock.now()
        self._in_a_row = 0
        if schedule is not None:
            schedule.waited_for_device(done - t)
        self._rtt = 0.8 * self._rtt + 0.2 * (done - t) if self._rtt else done - t
        self._last = done
        check_crosshead_status(status, self.machine)
        return status

    def note(self) -> str:
        """The failed polls of the run in one line ("" when none failed)."""
        if not self.failed:
            return ""
        return f"{len(self.failed)} crosshead status poll(s) failed, first: {self.failed[0]}"


class Stopper:
    """Brings the crosshead to rest at the end of a run, whatever the link does. Never raises.

    `estop` set: only emergency stops are sent. `link_alive` turns False when the link is lost
    for good (then nothing more is sent: no park).
    """

    def __init__(self, machine: Machine, estop: threading.Event, clock: RunClock = WALL_CLOCK,
                 settings: AcquisitionSettings = DEFAULT):
        self.machine, self.clock, self.settings = machine, clock, settings
        self.estop = estop
        self.link_alive = False

    def stop(self) -> str:
        """Stop, else emergency stop, retried (reconnecting) for settings.stop_retry_s; says what
        happened. A link that glitched may come back within it; a real drive's watchdog is the
        last line of defence beyond that.
        """
        crosshead = self.machine.crosshead
        deadline = self.clock.now() + self.settings.stop_retry_s
        errors: list[str] = []
        while True:
            estop = ("emergency stop", "emergency stopped", crosshead.emergency_stop)
            attempts = (estop,) if self.estop.is_set() else (("stop", "stopped", crosshead.stop), estop)
            lost = False
            for verb, label, action in attempts:
                try:
                    action()
                    if errors:
                        return f"{label} after {len(errors)} failed attempt(s): {errors[0]}"
                    return label
                except Exception as exc:
                    lost |= isinstance(exc, DeviceConnectionLost)
                    if not errors:
                        log.warning("%s of the crosshead failed: %s (retrying for %g s)", verb, exc,
                                    self.settings.stop_retry_s)
                    errors.append(str(exc))
            if self.clock.now() >= deadline:
                self.link_alive = False
                return f"stop and emergency stop failed ({len(errors)} attempts): {errors[-1]}"
            if lost:
                try:
                    self.machine.connect()
                except Exception as exc:
                    errors.append(str(exc))
            self.clock.sleep(0.02)

    def confirm_at_rest(self) -> str:
        """Wait until the drive reports no motion: "" when it does, else why not, in one line.

        Not confirmed within settings.stop_confirm_s (or the status unreadable): an emergency stop is
        sent and the reason is returned, never swallowed - the run's trailer and the screen say it.
        """
        deadline = self.clock.now() + self.settings.stop_confirm_s
        last_error = ""
        while self.clock.now() < deadline:
            try:
                if not self.machine.crosshead.status().moving:
                    return ""
                last_error = "the drive still reports motion"
            except DeviceConnectionLost as exc:
                self.link_alive = False
                note = f"crosshead not confirmed at rest: link lost ({exc})"
                log.error(note)
                return note
            except DeviceError as exc:
                last_error = f"status unreadable: {exc}"
            self.clock.sleep(0.005)
        note = f"crosshead not confirmed at rest within {self.settings.stop_confirm_s:g} s ({last_error})"
        try:
            self.machine.crosshead.emergency_stop()
            note += "; emergency stop sent"
        except DeviceError as exc:
            note += f"; emergency stop failed: {exc}"
        log.error(note)
        return note


def bring_to_rest(machine: Machine, settings: AcquisitionSettings = DEFAULT) -> str:
    """Leave the crosshead at rest before letting go of the link (a jog, a park cut short): where it
    moves, or its status cannot be read (taken as moving), stopped and confirmed at rest as a run's
    end is (Stopper). "" when it was or came to rest; else what happened, in one line, logged as an
    error - never swallowed."""
    try:
        if not machine.crosshead.status().moving:
            return ""
    except DeviceError as exc:      # a lost link too: Stopper reconnects for settings.stop_retry_s
        log.warning("crosshead status unreadable before closing (%s): taken as moving", exc)
    stopper = Stopper(machine, threading.Event(), settings=settings)
    said = stopper.stop()
    if said not in ("stopped", "emergency stopped"):
        note = f"closing: {said}"
        log.error(note)
        return note
    return stopper.confirm_at_rest()


def park(machine: Machine, stopper: Stopper, limits: Limits, target: float, speed: float, *,
         speedup: float, poll_s: float, interrupted: Callable[[], bool], wake: threading.Event,
         clock: RunClock = WALL_CLOCK) -> str:
    """Move back to the start position; `interrupted`, the force or a fault halts it. Says what happened."""
    crosshead = machine.crosshead
    try:
        start = machine.read_sample()
        # moving up unloads the specimen: only a force that rises and stays up means the
        # plate pushes on something (after a force-limit stop the force starts above the
        # limit; a viscoelastic specimen may spike for an instant when the motion reverses)
        force_stop = max(limits.force_N, start.force_N + 0.01 * limits.force_N)
        high = 0
        crosshead.move_to(target, speed)
        distance = abs(start.position_mm - target)
        deadline = clock.now() + (distance / speed * 60.0 * 1.5 + 5.0) / speedup + 2.0
        while clock.now() < deadline:
            if interrupted():
                crosshead.stop()
                return "park interrupted by a stop request"
            reading = machine.read_sample()
            high = high + 1 if reading.force_N >= force_stop else 0
            if high >= 3 or (reading.load_cell_status is not None and reading.load_cell_status.over_range):
                crosshead.stop()
                return f"park stopped: force {reading.force_N:.1f} N"
            status = crosshead.status()
            if status.fault or status.emergency_stopped:
                crosshead.stop()
                return "park stopped by a crosshead fault"
            arrived = abs(reading.position_mm - target) <= stopper.settings.at_target_mm or status.in_position
            if arrived and not status.moving:
                return f"parked at {target:.3f} mm"
            if (status.upper_limit or status.lower_limit) and not status.moving:
                return f"park ended at a travel limit, {reading.position_mm:.3f} mm"
            clock.wait(wake, poll_s)
        crosshead.stop()
        return "park timed out; crosshead stopped"
    except Exception as exc:
        stopper.stop()
        return f"park failed: {exc}"


# ---- before a run, a tare or a zero (the window and the engine) ------------------------------

_contacts: "weakref.WeakKeyDictionary[Machine, float]" = weakref.WeakKeyDictionary()


def remember_contact(machine: Machine, position_mm: float | None) -> None:
    """Where the plate touched the specimen in the last run (machine coordinates, mm)."""
    if position_mm is not None:
        _contacts[machine] = float(position_mm)


def last_contact(machine: Machine) -> float | None:
    return _contacts.get(machine)


def shift_contact(machine: Machine, by_mm: float) -> None:
    """The machine's position zero moved by `by_mm` (set_zero at position p: by = -p)."""
    if machine in _contacts:
        _contacts[machine] += by_mm


def unloaded_tolerance_N(machine: Machine, settings: AcquisitionSettings = DEFAULT) -> float:
    return settings.unloaded_fraction * float(machine.load_cell.capacity_N)


def check_safe_to_tare(machine: Machine, action: str = "tare", settings: AcquisitionSettings = DEFAULT) -> None:
    """Raise FoamlabError (one plain line) unless the load cell may be tared/zeroed now.

    Reads one sample from the machine: call it on the thread that owns the machine."""
    sample = machine.read_sample()
    tolerance = unloaded_tolerance_N(machine, settings)
    if abs(sample.force_N) > tolerance:
        raise FoamlabError(
            f"{action} refused: the load cell reads {sample.force_N:.1f} N, not its unloaded level "
            f"(within ±{tolerance:.3g} N); unload the specimen (jog up) before the {action}")
    contact = _contacts.get(machine)
    if contact is not None and sample.position_mm > contact:
        raise FoamlabError(
            f"{action} refused: the crosshead is at {sample.position_mm:.2f} mm, below the point where the "
            f"plate last touched the specimen ({contact:.2f} mm); jog up above it before the {action}")


def check_run_fits(method, specimen, limits, position_mm: float | None) -> None:
    """Raise FoamlabError, in the operator's words, when the method's deepest point on this
    specimen lies beyond the lower travel limit, counted from where the crosshead stands
    (the contact search starts there and only goes down). `position_mm` None: unknown,
    counted from the upper travel limit. (method: foamlab.methods.Method, specimen:
    foamlab.rundata.Specimen, limits: foamlab.acquisition.Limits.)"""
    stroke = method.max_strain * specimen.height_mm
    start = limits.travel_upper_mm if position_mm is None else position_mm
    room = limits.travel_lower_mm - start
    if stroke > room:
        raise FoamlabError(
            f"{specimen.height_mm:g} mm specimen, {method.max_strain:.0%} stroke: needs {stroke:.3g} mm of travel; "
            f"the lower travel limit ({limits.travel_lower_mm:g} mm) allows {max(room, 0):.3g} mm below the "
            f"crosshead at {start:.1f} mm")
