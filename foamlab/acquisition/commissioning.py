"""Commissioning: check a machine against its profile before the first run (`foamlab probe`).

The probe connects, lets the device say what it is where its protocol can, reads every channel
once, runs the driver's own checks of reply formats, units and settings against the profile (a
driver offers them as `self_checks()`), writes the travel limits and reads them back where the
device allows, and - only with the operator's confirmation - moves the crosshead at most
settings.jog_mm up and back while watching force and position. It says in plain words what works and
what does not; a probe that passed is remembered for this computer (foamlab.storage.probes) so
that `foamlab run` can warn about a profile that never passed one.

Optional driver methods used when present (drivers.base keeps the required interface small):
  machine.identify() -> str                       what the device says it is
  machine.self_checks() -> list[(name, ok, detail)]  the device's documented settings and formats
  crosshead.read_travel_limits() -> (upper, lower) | None   limits as the device holds them
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

from drivers.base import DeviceError, Machine
from foamlab.acquisition.safety import Limits
from foamlab.acquisition.settings import COMMISSIONING, CommissioningSettings

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class Check:
    """One thing the probe looked at: passed (True), failed (False) or not done (None), and why."""

    name: str
    ok: bool | None
    detail: str

    def line(self) -> str:
        mark = {True: "ok  ", False: "FAIL", None: "skip"}[self.ok]
        return f"  {mark}  {self.name}: {self.detail}"


@dataclass(frozen=True)
class ProbeReport:
    profile: str
    checks: tuple[Check, ...]
    moved: bool = False                 # the commissioning move was made
    identity: str = ""

    @property
    def passed(self) -> bool:
        return all(c.ok is not False for c in self.checks) and any(c.ok for c in self.checks)

    def failures(self) -> list[Check]:
        return [c for c in self.checks if c.ok is False]

    def text(self) -> str:
        head = (f"{self.profile}: every check passed" if self.passed else
                f"{self.profile}: {len(self.failures())} check(s) failed - do not run a test until they pass")
        if self.passed and not self.moved:
            head += " (the crosshead was not moved)"
        return "\n".join([head, *(c.line() for c in self.checks)])


@dataclass
class _Probe:
    machine: Machine
    limits: Limits
    settings: CommissioningSettings = COMMISSIONING
    checks: list[Check] = field(default_factory=list)

    def check(self, name: str, action: Callable[[], str]) -> bool:
        """Run one check; its return value is the detail; a DeviceError or ValueError fails it."""
        try:
            detail = action()
        except (DeviceError, ValueError) as exc:
            self.checks.append(Check(name, False, str(exc)))
            return False
        self.checks.append(Check(name, True, detail))
        return True


def probe(machine: Machine, profile: dict, limits: Limits, *,
          confirm_move: Callable[[str], bool] | None = None,
          settings: CommissioningSettings = COMMISSIONING) -> ProbeReport:
    """Commission `machine` (built from `profile`, not yet connected). Never raises for the
    device's failures: each is a failed check. `confirm_move` is asked before the crosshead
    moves (None or False: it does not move)."""
    p = _Probe(machine, limits, settings)
    name = str(profile.get("name", "machine"))
    if not p.check("connection", lambda: _connect(machine, profile)):
        return ProbeReport(name, tuple(p.checks))
    identity = ""
    if getattr(machine, "identify", None) is not None:
        holder: list[str] = []
        p.check("identity", lambda: holder.append(machine.identify()) or holder[0])
        identity = holder[0] if holder else ""
    else:
        p.checks.append(Check("identity", None, "the device's protocol has no identification request"))
    _channels(p)
    if getattr(machine, "self_checks", None) is not None:
        try:
            for check_name, ok, detail in machine.self_checks():
                p.checks.append(Check(check_name, bool(ok), detail))
        except DeviceError as exc:
            p.checks.append(Check("device settings", False, str(exc)))
    _limits(p)
    moved = _move(p, confirm_move)
    return ProbeReport(name, tuple(p.checks), moved, identity)


def _connect(machine: Machine, profile: dict) -> str:
    machine.connect()
    connection = profile.get("connection", {})
    where = connection.get("port_url") or f"{connection.get('host', '')}:{connection.get('port', '')}"
    return f"connected ({profile.get('protocol', '?')} on {where})"


def _channels(p: _Probe) -> None:
    """Every channel once, through the same calls a run makes."""
    m = p.machine

    def plausible(force_N: float) -> None:
        if not math.isfinite(force_N):
            raise ValueError(f"force is not a number: {force_N!r}")
        if abs(force_N) > m.load_cell.capacity_N:
            raise ValueError(f"force {force_N:.6g} N beyond the cell's capacity {m.load_cell.capacity_N:g} N "
                             "(unit, scale or word order wrong?)")

    def force() -> str:
        reading = m.load_cell.read()
        plausible(reading.force_N)
        flags = [k for k, v in vars(reading.status).items() if v]
        return f"{reading.force_N:.3f} N" + (f", status {', '.join(flags)}" if flags else "")

    def position() -> str:
        mm = m.crosshead.read_position()
        if not math.isfinite(mm):
            raise ValueError(f"position is not a number: {mm!r}")
        return f"{mm:.3f} mm"

    def status() -> str:
        s = m.crosshead.status()
        flags = [k for k, v in vars(s).items() if v]
        if s.fault or s.emergency_stopped:
            raise ValueError(f"the drive reports {', '.join(flags)}: clear it at the machine first")
        return ", ".join(flags) or "at rest, no fault"

    def sample() -> str:
        s = m.read_sample()
        plausible(s.force_N)
        return f"{s.force_N:.3f} N at {s.position_mm:.3f} mm in one sample"

    p.check("force", force)
    p.check("position", position)
    p.check("crosshead status", status)
    p.check("sample (what a run reads 16 times a second)", sample)


def _limits(p: _Probe) -> None:
    lim, crosshead = p.limits, p.machine.crosshead

    def write_and_read() -> str:
        crosshead.set_travel_limits(lim.travel_upper_mm, lim.travel_lower_mm)
        reader = getattr(crosshead, "read_travel_limits", None)
        held = reader() if reader is not None else None
        if held is None:
            return (f"[{lim.travel_upper_mm:g}, {lim.travel_lower_mm:g}] mm kept by foamlab: the device holds no "
                    "travel limits it can report (its limit switches and the per-sample checks protect travel)")
        upper, lower = held
        tolerance = p.settings.limit_tolerance_mm
        if abs(upper - lim.travel_upper_mm) > tolerance or abs(lower - lim.travel_lower_mm) > tolerance:
            raise ValueError(f"wrote [{lim.travel_upper_mm:g}, {lim.travel_lower_mm:g}] mm, the device holds "
                             f"[{upper:g}, {lower:g}] mm (sign or scale wrong?)")
        return f"written and read back: [{upper:g}, {lower:g}] mm"

    p.check("travel limits", write_and_read)


def _move(p: _Probe, confirm: Callable[[str], bool] | None) -> bool:
    """settings.jog_mm up and back, only when asked and confirmed; the force watched throughout."""
    jog = p.settings
    if any(c.ok is False for c in p.checks):
        p.checks.append(Check("commissioning move", None, "not attempted: fix the failures above first"))
        return False
    question = (f"Move the crosshead {jog.jog_mm:g} mm UP and back at {jog.jog_speed_mm_min:g} mm/min? "
                "Keep clear of the plates; the machine's own emergency stop must be within reach.")
    if confirm is None or not confirm(question):
        p.checks.append(Check("commissioning move", None, "not done (not confirmed)"))
        return False
    m = p.machine
    speed = min(jog.jog_speed_mm_min, p.limits.max_speed_mm_min)
    try:
        start = m.read_sample()
    except DeviceError as exc:
        p.checks.append(Check("commissioning move", False, f"no sample before moving: {exc}"))
        return False
    up = p.check("move up", lambda: _move_and_watch(m, start.position_mm - jog.jog_mm, speed, start.force_N,
                                                    p.limits, jog))
    if up:
        p.check("move back", lambda: _move_and_watch(m, start.position_mm, speed, start.force_N, p.limits, jog))
    else:
        _stop_quietly(m)
    return True


def _move_and_watch(m: Machine, target: float, speed: float, force0: float, limits: Limits,
                    jog: CommissioningSettings) -> str:
    if not limits.travel_upper_mm <= target <= limits.travel_lower_mm:
        raise ValueError(f"{target:.3f} mm is outside the travel limits: move the crosshead first")
    m.crosshead.move_to(target, speed)
    deadline = time.monotonic() + jog.jog_mm / speed * 60.0 * 2.0 + 5.0
    force_band = jog.jog_force_fraction * limits.force_N
    while time.monotonic() < deadline:
        s = m.read_sample()
        if abs(s.force_N - force0) > force_band:
            _stop_quietly(m)
            raise ValueError(f"the force changed by {s.force_N - force0:+.2f} N while moving (more than "
                             f"{force_band:.2g} N): something touches the plate, or the force channel follows the motion")
        status = m.crosshead.status()
        if status.fault or status.emergency_stopped:
            raise ValueError("the drive reported a fault while moving")
        if not status.moving and abs(s.position_mm - target) <= jog.jog_tolerance_mm:
            return f"arrived at {s.position_mm:.3f} mm (sent {target:.3f} mm)"
        time.sleep(0.05)      # a commissioning move is watched, not sampled on a schedule
    _stop_quietly(m)
    position = m.crosshead.read_position()
    raise ValueError(f"did not arrive: at {position:.3f} mm, sent {target:.3f} mm (direction, scale or speed wrong?)")


def _stop_quietly(m: Machine) -> None:
    try:
        m.crosshead.stop()
    except DeviceError as exc:     # said, and the operator is at the machine
        log.error("stop after a failed commissioning move failed: %s", exc)
