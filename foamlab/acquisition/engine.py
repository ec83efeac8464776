"""The run state machine: run a test method on a machine, safely, losing nothing.

One worker thread owns the run:

    connect -> tare (plate in air) -> contact search -> steps of the method -> stop -> park

- Contact search: jog down slowly until the force reaches the method's preload;
  that position becomes displacement 0 (kept in software, so the machine's own
  zero and its travel limits stay valid).
- Sampling (sampling.Sampler) runs on a fixed monotonic schedule (schedule.SampleSchedule); a
  deadline whose whole period passed without a sample is counted as missed, never filled in.
- At `speedup` S (a simulated machine whose clock runs S times faster) the schedule's wall
  period is period / S and time_s = wall elapsed * S: the method's rate in machine time.
- Every sample goes to the recorder (foamlab.storage.recorder) when it arrives, then the
  safety limits (safety.Limits) are checked; a violation stops the crosshead at once.
- Every exit path (end, limit, overload, e-stop, lost link, a full disk, any exception, a
  stop request) goes through the same cleanup (_finish): stop the crosshead, close the run
  file with its status and reason, park when the exit allows it (events.PARK_AFTER).

The analysis of the run (method results, fit, diagnosis) is foamlab.pipeline's, not this.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import math
import threading
from pathlib import Path
from typing import Any, Callable

from drivers.base import DeviceConnectionLost, DeviceError, Machine
from foamlab import FoamlabError, __version__
from foamlab.acquisition.clock import WALL_CLOCK, RunClock
from foamlab.acquisition.events import (ABORTED, CONNECTING, CONTACT_SEARCH, END_ERROR, END_ESTOP, END_FAULT,
                                        END_FINISHED, END_LIMIT, END_LINK, END_STOP, END_STORAGE, FINISHED,
                                        IDLE, PARK_AFTER, PARKING, RUNNING, STOPPING, TARING, Listeners,
                                        ProgressReporter, RunAborted, RunResult)
from foamlab.acquisition.safety import (Limits, StallWatch, Stopper,
                                        check_safe_to_tare, fault_name, park)
from foamlab.acquisition.sampling import Sampler
from foamlab.acquisition.schedule import CpuWakeupLatency, raise_thread_priority
from foamlab.acquisition.settings import DEFAULT, AcquisitionSettings
from foamlab.methods import METHOD_FILE_KEY, METHOD_KEY, Method, PlannedStep, method_record
from foamlab.rundata import Specimen
from foamlab.runformat import END_KEY, PROFILE_KEY, RESOLUTION_KEY, SCHEDULE_KEY
from foamlab.storage.recorder import Recorder, RecordingFailed
from foamlab.storage.runfile import now_iso

log = logging.getLogger(__name__)



class RunEngine:
    """Run `method` on `machine` for `specimen`, recording into `out_dir`.

    `limits` default to the machine profile's [limits] (machine.profile); given limits must
    lie inside the profile's. `speedup` is the machine's clock rate relative to the wall clock
    (1 for a real machine). `connect=False` leaves the link to the caller (the window connects
    and disconnects itself). `recorder`: where the samples go (default: a Recorder on
    `out_dir`). A folder the recorder cannot write refuses the run here, before any motion.
    `clock`: what the run waits by (a virtual clock for the in-process machine: acquisition.clock).
    `settings`: the acquisition's thresholds (acquisition.settings; docs/settings.md).
    """

    def __init__(self, machine: Machine, method: Method, specimen: Specimen, out_dir: str | Path,
                 limits: Limits | None = None, speedup: float = 1.0, progress_interval_s: float = 0.25,
                 *, connect: bool = True, machine_name: str | None = None, run_name: str | None = None,
                 realtime: bool = True, recorder: Recorder | None = None, clock: RunClock = WALL_CLOCK,
                 settings: AcquisitionSettings = DEFAULT):
        self.machine, self.method, self.specimen = machine, method, specimen
        self.settings = settings
        self.speedup = float(speedup)
        self.clock = clock
        self.progress_interval_s = float(progress_interval_s)
        self.manage_connection = connect
        profile = getattr(machine, "profile", None) or {}     # drivers built from a profile carry it
        self.profile_name = str(profile.get("name") or "")
        self.machine_name = machine_name or self.profile_name or type(machine).__name__
        if not (self.speedup > 0 and math.isfinite(self.speedup)):
            raise FoamlabError(f"speedup must be a positive number, got {speedup!r}")
        if not specimen.height_mm or not specimen.height_mm > 0:
            raise FoamlabError("the specimen height must be given (mm, > 0)")
        self.limits = _limits(limits, profile)
        if method.max_speed_mm_min > self.limits.max_speed_mm_min:
            raise FoamlabError(f"method {method.name} needs {method.max_speed_mm_min:g} mm/min, above the "
                               f"speed limit {self.limits.max_speed_mm_min:g} mm/min")
        self.plan: list[PlannedStep] = method.plan(specimen.height_mm)
        self.nominal_s = sum(p.duration_s for p in self.plan)
        self.period_s = 1.0 / (method.sampling_hz * self.speedup)      # wall
        self.recorder = recorder if recorder is not None else Recorder(out_dir, run_name)
        self.recorder.check_folder()
        self.realtime = realtime
        self.scheduling = "not started"

        self._listeners = Listeners()
        self._state = IDLE
        self._stop, self._estop = threading.Event(), threading.Event()
        self._wake, self._done = threading.Event(), threading.Event()
        self._stop_reason = ""
        self._thread: threading.Thread | None = None
        self._result: RunResult | None = None
        self._stopper = Stopper(machine, self._estop, clock, settings)
        # filled by the worker
        self._start_position: float | None = None
        self._contact: float | None = None
        self._step_start_s = 0.0
        self._sampler = Sampler(machine, self.limits, self.recorder, self._listeners, period_s=self.period_s,
                                speedup=self.speedup, wake=self._wake, check_flags=self._check_flags,
                                on_sample=lambda s: self._report_progress(s.displacement_mm, s.force_N),
                                clock=clock, settings=settings)
        self._progress = ProgressReporter(self._listeners, self.plan, method.n_cycles, self.speedup,
                                          progress_interval_s, clock.now)
        self._connected_once = False

    # -- public API ------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    @property
    def path(self) -> Path | None:
        return self.recorder.path

    def add_listener(self, listener: Any) -> None:
        """`listener` may implement on_sample, on_progress, on_state, on_finished (any subset)."""
        self._listeners.add(listener)

    def start(self) -> None:
        if self._thread is not None:
            raise FoamlabError("this run has already been started; make a new RunEngine for another run")
        self._thread = threading.Thread(target=self._worker, name=f"foamlab-run-{self.method.name}", daemon=True)
        self._thread.start()

    def request_stop(self, reason: str = "stopped by the operator") -> None:
        """Stop the run (the crosshead stops, the data are kept, the run is marked aborted).

        A second request while parking stops the park too.
        """
        if not self._stop_reason:
            self._stop_reason = reason
        self._stop.set()
        self._wake.set()

    def emergency_stop(self) -> None:
        """E-stop the crosshead now, from the calling thread, then end the run (no park)."""
        self._estop.set()
        self._wake.set()
        try:
            self.machine.crosshead.emergency_stop()
        except Exception as exc:   # the worker retries in its cleanup
            log.warning("emergency stop from %s failed: %s", threading.current_thread().name, exc)

    def wait(self, timeout: float | None = None) -> RunResult | None:
        """The run's result once it has ended (None if `timeout` expired first)."""
        if not self._done.wait(timeout):
            return None
        return self._result

    def run(self) -> RunResult:
        """start() and wait(): for scripts."""
        self.start()
        while True:
            result = self.wait(0.2)
            if result is not None:
                return result

    # -- worker ----------------------------------------------------------------------
    def _set_state(self, state: str) -> None:
        self._state = state
        self._listeners.emit("on_state", state)

    def _worker(self) -> None:
        self.scheduling = raise_thread_priority() if self.realtime else "normal"
        wakeup = CpuWakeupLatency()
        if self.realtime:
            self.scheduling += f", {wakeup.hold()}"
        # A full collection walks every object the imports made (~18 ms here: three 16 Hz
        # periods at speedup 10). Frozen, they are skipped; unfrozen when the run ends.
        gc.collect()
        gc.freeze()
        try:
            end, reason = self._main_phase()
            self._finish(end, reason)
        finally:
            wakeup.release()
            gc.unfreeze()

    def _main_phase(self) -> tuple[str, str]:
        """Connect, prepare, find contact, run the plan; (END_* kind, reason) of how it ended."""
        try:
            self._set_state(CONNECTING)
            if self.manage_connection:
                self.machine.connect()
            self._stopper.link_alive = self._connected_once = True
            self._check_flags()
            self._prepare()
            self._contact_search()
            self.recorder.open(self._header())
            self._set_state(RUNNING)
            for planned in self.plan:
                self._run_step(planned)
        except RunAborted as exc:
            return exc.kind, exc.reason
        except RecordingFailed as exc:
            return END_STORAGE, str(exc)
        except DeviceConnectionLost as exc:
            self._stopper.link_alive = False
            return END_LINK, f"connection lost: {exc}"
        except DeviceError as exc:
            return END_FAULT, f"device error: {exc}"
        except FoamlabError as exc:
            return END_ERROR, str(exc)
        except ValueError as exc:  # a driver refusing a command's parameters (speed, target)
            return END_ERROR, f"command refused: {exc}"
        except Exception as exc:   # any bug still ends in a stopped machine and a kept run
            log.error("run engine failure: %s: %s", type(exc).__name__, exc)
            log.debug("run engine failure", exc_info=True)
            return END_ERROR, f"internal error: {type(exc).__name__}: {exc}"
        return END_FINISHED, ""

    def _interrupted(self) -> bool:
        return self._stop.is_set() or self._estop.is_set()

    def _check_flags(self) -> None:
        if self._estop.is_set():
            raise RunAborted(END_ESTOP, "emergency stop")
        if self._stop.is_set():
            raise RunAborted(END_STOP, self._stop_reason or "stopped by the operator")

    def _prepare(self) -> None:
        crosshead = self.machine.crosshead
        # a reply lost to a busy link is asked for again, as in every other request of the run
        status = self._command(crosshead.status)
        if status.emergency_stopped or status.fault:
            what = "emergency stop" if status.emergency_stopped else f"fault ({fault_name(self.machine)})"
            raise RunAborted(END_FAULT, f"the crosshead has a latched {what}: reset it before starting a run")
        if status.moving:
            self._command(crosshead.stop)
            self._wait_at_rest()
        self._start_position = self._command(crosshead.read_position)
        lim = self.limits
        if not lim.travel_upper_mm <= self._start_position <= lim.travel_lower_mm:
            raise RunAborted(END_LIMIT, f"the crosshead is at {self._start_position:.3f} mm, outside the travel "
                                        f"limits [{lim.travel_upper_mm:g}, {lim.travel_lower_mm:g}] mm")
        self._command(crosshead.set_travel_limits, lim.travel_upper_mm, lim.travel_lower_mm)
        self._set_state(TARING)
        # never tare a squeezed specimen (issue 18)
        self._command(check_safe_to_tare, self.machine, "tare", self.settings)
        self._command(self.machine.load_cell.tare)

    def _contact_search(self) -> None:
        """Jog down until the force reaches the preload; that position is displacement 0."""
        self._set_state(CONTACT_SEARCH)
        contact = self.method.contact
        crosshead = self.machine.crosshead
        self._sampler.restart(self._interrupted())
        self._report_progress(0.0, 0.0, immediate=True)
        reach = min(self._start_position + contact.max_search_mm, self.limits.travel_lower_mm)
        self._command(crosshead.jog, +1, contact.search_speed_mm_min)
        previous = None
        while True:
            sample = self._sampler.take(record=False)
            if sample is None:
                continue
            position, force = sample
            if force >= contact.preload_N:
                self._command(crosshead.stop)
                # the preload was crossed between the previous sample and this one
                if previous is not None and force > previous[1]:
                    frac = (contact.preload_N - previous[1]) / (force - previous[1])
                    self._contact = previous[0] + frac * (position - previous[0])
                else:
                    self._contact = position
                self._sampler.contact = self._contact
                break
            if position >= reach - self.settings.at_target_mm:
                self._command(crosshead.stop)
                raise RunAborted(END_LIMIT, f"no contact: the force stayed below the {contact.preload_N:g} N "
                                            f"preload down to {position:.2f} mm")
            previous = sample
        self._wait_at_rest()
        deepest = self._contact + self.method.max_strain * self.specimen.height_mm
        if deepest > self.limits.travel_lower_mm:
            raise RunAborted(END_LIMIT, f"the method needs travel to {deepest:.2f} mm, beyond the lower travel "
                                        f"limit {self.limits.travel_lower_mm:g} mm (contact at {self._contact:.2f} mm)")

    def _wait_at_rest(self) -> None:
        deadline = self.clock.now() + self.settings.stop_confirm_s + 5.0 / self.speedup
        while self.clock.now() < deadline:
            self._check_flags()
            status = self._sampler.read_status()   # a lost poll is tolerated as between samples
            if status is not None and not status.moving:
                return
            self.clock.wait(self._wake, 0.005)
        raise RunAborted(END_FAULT, "the crosshead did not come to rest after a stop")

    def _header(self) -> dict:
        header = {
            "method": self.method.name, "method_title": self.method.title, "machine": self.machine_name,
            "specimen": self.specimen, "started_at": now_iso(), "software": f"foamlab {__version__}",
            "sampling_hz": self.method.sampling_hz, "speedup": self.speedup,
            "preload_N": self.method.contact.preload_N, "contact_position_mm": round(self._contact, 4),
            "start_position_mm": round(self._start_position, 4), "limits": self.limits.describe(),
            "nominal_duration_s": round(self.nominal_s, 3), "scheduling": self.scheduling,
            RESOLUTION_KEY: self.machine.crosshead.position_resolution_mm,
        }
        if self.method.source:      # where the method came from (the method itself is the next key)
            header[METHOD_FILE_KEY] = str(Path(self.method.source).resolve())
        header[METHOD_KEY] = method_record(self.method)
        if self.profile_name:
            header[PROFILE_KEY] = self.profile_name
        return header

    def _run_step(self, planned: PlannedStep) -> None:
        self._sampler.step = planned
        step = planned.step
        target = self._contact + planned.end_mm
        if step.action != "dwell":
            sent = self.clock.now()
            self._command(self.machine.crosshead.move_to, target, step.speed_mm_min)
            self._sampler.waited_for_device(self.clock.now() - sent)
        # the run's own schedule (and machine clock) starts when the first step is under way;
        # the contact search had its own, whose samples are not part of the run
        if planned.index == 0:
            self._sampler.restart(self._interrupted())
        start_s = self._step_start_s = self._sampler.machine_time(self.clock.now())
        if step.action == "dwell":
            while True:
                if self._sampler.take(record=True) is not None and self.recorder.last[0] - start_s >= step.duration_s:
                    return
        watch = StallWatch(step.speed_mm_min, start_s, planned.duration_s, self.settings)
        previous = math.inf
        while True:
            sample = self._sampler.take(record=True)
            if sample is None:
                continue
            position = sample[0]
            if abs(position - target) <= self.settings.near_target_mm:
                # Done once the drive is at rest there (reversing a crosshead that is still
                # decelerating would overshoot) AND a recorded sample shows where it stopped: on
                # the target, or - for a drive that settles within its in-position window -
                # twice at the same place.
                status = self._sampler.read_status()
                if status is not None and not status.moving and (
                        abs(position - target) <= self.settings.at_target_mm
                        or (status.in_position and abs(position - previous) <= self.settings.at_target_mm)):
                    return
            previous = position
            problem = watch.check(self.recorder.last[0], position, target)
            if problem:
                status = self._sampler.read_status()   # raises for faults/limits: the better reason
                detail = f" (drive fault: {fault_name(self.machine)})" if status is not None and status.fault else ""
                raise RunAborted(END_FAULT, problem + detail)

    def _report_progress(self, disp: float, force: float, fraction: float | None = None,
                         immediate: bool = False) -> None:
        last = self.recorder.last
        self._progress.report(self._sampler.step, (last[0] if last else 0.0) - self._step_start_s, disp, force,
                              self._state, fraction, immediate)

    # -- ending ------------------------------------------------------------------------
    def _command(self, action: Callable, *args):
        return command(action, *args, attempts=self.settings.command_attempts)

    def _park(self) -> str:
        """Back to the start position; a new stop request or a limit halts it."""
        self._set_state(PARKING)
        stop_requested = self._stop.is_set()
        self._stop.clear()
        self._wake.clear()
        speed = min(self.method.park_speed_mm_min, self.limits.max_speed_mm_min)
        try:
            return park(self.machine, self._stopper, self.limits, self._start_position, speed,
                        speedup=self.speedup, poll_s=max(min(self.period_s, 0.05), 0.001), wake=self._wake,
                        interrupted=lambda: self._estop.is_set() or self._stop.is_set(), clock=self.clock)
        finally:
            if stop_requested:
                self._stop.set()

    def _finish(self, end: str, reason: str) -> None:
        """The single exit path: stop, mark and close the file, park, report. Never raises."""
        result = None
        try:
            self._set_state(STOPPING)
            # nothing to stop when the link never came up: no command ever reached the machine
            stop_note = self._stopper.stop() if self._connected_once else "never connected"
            rest_note = ""
            if self._connected_once and "failed (" not in stop_note:
                rest_note = self._stopper.confirm_at_rest()
            safety = safety_note(stop_note, rest_note, self._sampler.watch.note())
            status = FINISHED if end == END_FINISHED else ABORTED
            if status == ABORTED:
                log.info("run aborted: %s (%s)", reason, stop_note)
            timing = self._sampler.stats()
            self.recorder.finish(status, reason, safety=safety,
                                 facts={SCHEDULE_KEY: dataclasses.asdict(timing), END_KEY: end})
            park_note = "not parked"
            if self._stopper.link_alive and end in PARK_AFTER and self._start_position is not None:
                park_note = self._park()
            elif end not in PARK_AFTER:
                park_note = f"not parked after {end}: {stop_note}"
            run = self.recorder.run_data()      # the file's facts, as load_run reads them
            result = RunResult(self.recorder.path, status, reason, len(self.recorder), timing.missed, end,
                               park_note, self._contact, timing, run, safety)
            if status == FINISHED:
                last = self.recorder.last or (0.0, 0.0, 0.0)
                self._report_progress(last[1], last[2], 1.0, immediate=True)
        except Exception as exc:   # last resort: the result must exist and the waiters must wake
            log.error("run engine cleanup failed: %s: %s", type(exc).__name__, exc)
            log.debug("run engine cleanup failed", exc_info=True)
            result = RunResult(self.recorder.path, ABORTED, reason or f"cleanup failed: {exc}", len(self.recorder),
                               self._sampler.schedule.missed if self._sampler.schedule else 0, end=end)
        finally:
            if self.manage_connection:
                try:
                    self.machine.close()
                except Exception:
                    pass
            self._result = result
            self._set_state(result.status if result else ABORTED)
            self._listeners.emit("on_finished", result)
            self._done.set()


