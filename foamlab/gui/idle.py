"""The idle machine's commands from the left-hand panel: jog, stop, return to start, reset
the e-stop, zero the position, tare / zero the force (refused in words on a loaded cell,
foamlab.acquisition.safety). Each goes to the machine on the MachineLink's thread; what
happened is said through the window's status line."""

from __future__ import annotations

from collections.abc import Callable

from foamlab import FoamlabError
from foamlab.acquisition.safety import check_safe_to_tare, shift_contact
from foamlab.gui.background import BackgroundQueue
from foamlab.gui.controls import ControlPanel
from foamlab.gui.machine_link import MachineLink


def _zero_position(machine) -> None:
    """Make the present position the machine's zero; the remembered contact point moves with it."""
    position = machine.crosshead.read_position()
    machine.crosshead.set_zero()
    shift_contact(machine, -position)


def _tare_if_safe(machine, what: str) -> None:
    """On the machine thread: tare ("tare") or zero ("zero force") unless the cell is loaded."""
    check_safe_to_tare(machine, what)
    if what == "tare":
        machine.load_cell.tare()
    else:
        machine.load_cell.zero()


class IdleCommands:
    """`status(text, error=False, timeout_ms=0)`: the window's status line; `start_mm()`:
    where "Return to start" goes (the last run's start, 0 mm before any run); `estops`: the
    window's e-stop queue (its own thread, so an e-stop never waits behind a slow link call)."""

    def __init__(self, link: MachineLink, controls: ControlPanel, status: Callable[..., None],
                 start_mm: Callable[[], float], estops: BackgroundQueue) -> None:
        self.link, self.controls, self._status, self._start_mm = link, controls, status, start_mm
        self.estops = estops

    def move_speed(self, what: str) -> float | None:
        """The jog speed, capped by the speed limit entered; None (and why) if an entry is wrong."""
        jog_speed, limits_form = self.controls.jog_speed, self.controls.limits_form
        try:
            problem = jog_speed.problem()
            if problem:
                raise FoamlabError(problem)
            speed = jog_speed.value()
            if limits_form.profile_limits is not None:   # the speed limit entered applies too
                speed = min(speed, limits_form.values()["max_speed_mm_min"])
        except FoamlabError as exc:
            self._status(f"{what} refused: {exc}", error=True)
            return None
        return speed

    def jog(self, direction: int) -> None:
        speed = self.move_speed("jog")
        if speed is not None:
            self.link.call("jog", lambda m: m.crosshead.jog(direction, speed))

    def stop_motion(self) -> None:
        self.link.call("stop", lambda m: m.crosshead.stop())

    def return_to_start(self) -> None:
        target, speed = self._start_mm(), self.move_speed("return to start")
        if speed is None:
            return
        self.link.call("return to start", lambda m: m.crosshead.move_to(target, speed))
        self._status(f"returning to the start position, {target:.2f} mm, at {speed:g} mm/min (Stop or Esc halts)")

    def reset_estop(self) -> None:
        """Reset once every e-stop clicked before it has been sent: an e-stop still waiting for the
        link's lock (the run's last requests hold it) would land after the reset and undo it (ci 63:
        the reset said "may move again", the drive stayed stopped)."""
        self.estops.submit(lambda: None, lambda _: self._reset_estop_now())

    def _reset_estop_now(self) -> None:
        conn = self.link.connection
        if conn is not None:     # the red EMERGENCY STOP line is replaced once the drive is reset
            self.link.submit(conn.machine.crosshead.reset_fault,
                             lambda _: self._status("e-stop reset: the crosshead may move again", timeout_ms=10_000),
                             lambda msg: self._status(f"reset e-stop failed: {msg}", error=True))

    def zero_position(self) -> None:
        self.link.call("zero position", _zero_position)

    def tare(self, what: str) -> None:
        """Tare ("tare") or zero ("zero force") the load cell, refused in words while it carries a load."""
        conn = self.link.connection
        if conn is None:
            return

        def failed(message: str) -> None:
            self._status(message if message.startswith(f"{what} refused") else f"{what} failed: {message}",
                         error=True)

        self.link.submit(lambda: _tare_if_safe(conn.machine, what),
                         lambda _: self._status(f"{what}: done", timeout_ms=5000), failed)
