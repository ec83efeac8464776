"""The Leadshine CS2RS drive in PR mode as a Crosshead (its registers: configs/devices/leadshine-cs2rs.toml).

The drive works in pulses (Pr0.00 per motor revolution, 0x0001) and whole rpm; the
machine's screw is the profile's: `lead_mm` (travel per screw revolution), `gear_ratio`
(motor revolutions per screw revolution), `pulses_per_rev` (what 0x0001 must read).
Every motion is one absolute PR0 move: the PR0 block (mode, position, speed, ramps) in
one function-16 write, then path 0 triggered at 0x6002. Positions positive down: the
drive's direction (Pr0.03) is set so that positive pulses move the plate down.
"""

from __future__ import annotations

from .base import Crosshead, CrossheadStatus, DeviceError
from .modbus_link import DeviceOnLink, ModbusLink
from .registers import DeviceMap

#: A target this close beyond a travel limit is at the limit (rounding of a position in mm).
LIMIT_TOLERANCE_MM = 1e-6
#: A speed the drive's whole rpm would change by more than this is refused.
SPEED_TOLERANCE = 0.01


class DeviceMismatch(DeviceError):
    """A drive setting differs from what the machine profile says it is: running would move wrongly."""


class EmergencyStopLatched(DeviceError):
    """This driver holds an emergency stop until reset_fault() (the drive itself latches nothing)."""


def motor_rpm(speed_mm_min: float, lead_mm: float, gear_ratio: float) -> float:
    """Crosshead speed -> motor speed: rpm = mm/min x gear_ratio / lead_mm."""
    return speed_mm_min * gear_ratio / lead_mm


def ramp_ms(acceleration_mm_s2: float, lead_mm: float, gear_ratio: float) -> int:
    """The drive's ramp unit, ms per 1000 rpm, for an acceleration in mm/s^2 (whole ms, >= 1)."""
    mm_s_at_1000_rpm = 1000.0 * lead_mm / gear_ratio / 60.0
    return max(1, round(1000.0 * mm_s_at_1000_rpm / acceleration_mm_s2))