def safety_note(stop_note: str, rest_note: str, status_note: str) -> str:
    """What went wrong bringing the machine to rest, in one line ("" when nothing did)."""
    plain = stop_note in ("stopped", "emergency stopped", "never connected")
    parts = ["" if plain else stop_note, rest_note, status_note]
    return "; ".join(p for p in parts if p)


def command(action: Callable, *args, attempts: int = DEFAULT.command_attempts):
    """Send an idempotent command (move, jog, stop, tare, limits) or query (status, position),
    retried on a lost reply; what it returns.

    The driver already retried the request itself; a command whose reply went missing may
    still have been done, and sending it again does the same thing. A lost link is not
    retried here (cleanup reconnects).
    """
    for attempt in range(attempts):
        try:
            return action(*args)
        except DeviceConnectionLost:
            raise
        except DeviceError as exc:
            if attempt == attempts - 1:
                raise
            log.warning("%s failed (%s); sending it again", getattr(action, "__name__", "command"), exc)


def _limits(limits: Limits | None, profile: dict) -> Limits:
    """The limits a run obeys: the profile's, or tighter ones given by the caller."""
    profile_limits = Limits.from_profile(profile) if profile.get("limits") else None
    if limits is None:
        if profile_limits is None:
            raise FoamlabError("no safety limits: pass limits or use a machine built from a profile")
        return profile_limits
    if profile_limits is not None:
        limits.within(profile_limits)
    return limits