class Cs2rsCrosshead(Crosshead):
    """Leadshine CS2RS closed-loop stepper drive (Modbus RTU, PR mode) driving the crosshead screw."""

    USES = dict(registers=("pulses_per_rev", "status", "alarm", "control_word", "trigger", "motor_position"),
                blocks=("pr0",),
                bits={"status": ("fault", "running", "path_done")},
                values={"trigger": ("start_path0", "quick_stop", "set_zero"),
                        "control_word": ("reset_alarm",), "pr0_mode": ("absolute",)})

    @classmethod
    def check_device(cls, device: DeviceMap) -> DeviceMap:
        return device.require(**cls.USES)

    def __init__(self, link: ModbusLink, device: DeviceMap, settings: dict, limits: dict):
        self.drive = DeviceOnLink(link, self.check_device(device), int(settings["unit_id"]))
        self.lead_mm = float(settings["lead_mm"])
        self.gear_ratio = float(settings["gear_ratio"])
        self.pulses_per_rev = int(settings["pulses_per_rev"])
        self.mm_per_pulse = self.lead_mm / (self.gear_ratio * self.pulses_per_rev)
        self.position_resolution_mm = self.mm_per_pulse     # 0x602C counts pulses
        self.max_speed_mm_min = float(settings["max_speed_mm_min"])
        self.ramp_ms = ramp_ms(float(settings["acceleration_mm_s2"]), self.lead_mm, self.gear_ratio)
        # The drive has no documented soft limits: these are the driver's own, for its checks.
        self.travel_limits = (float(limits["travel_upper_mm"]), float(limits["travel_lower_mm"]))
        self._estop_latched = False

    # ------------------------------------------------------------------ units
    def _where(self) -> str:
        return f"{self.drive.link.where}: unit {self.drive.unit} ({self.drive.device.name})"

    def rpm(self, speed_mm_min: float) -> int:
        """The drive's whole rpm for a crosshead speed; ValueError (with the numbers) when the
        rounding would change the speed by more than 1 %, or it is outside the machine's range."""
        if not 0 < speed_mm_min <= self.max_speed_mm_min:
            raise ValueError(f"speed {speed_mm_min:g} mm/min outside (0, {self.max_speed_mm_min:g}] mm/min")
        exact = motor_rpm(speed_mm_min, self.lead_mm, self.gear_ratio)
        whole = round(exact)
        if whole < 1 or abs(whole - exact) > SPEED_TOLERANCE * exact:
            actual = whole * self.lead_mm / self.gear_ratio
            register = self.drive.device.registers["pr0_speed"].label()
            raise ValueError(f"speed {speed_mm_min:g} mm/min is {exact:.3f} rpm at the motor; the drive takes whole rpm "
                             f"({register}): {whole} rpm = {actual:g} mm/min, {abs(actual / speed_mm_min - 1) * 100:.1f} % "
                             f"off (> {SPEED_TOLERANCE * 100:g} %; lead {self.lead_mm:g} mm, gear {self.gear_ratio:g})")
        return whole

    def pulses(self, position_mm: float) -> int:
        return round(position_mm / self.mm_per_pulse)

    # ------------------------------------------------------------------ on connect
    def check_settings(self) -> None:
        """Refuse to run when the drive's pulses per revolution (0x0001) is not the profile's."""
        ppr = int(self.drive.read("pulses_per_rev"))
        if ppr != self.pulses_per_rev:
            register = self.drive.device.registers["pulses_per_rev"].label()
            raise DeviceMismatch(f"{self._where()}: {register} reads {ppr} pulse/rev, the profile "
                                 f"says {self.pulses_per_rev}: set Pr0.00 or the profile's pulses_per_rev")

    # ------------------------------------------------------------------ reading
    def read_position(self) -> float:
        return int(self.drive.read("motor_position")) * self.mm_per_pulse

    def status(self) -> CrossheadStatus:
        bits = self.drive.device.decode_bits("status", int(self.drive.read("status")))
        # 0x1003 has no limit, e-stop or in-position bit: a finished path is in position.
        return CrossheadStatus(moving=bits["running"], in_position=bits["path_done"] and not bits["running"],
                               fault=bits["fault"] or self._estop_latched, emergency_stopped=self._estop_latched)

    def fault_reason(self) -> str:
        """Why the fault bit is set: the driver's e-stop latch, or the drive's alarm (0x2203) in words."""
        if self._estop_latched:
            return "emergency stop (held by the driver until reset; the drive latches nothing)"
        code = int(self.drive.read("alarm"))
        if code == 0:
            return "no alarm code (0x2203 = 0)"
        return f"alarm 0x{code:04X}: {self.drive.device.meaning('alarm', code) or 'not in the device file'}"

    # ------------------------------------------------------------------ motion
    def move_to(self, target_mm: float, speed_mm_min: float) -> None:
        if self._estop_latched:
            raise EmergencyStopLatched(f"{self._where()}: emergency stop latched: reset_fault() before moving")
        upper, lower = self.travel_limits
        if not upper - LIMIT_TOLERANCE_MM <= target_mm <= lower + LIMIT_TOLERANCE_MM:
            raise ValueError(f"target {target_mm:g} mm outside the travel limits [{upper:g}, {lower:g}] mm")
        rpm = self.rpm(speed_mm_min)
        pr0 = {"pr0_mode": self.drive.device.value("pr0_mode", "absolute"), "pr0_position": self.pulses(target_mm),
               "pr0_speed": rpm, "pr0_accel": self.ramp_ms, "pr0_decel": self.ramp_ms}
        with self.drive.link.lock:   # the path and its trigger belong together
            self.drive.write_block("pr0", pr0)
            self.drive.command("trigger", "start_path0")

    def jog(self, direction: int, speed_mm_min: float) -> None:
        if direction not in (1, -1):
            raise ValueError(f"jog direction must be +1 (down) or -1 (up), got {direction!r}")
        # A bounded move: velocity mode or the 0x4001 jog would run on if the host fell silent.
        limit = self.travel_limits[1] if direction > 0 else self.travel_limits[0]
        position = self.read_position()    # at or beyond that limit the move would go the other way
        if direction * (limit - position) <= LIMIT_TOLERANCE_MM:
            raise ValueError(f"jog {'down' if direction > 0 else 'up'} refused: the crosshead is at {position:.3f} mm, "
                             f"at or beyond the travel limit {limit:g} mm")
        self.move_to(limit, speed_mm_min)

    def stop(self) -> None:
        # 0x40 (quick stop, Pr8.23's deceleration) is the drive's only documented stop.
        self.drive.command("trigger", "quick_stop", repeatable=True)

    def emergency_stop(self) -> None:
        self._estop_latched = True   # first: even if the write fails, nothing moves from here
        self.drive.command("trigger", "quick_stop", repeatable=True)

    def reset_fault(self) -> None:
        self.drive.command("control_word", "reset_alarm", repeatable=True)
        self._estop_latched = False

    def set_zero(self) -> None:
        self.drive.command("trigger", "set_zero", repeatable=True)

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        """Recorded for this driver's checks (move_to refuses targets beyond them; jog ends at them).

        Nothing is written: the CS2RS has no documented soft limits (0x6010/0x6012 are its
        homing speed and deceleration); the machine's limit switches and the engine's
        per-sample checks protect the travel.
        """
        if not upper_mm < lower_mm:
            raise ValueError(f"upper limit {upper_mm:g} mm must be above (smaller than) lower limit {lower_mm:g} mm")
        self.travel_limits = (float(upper_mm), float(lower_mm))

    # ------------------------------------------------------------------ commissioning (foamlab probe)
    def self_checks(self) -> list[tuple[str, bool, str]]:
        """At rest: the settings and the reads that settle what the CS2RS manuals leave open."""
        ppr = int(self.drive.read("pulses_per_rev"))
        word = int(self.drive.read("status"))
        bits = self.drive.device.decode_bits("status", word)
        alarm = int(self.drive.read("alarm"))
        command, motor = int(self.drive.read("command_position")), int(self.drive.read("motor_position"))
        return [
            ("CS2RS pulses per revolution", ppr == self.pulses_per_rev,
             f"0x0001 reads {ppr}, the profile says {self.pulses_per_rev}"),
            ("CS2RS status bits", bits["enabled"] and not bits["running"] and not bits["fault"],
             f"0x1003 reads 0x{word:04X} at rest: expected enabled (bit 1), not running (bit 2), no fault (bit 0)"),
            ("CS2RS alarm", alarm == 0, f"0x2203 reads 0x{alarm:04X}"
             + (f" ({self.drive.device.meaning('alarm', alarm) or 'not in the device file'})" if alarm else "")),
            ("CS2RS position units", abs(command - motor) <= 2,
             f"0x602A (command) reads {command}, 0x602C (motor) {motor} at rest: the same unit if they agree"),
        ]

