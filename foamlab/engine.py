"""The run engine: run a test method on a machine, safely, losing nothing.

One worker thread owns the run:

    connect -> tare (plate in air) -> contact search -> steps of the method -> stop -> park

- Contact search: jog down slowly until the force reaches the method's preload;
  that position becomes displacement 0 (kept in software, so the machine's own
  zero and its travel limits stay valid).
- Sampling runs on a fixed monotonic schedule, deadline_k = t0 + k * period
  (SampleSchedule). A deadline whose whole period passed without a sample (a slow
  request, a failed read) is counted as missed; nothing is interpolated or hidden.
  Each sample keeps its request round-trip time and its lateness.
- At `speedup` S (a simulated machine whose clock runs S times faster) the
  schedule's wall period is period / S and time_s = wall elapsed * S, so the run
  is sampled at the method's rate in machine time.
- Every sample goes to disk when it arrives (foamlab.storage.runfile.RunWriter).
- Safety limits (force, travel, speed; `Limits`) are checked on every sample and
  on the crosshead's status; a violation stops the crosshead at once and the run
  is kept, marked aborted with the reason.
- Every exit path (end, limit, overload, e-stop, lost link, any exception, a stop
  request) goes through the same cleanup: stop the crosshead (stop, else
  emergency stop; cleanup never raises), mark and close the run file, park the
  crosshead at its start position when the link is alive and the exit was not an
  e-stop or a fault, then fit finished runs when foamlab.identification exists.

Listeners (GUI, CLI) receive on_sample / on_progress / on_state / on_finished,
called from the worker thread: keep them short (queue the data for a GUI).
"""

from __future__ import annotations

import datetime as _dt
import importlib
import importlib.util
import logging
import gc
import math
import os
import re
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivers.base import CrossheadStatus, DeviceConnectionLost, DeviceError, Machine
from foamlab import FoamlabError, __version__
from foamlab.methods import Method, MethodResults, PlannedStep
from foamlab.rundata import RunData, Specimen
from foamlab.safety import check_safe_to_tare

log = logging.getLogger(__name__)

# States, in the order a run goes through them.
IDLE, CONNECTING, TARING, CONTACT_SEARCH, RUNNING = "idle", "connecting", "taring", "contact_search", "running"
STOPPING, PARKING, FITTING, FINISHED, ABORTED = "stopping", "parking", "fitting", "finished", "aborted"

# Why a run ended. The crosshead is parked only after FINISHED, STOP and LIMIT exits:
# after an e-stop, an overload or a device fault the operator looks first.
END_FINISHED, END_STOP, END_LIMIT = "finished", "stop", "limit"
END_ESTOP, END_OVERLOAD, END_FAULT, END_LINK, END_ERROR = "estop", "overload", "fault", "link", "error"
PARK_AFTER = (END_FINISHED, END_STOP, END_LIMIT)

#: A move is complete when the drive is at rest and in position (or this close to the
#: target: drives report um)...
AT_TARGET_MM = 0.003
#: ...which is asked once the position is this close to the target.
NEAR_TARGET_MM = 0.05
#: Consecutive failed reads (after the driver's own retries) tolerated before aborting.
MAX_FAILED_READS = 3
#: Attempts for an idempotent command whose reply was lost (after the driver's retries).
COMMAND_ATTEMPTS = 3
#: Crosshead status is read between samples when there is slack, at most this often (wall s)...
STATUS_INTERVAL_S = 0.1
#: ...and at least this often even without slack (wall s; may cost a sample, counted as missed).
STATUS_FORCED_INTERVAL_S = 1.0
#: Stall: over this window (machine s) the crosshead moved < STALL_FRACTION of the commanded travel.
STALL_WINDOW_S = 1.0
STALL_FRACTION = 0.2
#: How long to wait for the crosshead to come to rest after a stop (wall s).
STOP_CONFIRM_S = 2.0
#: How long cleanup keeps trying to send stop / emergency stop over a failing link (wall s).
STOP_RETRY_S = 3.0


class RunAborted(Exception):
    """Internal: ends the run's main phase with a reason (kind is one of END_*)."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind, self.reason = kind, reason


# --------------------------------------------------------------------------- data types

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


@dataclass(frozen=True)
class Sample:
    index: int
    time_s: float             # machine time since the first step (virtual at speedup > 1)
    displacement_mm: float    # position - contact zero, compression positive
    force_N: float
    rtt_ms: float             # wall round-trip time of the sample's request(s)
    lateness_ms: float        # wall delay between the deadline and the request
    position_mm: float        # machine position
    cycle: int
    step: int


@dataclass(frozen=True)
class Progress:
    cycle: int
    n_cycles: int
    fraction: float           # 0..1 of the method's nominal duration
    displacement_mm: float
    force_N: float
    time_left_s: float        # wall seconds
    state: str


@dataclass(frozen=True)
class ScheduleStats:
    period_s: float           # wall period of the schedule
    samples: int
    missed: int
    failed_reads: int
    missed_waiting_device: int   # of `missed`: deadlines that passed only because a request was out
    lateness_p50_ms: float
    lateness_p99_ms: float
    lateness_max_ms: float
    rtt_p50_ms: float
    rtt_p99_ms: float
    rtt_max_ms: float
    work_p99_ms: float = float("nan")   # the engine's own work per sample (device waits excluded)
    work_max_ms: float = float("nan")

    @classmethod
    def from_arrays(cls, period_s: float, lateness_ms, rtt_ms, missed: int, failed: int,
                    missed_waiting_device: int = 0, work_ms=()) -> "ScheduleStats":
        def q(a, p):
            return float(np.percentile(a, p)) if len(a) else float("nan")
        lat, rtt, work = (np.asarray(a, float) for a in (lateness_ms, rtt_ms, work_ms))
        return cls(period_s, len(lat), missed, failed, missed_waiting_device, q(lat, 50), q(lat, 99),
                   q(lat, 100), q(rtt, 50), q(rtt, 99), q(rtt, 100), q(work, 99), q(work, 100))

    @property
    def missed_by_engine(self) -> int:
        """Deadlines the engine's own work lost: they would have passed with instant replies."""
        return self.missed - self.missed_waiting_device


@dataclass
class RunResult:
    path: Path | None         # the run file (None when the run ended before contact)
    status: str               # finished | aborted
    reason: str               # why it was aborted ("" when finished)
    n_samples: int
    missed: int
    fit: Any = None           # foamlab.identification FitResult, when fitted
    results: MethodResults | None = None
    fit_error: str = ""
    fit_path: Path | None = None
    end: str = END_FINISHED   # END_* kind
    park: str = ""            # what happened to the crosshead after the run
    contact_position_mm: float | None = None
    timing: ScheduleStats | None = None
    run: RunData | None = None

    @property
    def ok(self) -> bool:
        return self.status == FINISHED


# --------------------------------------------------------------------------- schedule

class SampleSchedule:
    """Deadlines t0 + k * period on the monotonic clock.

    `next()` blocks until the next deadline (or until `wake` is set) and returns
    (k, lateness_s). A deadline whose whole period has passed before its sample
    could start is skipped and counted in `missed`: sample k is taken in
    [deadline_k, deadline_k+1) or not at all.

    The caller reports the wall time it spent waiting for the device (`waited_for_device`), so
    that each miss is attributed: `missed_waiting_device` counts the deadlines that would not
    have passed had the device answered at once (a stalled reply, a failed read), the rest are
    the caller's own (`missed - missed_waiting_device`): its work between samples (`work_s`,
    device waits excluded) or a stall of the computer while it worked.
    """

    def __init__(self, period_s: float, start: float | None = None,
                 clock: Callable[[], float] = time.monotonic, wake: threading.Event | None = None):
        if not period_s > 0:
            raise ValueError("the sampling period must be > 0")
        self.period = float(period_s)
        self.clock = clock
        self.t0 = clock() if start is None else start
        self.k = 0
        self.missed = 0
        self.missed_waiting_device = 0
        self._device_s = 0.0          # waited for the device since the last next()
        self._returned = None         # when next() last returned a deadline
        self.work_s: list[float] = []  # per sample: wall time between next()s minus device waits
        self._wake = wake or threading.Event()

    def deadline(self, k: int) -> float:
        return self.t0 + k * self.period

    def miss(self) -> None:
        """The sample of the deadline just returned by next() failed (the device's doing)."""
        self.missed += 1
        self.missed_waiting_device += 1

    def waited_for_device(self, seconds: float) -> None:
        """The caller spent `seconds` (wall) in a request to the device."""
        self._device_s += max(0.0, seconds)

    def next(self) -> tuple[int, float] | None:
        """Wait for the next deadline; None when woken early (check your stop flags)."""
        deadline = self.deadline(self.k)
        now = self.clock()
        if self._returned is not None:
            self.work_s.append(max(0.0, now - self._returned - self._device_s))
        self._returned = None
        while now < deadline:
            if self._wake.wait(deadline - now):
                return None
            now = self.clock()
        behind = int((now - deadline) // self.period)
        if behind > 0:
            without_device = max(0, int((now - self._device_s - deadline) // self.period))
            self.missed += behind
            self.missed_waiting_device += behind - without_device
            self.k += behind
            deadline = self.deadline(self.k)
        self._device_s = 0.0
        self._returned = now
        k = self.k
        self.k += 1
        return k, now - deadline

    def slack(self) -> float:
        """Wall seconds until the next deadline."""
        return self.deadline(self.k) - self.clock()


# --------------------------------------------------------------------------- durability

class FileSyncer:
    """fsync a file every `interval_s` from a background thread (a power cut loses at most that).

    fsync works on the file (inode), whatever descriptor wrote it, so this thread opens its
    own read-only descriptor and the writer never waits for the disk.
    """

    def __init__(self, path: Path, interval_s: float = 0.5):
        self._fd = os.open(path, os.O_RDONLY)
        self._interval = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="foamlab-run-fsync", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(self._interval):
            try:
                os.fsync(self._fd)
            except OSError as exc:
                log.warning("fsync of the run file failed: %s", exc)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        try:
            os.close(self._fd)
        except OSError:
            pass


# --------------------------------------------------------------------------- engine

#: Real-time priority asked for the worker thread (Linux SCHED_FIFO, low priority: above
#: normal processes, below the kernel's own real-time threads).
REALTIME_PRIORITY = 10


def raise_thread_priority(priority: int = REALTIME_PRIORITY) -> str:
    """Give the calling thread SCHED_FIFO priority when the OS allows it; say what we got.

    On a busy computer an ordinary thread may wake several ms after its deadline;
    a SCHED_FIFO thread wakes within ~0.1 ms. It needs CAP_SYS_NICE or an rtprio
    limit (/etc/security/limits.conf); without it the run proceeds at normal priority
    (and the schedule statistics show the difference). The thread sleeps between
    samples and blocks on I/O, so it cannot starve the machine.
    """
    setter = getattr(os, "sched_setscheduler", None)
    if setter is None:
        return "normal (no SCHED_FIFO on this OS)"
    try:
        setter(0, os.SCHED_FIFO, os.sched_param(priority))   # pid 0: the calling thread (Linux)
    except (OSError, ValueError) as exc:
        return f"normal (SCHED_FIFO refused: {exc.strerror if isinstance(exc, OSError) else exc})"
    return f"SCHED_FIFO {priority}"


class CpuWakeupLatency:
    """Hold a Linux PM QoS request for zero CPU wake-up latency while a run samples.

    An idle CPU sleeps in a state it takes time to leave - on a virtual machine a halted
    virtual CPU waits for its hypervisor: measured here, the 16 Hz x S deadlines and the
    device's replies then came up to ~20 ms late while the computer was otherwise idle.
    With the request held (the kernel's /dev/cpu_dma_latency: it lasts while the file is
    open; the method cyclictest uses) idle CPUs poll instead. It costs power during a run
    only; it needs root (or a udev rule for the file) and is skipped without.
    """

    PATH = "/dev/cpu_dma_latency"

    def __init__(self) -> None:
        self._fd: int | None = None

    def hold(self) -> str:
        try:
            fd = os.open(self.PATH, os.O_WRONLY)
        except OSError as exc:
            return f"CPU idle states as configured ({exc.strerror})"
        try:
            os.write(fd, (0).to_bytes(4, sys.byteorder))
        except OSError as exc:
            os.close(fd)
            return f"CPU idle states as configured ({exc.strerror})"
        self._fd = fd
        return "CPU wake-up latency 0 us"

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _now_iso() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "run"


class RunEngine:
    """Run `method` on `machine` for `specimen`, writing into `out_dir`.

    `limits` default to the machine profile's [limits] (machine.profile); given
    limits must lie inside the profile's. `speedup` is the machine's clock rate
    relative to the wall clock (1 for a real machine). `connect=False` leaves the
    link to the caller (the GUI connects and disconnects itself); otherwise the
    engine connects and closes it. `fit=False` skips the automatic fit.
    """

    def __init__(self, machine: Machine, method: Method, specimen: Specimen, out_dir: str | Path,
                 limits: Limits | None = None, speedup: float = 1.0, progress_interval_s: float = 0.25,
                 fit: bool = True, *, connect: bool = True, machine_name: str | None = None,
                 run_name: str | None = None, realtime: bool = True):
        self.machine = machine
        self.method = method
        self.specimen = specimen
        self.out_dir = Path(out_dir)
        self.speedup = float(speedup)
        self.progress_interval_s = float(progress_interval_s)
        self.fit_enabled = fit
        self.manage_connection = connect
        profile = getattr(machine, "profile", None) or {}
        self.machine_name = machine_name or profile.get("name") or type(machine).__name__
        if not (self.speedup > 0 and math.isfinite(self.speedup)):
            raise FoamlabError(f"speedup must be a positive number, got {speedup!r}")
        if not specimen.height_mm or not specimen.height_mm > 0:
            raise FoamlabError("the specimen height must be given (mm, > 0)")
        profile_limits = Limits.from_profile(profile) if profile.get("limits") else None
        if limits is None:
            if profile_limits is None:
                raise FoamlabError("no safety limits: pass limits or use a machine built from a profile")
            limits = profile_limits
        elif profile_limits is not None:
            limits.within(profile_limits)
        self.limits = limits
        if method.max_speed_mm_min > limits.max_speed_mm_min:
            raise FoamlabError(f"method {method.name} needs {method.max_speed_mm_min:g} mm/min, above the "
                               f"speed limit {limits.max_speed_mm_min:g} mm/min")
        self.plan: list[PlannedStep] = method.plan(specimen.height_mm)
        self.nominal_s = sum(p.duration_s for p in self.plan)
        self.period_s = 1.0 / (method.sampling_hz * self.speedup)      # wall
        self.run_name = run_name
        self.realtime = realtime
        self.scheduling = "not started"

        self._listeners: list[Any] = []
        self._state = IDLE
        self._stop = threading.Event()
        self._estop = threading.Event()
        self._wake = threading.Event()
        self._done = threading.Event()
        self._stop_reason = ""
        self._thread: threading.Thread | None = None
        self._result: RunResult | None = None
        self._listener_errors: set[tuple[int, str]] = set()

        # filled by the worker
        self._writer = None
        self._syncer: FileSyncer | None = None
        self._path: Path | None = None
        self._start_position: float | None = None
        self._contact: float | None = None
        self._t0 = 0.0
        self._times: list[float] = []
        self._disp: list[float] = []
        self._force: list[float] = []
        self._rtt: list[float] = []
        self._late: list[float] = []
        self._failed_reads = 0
        self._consecutive_failures = 0
        self._schedule: SampleSchedule | None = None
        self._last_status = 0.0
        self._status_rtt = 0.0
        self._step: PlannedStep | None = None
        self._step_start_s = 0.0
        self._last_progress = -math.inf
        self._link_alive = False
        self._connected_once = False
        self._started_at = ""

    # -- public API ------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    @property
    def path(self) -> Path | None:
        return self._path

    def add_listener(self, listener: Any) -> None:
        """`listener` may implement on_sample, on_progress, on_state, on_finished (any subset)."""
        self._listeners.append(listener)

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

    # -- listeners -------------------------------------------------------------------
    def _emit(self, name: str, *args) -> None:
        for listener in self._listeners:
            handler = getattr(listener, name, None)
            if handler is None:
                continue
            try:
                handler(*args)
            except Exception:
                # A broken display must not abort a test in progress; say it once per handler.
                key = (id(listener), name)
                if key not in self._listener_errors:
                    self._listener_errors.add(key)
                    log.error("listener %r.%s failed (further errors of it are not logged)", listener, name,
                              exc_info=True)

    def _set_state(self, state: str) -> None:
        self._state = state
        self._emit("on_state", state)

    # -- time --------------------------------------------------------------------------
    def _machine_time(self, wall: float) -> float:
        return (wall - self._t0) * self.speedup

    # -- worker ----------------------------------------------------------------------
    def _worker(self) -> None:
        end, reason = END_FINISHED, ""
        self.scheduling = raise_thread_priority() if self.realtime else "normal"
        wakeup = CpuWakeupLatency()
        if self.realtime:
            self.scheduling += f", {wakeup.hold()}"
        # A full collection walks every object the imports made (numpy, scipy, pymodbus:
        # ~18 ms here, three 16 Hz periods at speedup 10). Frozen, they are skipped; the
        # run itself makes few container objects. Unfrozen when the run ends.
        gc.collect()
        gc.freeze()
        try:
            self._set_state(CONNECTING)
            if self.manage_connection:
                self.machine.connect()
            self._link_alive = self._connected_once = True
            self._check_flags()
            self._prepare()
            self._contact_search()
            self._open_run_file()
            self._set_state(RUNNING)
            for planned in self.plan:
                self._run_step(planned)
        except RunAborted as exc:
            end, reason = exc.kind, exc.reason
        except DeviceConnectionLost as exc:
            end, reason = END_LINK, f"connection lost: {exc}"
            self._link_alive = False
        except DeviceError as exc:
            end, reason = END_FAULT, f"device error: {exc}"
        except FoamlabError as exc:
            end, reason = END_ERROR, str(exc)
        except ValueError as exc:  # a driver refusing a command's parameters (speed, target)
            end, reason = END_ERROR, f"command refused: {exc}"
        except Exception as exc:   # any bug still ends in a stopped machine and a kept run
            log.error("run engine failure: %s: %s", type(exc).__name__, exc)
            log.debug("run engine failure", exc_info=True)
            end, reason = END_ERROR, f"internal error: {type(exc).__name__}: {exc}"
        try:
            self._finish(end, reason)
        finally:
            wakeup.release()
            gc.unfreeze()

    def _check_flags(self) -> None:
        if self._estop.is_set():
            raise RunAborted(END_ESTOP, "emergency stop")
        if self._stop.is_set():
            raise RunAborted(END_STOP, self._stop_reason or "stopped by the operator")

    def _command(self, action: Callable, *args) -> None:
        """Send an idempotent command (move, jog, stop, tare, limits), retried on a lost reply.

        The driver already retried the request itself; a command whose reply went missing
        may still have been done, and sending it again does the same thing. A lost link is
        not retried here (cleanup reconnects).
        """
        for attempt in range(COMMAND_ATTEMPTS):
            try:
                action(*args)
                return
            except DeviceConnectionLost:
                raise
            except DeviceError as exc:
                if attempt == COMMAND_ATTEMPTS - 1:
                    raise
                log.warning("%s failed (%s); sending it again", getattr(action, "__name__", "command"), exc)

    def _prepare(self) -> None:
        crosshead = self.machine.crosshead
        status = crosshead.status()
        if status.emergency_stopped or status.fault:
            what = "emergency stop" if status.emergency_stopped else f"fault ({self._fault_name()})"
            raise RunAborted(END_FAULT, f"the crosshead has a latched {what}: reset it before starting a run")
        if status.moving:
            self._command(crosshead.stop)
            self._wait_at_rest()
        self._start_position = crosshead.read_position()
        lim = self.limits
        if not lim.travel_upper_mm <= self._start_position <= lim.travel_lower_mm:
            raise RunAborted(END_LIMIT, f"the crosshead is at {self._start_position:.3f} mm, outside the travel "
                                        f"limits [{lim.travel_upper_mm:g}, {lim.travel_lower_mm:g}] mm")
        self._command(crosshead.set_travel_limits, lim.travel_upper_mm, lim.travel_lower_mm)
        self._set_state(TARING)
        self._command(check_safe_to_tare, self.machine)   # never tare a squeezed specimen (issue 18)
        self._command(self.machine.load_cell.tare)

    def _new_schedule(self) -> SampleSchedule:
        self._wake.clear()
        if self._stop.is_set() or self._estop.is_set():
            self._wake.set()
        return SampleSchedule(self.period_s, wake=self._wake)

    def _contact_search(self) -> None:
        """Jog down until the force reaches the preload; that position is displacement 0."""
        self._set_state(CONTACT_SEARCH)
        contact = self.method.contact
        crosshead = self.machine.crosshead
        self._schedule = self._new_schedule()
        self._t0 = self._schedule.t0
        self._emit_progress(0.0, 0.0, immediate=True)
        reach = min(self._start_position + contact.max_search_mm, self.limits.travel_lower_mm)
        self._command(crosshead.jog, +1, contact.search_speed_mm_min)
        previous = None
        while True:
            sample = self._acquire(record=False)
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
                break
            if position >= reach - AT_TARGET_MM:
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
        deadline = time.monotonic() + STOP_CONFIRM_S + 5.0 / self.speedup
        while time.monotonic() < deadline:
            self._check_flags()
            status = self.machine.crosshead.status()
            self._check_crosshead_status(status)
            if not status.moving:
                return
            self._wake.wait(0.005)
        raise RunAborted(END_FAULT, "the crosshead did not come to rest after a stop")

    def _open_run_file(self) -> None:
        from foamlab.storage.runfile import RunWriter   # noqa: PLC0415 (storage is optional at import)

        self.out_dir.mkdir(parents=True, exist_ok=True)
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        name = self.run_name or f"{stamp}_{_safe_name(self.specimen.label or 'specimen')}_{self.method.name}"
        path = self.out_dir / f"{name}.csv"
        n = 2
        while path.exists():
            path = self.out_dir / f"{name}-{n}.csv"
            n += 1
        self._started_at = _now_iso()
        # Each sample is flushed to the OS as it is written (a crash of this process loses
        # nothing); the fsync to the disk (5-10 ms here) runs on its own thread so that it
        # never delays a sample (FileSyncer).
        self._writer = RunWriter(path, self._header(), fsync_interval_s=math.inf)
        self._path = path
        self._syncer = FileSyncer(path)

    def _header(self) -> dict:
        lim = self.limits
        return {
            "method": self.method.name,
            "method_title": self.method.title,
            "machine": self.machine_name,
            "specimen": self.specimen,
            "started_at": self._started_at,
            "software": f"foamlab {__version__}",
            "sampling_hz": self.method.sampling_hz,
            "speedup": self.speedup,
            "preload_N": self.method.contact.preload_N,
            "contact_position_mm": round(self._contact, 4),
            "start_position_mm": round(self._start_position, 4),
            "limits": f"force {lim.force_N:g} N, travel [{lim.travel_upper_mm:g}, {lim.travel_lower_mm:g}] mm, "
                      f"speed {lim.max_speed_mm_min:g} mm/min",
            "nominal_duration_s": round(self.nominal_s, 3),
            "scheduling": self.scheduling,
        }

    def _run_step(self, planned: PlannedStep) -> None:
        self._step = planned
        step = planned.step
        crosshead = self.machine.crosshead
        target = self._contact + planned.end_mm
        if step.action != "dwell":
            sent = time.monotonic()
            self._command(crosshead.move_to, target, step.speed_mm_min)
            if self._schedule is not None:
                self._schedule.waited_for_device(time.monotonic() - sent)
        # the run's own schedule (and machine clock) starts when the first step is under way;
        # the contact search had its own, whose samples are not part of the run
        if planned.index == 0:
            self._schedule = self._new_schedule()
            self._t0 = self._schedule.t0
            self._failed_reads = 0
        start_s = self._machine_time(time.monotonic())
        self._step_start_s = start_s
        if step.action == "dwell":
            while True:
                sample = self._acquire(record=True)
                if sample is not None and self._times[-1] - start_s >= step.duration_s:
                    return
        expected_s = planned.duration_s
        window: list[tuple[float, float]] = []
        previous = math.inf
        while True:
            sample = self._acquire(record=True)
            if sample is None:
                continue
            position = sample[0]
            now_s = self._times[-1]
            if abs(position - target) <= NEAR_TARGET_MM:
                # Done once the drive is at rest there (reversing a crosshead that is still
                # decelerating would overshoot; a drive may fault on that) AND a recorded
                # sample shows where it stopped: on the target, or - for a drive that settles
                # within its in-position window - twice at the same place.
                status = self._read_status()
                if status is not None and not status.moving and (
                        abs(position - target) <= AT_TARGET_MM
                        or (status.in_position and abs(position - previous) <= AT_TARGET_MM)):
                    return
            previous = position
            window.append((now_s, position))
            while window and window[0][0] < now_s - STALL_WINDOW_S:
                window.pop(0)
            elapsed = now_s - start_s
            if elapsed > 2 * STALL_WINDOW_S and len(window) >= 3 and window[-1][0] - window[0][0] >= 0.8 * STALL_WINDOW_S:
                moved = abs(window[-1][1] - window[0][1])
                commanded = step.speed_mm_min / 60.0 * (window[-1][0] - window[0][0])
                if moved < STALL_FRACTION * commanded:
                    self._stalled(step.speed_mm_min, moved, window[-1][0] - window[0][0])
            if elapsed > 1.25 * expected_s + 5.0:
                self._stalled(step.speed_mm_min, abs(position - target), elapsed, timeout=True)

    def _stalled(self, speed: float, moved: float, over_s: float, timeout: bool = False) -> None:
        status = self._read_status()   # raises for faults/limits
        detail = f" (drive fault: {self._fault_name()})" if status is not None and status.fault else ""
        if timeout:
            raise RunAborted(END_FAULT, f"crosshead did not reach its target: {moved:.3f} mm short after "
                                        f"{over_s:.1f} s{detail}")
        raise RunAborted(END_FAULT, f"crosshead stalled: commanded {speed:g} mm/min, moved {moved:.3f} mm "
                                    f"in {over_s:.1f} s{detail}")

    def _fault_name(self) -> str:
        """The drive's fault, named when the driver can tell (Modbus fault code), else generic."""
        reason = getattr(self.machine.crosshead, "fault_reason", None)
        if reason is not None:
            try:
                return reason()
            except Exception:
                pass
        return "latched by the drive"

    # -- sampling ----------------------------------------------------------------------
    def _acquire(self, record: bool) -> tuple[float, float] | None:
        """Take the next scheduled sample: (position, force), or None when woken/failed."""
        schedule = self._schedule
        slot = schedule.next()
        self._check_flags()
        if slot is None:
            return None
        _, lateness = slot
        t_request = time.monotonic()
        try:
            reading = self.machine.read_sample()
        except DeviceConnectionLost:
            raise
        except DeviceError as exc:
            schedule.waited_for_device(time.monotonic() - t_request)
            self._failed_reads += 1
            self._consecutive_failures += 1
            schedule.miss()
            if self._consecutive_failures > MAX_FAILED_READS:
                raise RunAborted(END_FAULT, f"device not answering: {exc}") from None
            log.warning("sample failed (%d in a row): %s", self._consecutive_failures, exc)
            return None
        t_done = time.monotonic()
        schedule.waited_for_device(t_done - t_request)
        self._consecutive_failures = 0
        position, force = reading.position_mm, reading.force_N
        # the sample goes to disk first (also the one that crosses a limit), then the limits
        # are checked (an abort stops the crosshead at once), then the listeners hear of it
        # stamped with the instant the driver says both values describe (drivers.base.Machine.read_sample)
        instant = getattr(reading, "time", None) or (t_request + t_done) / 2
        sample = self._store(instant, position, force, (t_done - t_request) * 1e3,
                             lateness * 1e3) if record else None
        self._check_limits(position, force, reading.load_cell_status)
        if sample is not None:
            self._notify(sample)
        self._maybe_read_status()
        return position, force

    def _check_limits(self, position: float, force: float, status) -> None:
        lim = self.limits
        if status is not None and status.over_range:
            raise RunAborted(END_OVERLOAD, f"load cell overload (over-range) at {force:.1f} N")
        if force >= lim.force_N:
            raise RunAborted(END_LIMIT, f"force limit {lim.force_N:g} N reached ({force:.1f} N)")
        if position > lim.travel_lower_mm + AT_TARGET_MM or position < lim.travel_upper_mm - AT_TARGET_MM:
            raise RunAborted(END_LIMIT, f"travel limit: crosshead at {position:.3f} mm, outside "
                                        f"[{lim.travel_upper_mm:g}, {lim.travel_lower_mm:g}] mm")

    def _store(self, wall: float, position: float, force: float, rtt_ms: float, late_ms: float) -> Sample:
        # rounded far below the instruments' resolution: keeps the float noise of the
        # subtraction (0.015000000000000568) out of the file
        t = round(self._machine_time(wall), 6)
        disp = round(position - self._contact, 6)
        force = round(force, 6)           # float32 registers widen to 0.03999999910593033
        rtt_ms = round(rtt_ms, 3)
        index = len(self._times)
        self._times.append(t)
        self._disp.append(disp)
        self._force.append(force)
        self._rtt.append(rtt_ms)
        self._late.append(late_ms)
        self._writer.write_sample(t, disp, force, rtt_ms)
        step = self._step
        return Sample(index, t, disp, force, rtt_ms, late_ms, position,
                      step.step.cycle if step else 0, step.index if step else -1)

    def _notify(self, sample: Sample) -> None:
        if self._listeners:
            self._emit("on_sample", sample)
        self._emit_progress(sample.displacement_mm, sample.force_N)

    def _emit_progress(self, disp: float, force: float, fraction: float | None = None,
                       immediate: bool = False) -> None:
        now = time.monotonic()
        if not immediate and now - self._last_progress < self.progress_interval_s:
            return
        self._last_progress = now
        step = self._step
        if fraction is None:
            if step is None:
                fraction = 0.0
            else:
                done = sum(p.duration_s for p in self.plan[:step.index])
                in_step = max(0.0, (self._times[-1] if self._times else 0.0) - self._step_start_s)
                fraction = (done + min(in_step, step.duration_s)) / self.nominal_s if self.nominal_s else 1.0
        left = max(0.0, (1.0 - fraction) * self.nominal_s / self.speedup)
        cycle = step.step.cycle if step else 0
        self._emit("on_progress", Progress(cycle, self.method.n_cycles, min(max(fraction, 0.0), 1.0),
                                           disp, force, left, self._state))

    # -- crosshead status ----------------------------------------------------------------
    def _maybe_read_status(self) -> None:
        now = time.monotonic()
        since = now - self._last_status
        if since < STATUS_INTERVAL_S:
            return
        # between samples only when the request fits before the next deadline, unless overdue
        if since < STATUS_FORCED_INTERVAL_S and self._schedule.slack() < 1.5 * self._status_rtt + 1e-4:
            return
        self._read_status()

    def _read_status(self) -> CrossheadStatus | None:
        t = time.monotonic()
        try:
            status = self.machine.crosshead.status()
        except DeviceConnectionLost:
            raise
        except DeviceError as exc:
            log.warning("crosshead status failed: %s", exc)
            return None
        done = time.monotonic()
        if self._schedule is not None:
            self._schedule.waited_for_device(done - t)
        self._status_rtt = 0.8 * self._status_rtt + 0.2 * (done - t) if self._status_rtt else done - t
        self._last_status = done
        self._check_crosshead_status(status)
        return status

    def _check_crosshead_status(self, status: CrossheadStatus) -> None:
        if status.emergency_stopped:
            raise RunAborted(END_ESTOP, "emergency stop on the machine")
        if status.fault:
            raise RunAborted(END_FAULT, f"crosshead fault: {self._fault_name()}")
        if status.lower_limit:
            raise RunAborted(END_LIMIT, "crosshead reached its lower travel limit")
        if status.upper_limit:
            raise RunAborted(END_LIMIT, "crosshead reached its upper travel limit")

    # -- ending ------------------------------------------------------------------------
    def _safe_stop(self) -> str:
        """Stop the crosshead: stop, else emergency stop, retried (reconnecting) for a while.

        A link that glitched may come back within STOP_RETRY_S; a real drive's watchdog
        is the last line of defence beyond that. Never raises; says what happened.
        """
        crosshead = self.machine.crosshead
        deadline = time.monotonic() + STOP_RETRY_S
        errors: list[str] = []
        while True:
            estop = ("emergency stop", "emergency stopped", crosshead.emergency_stop)
            attempts = (estop,) if self._estop.is_set() else (("stop", "stopped", crosshead.stop), estop)
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
                        log.warning("%s of the crosshead failed: %s (retrying for %g s)", verb, exc, STOP_RETRY_S)
                    errors.append(str(exc))
            if time.monotonic() >= deadline:
                self._link_alive = False
                return f"stop and emergency stop failed ({len(errors)} attempts): {errors[-1]}"
            if lost:
                try:
                    self.machine.connect()
                except Exception as exc:
                    errors.append(str(exc))
            time.sleep(0.02)

    def _confirm_at_rest(self) -> bool:
        deadline = time.monotonic() + STOP_CONFIRM_S
        while time.monotonic() < deadline:
            try:
                if not self.machine.crosshead.status().moving:
                    return True
            except DeviceConnectionLost:
                self._link_alive = False
                return False
            except Exception:
                pass
            time.sleep(0.005)
        try:
            self.machine.crosshead.emergency_stop()
        except Exception:
            pass
        return False

    def _park(self) -> str:
        """Move back to the start position; a new stop request or a limit halts it."""
        self._set_state(PARKING)
        crosshead = self.machine.crosshead
        target = self._start_position
        speed = min(self.method.park_speed_mm_min, self.limits.max_speed_mm_min)
        stop_requested = self._stop.is_set()
        self._stop.clear()
        self._wake.clear()
        try:
            start = self.machine.read_sample()
            # moving up unloads the specimen: only a force that rises and stays up means the
            # plate pushes on something (after a force-limit stop the force starts above the
            # limit; a viscoelastic specimen may spike for an instant when the motion reverses)
            force_stop = max(self.limits.force_N, start.force_N + 0.01 * self.limits.force_N)
            high = 0
            crosshead.move_to(target, speed)
            distance = abs(start.position_mm - target)
            deadline = time.monotonic() + (distance / speed * 60.0 * 1.5 + 5.0) / self.speedup + 2.0
            poll = max(min(self.period_s, 0.05), 0.001)
            while time.monotonic() < deadline:
                if self._estop.is_set() or self._stop.is_set():
                    crosshead.stop()
                    return "park interrupted by a stop request"
                reading = self.machine.read_sample()
                high = high + 1 if reading.force_N >= force_stop else 0
                if high >= 3 or (reading.load_cell_status is not None and reading.load_cell_status.over_range):
                    crosshead.stop()
                    return f"park stopped: force {reading.force_N:.1f} N"
                status = crosshead.status()
                if status.fault or status.emergency_stopped:
                    crosshead.stop()
                    return "park stopped by a crosshead fault"
                arrived = abs(reading.position_mm - target) <= AT_TARGET_MM or status.in_position
                if arrived and not status.moving:
                    return f"parked at {target:.3f} mm"
                if (status.upper_limit or status.lower_limit) and not status.moving:
                    return f"park ended at a travel limit, {reading.position_mm:.3f} mm"
                self._wake.wait(poll)
            crosshead.stop()
            return "park timed out; crosshead stopped"
        except Exception as exc:
            self._safe_stop()
            return f"park failed: {exc}"
        finally:
            if stop_requested:
                self._stop.set()

    def _finish(self, end: str, reason: str) -> None:
        """The single exit path: stop, mark and close the file, park, fit, report. Never raises."""
        result = None
        try:
            self._set_state(STOPPING)
            # nothing to stop when the link never came up: no command ever reached the machine
            stop_note = self._safe_stop() if self._connected_once else "never connected"
            if self._connected_once and "failed (" not in stop_note:
                self._confirm_at_rest()
            status = FINISHED if end == END_FINISHED else ABORTED
            if status == ABORTED:
                log.info("run aborted: %s (%s)", reason, stop_note)
            finished_at = _now_iso()
            self._close_file(status, reason)
            park = "not parked"
            if self._link_alive and end in PARK_AFTER and self._start_position is not None:
                park = self._park()
            elif end not in PARK_AFTER:
                park = f"not parked after {end}: {stop_note}"
            run = self._run_data(status, reason, finished_at)
            results = None
            if run is not None and len(run):
                try:
                    results = self.method.compute_results(run)
                except Exception as exc:
                    log.warning("method results failed: %s", exc)
            fit, fit_error, fit_path = None, "", None
            if status == FINISHED and self.fit_enabled and run is not None:
                self._set_state(FITTING)
                fit, fit_error, fit_path = self._fit(run)
            timing = ScheduleStats.from_arrays(self.period_s, self._late, self._rtt,
                                               self._schedule.missed if self._schedule else 0, self._failed_reads,
                                               self._schedule.missed_waiting_device if self._schedule else 0,
                                               np.multiply(self._schedule.work_s, 1e3) if self._schedule else ())
            result = RunResult(self._path, status, reason, len(self._times), timing.missed, fit, results,
                               fit_error, fit_path, end, park, self._contact, timing, run)
            if status == FINISHED:
                self._emit_progress(self._disp[-1] if self._disp else 0.0,
                                    self._force[-1] if self._force else 0.0, 1.0, immediate=True)
        except Exception as exc:   # last resort: the result must exist and the waiters must wake
            log.error("run engine cleanup failed: %s: %s", type(exc).__name__, exc)
            log.debug("run engine cleanup failed", exc_info=True)
            result = RunResult(self._path, ABORTED, reason or f"cleanup failed: {exc}", len(self._times),
                               self._schedule.missed if self._schedule else 0, end=end)
        finally:
            if self.manage_connection:
                try:
                    self.machine.close()
                except Exception:
                    pass
            self._result = result
            self._set_state(result.status if result else ABORTED)
            self._emit("on_finished", result)
            self._done.set()

    def _close_file(self, status: str, reason: str) -> None:
        if self._writer is None:
            return
        if self._syncer is not None:
            self._syncer.close()
        try:
            self._writer.finish(status, reason)
        except Exception as exc:
            log.error("could not close the run file %s: %s", self._path, exc)

    def _run_data(self, status: str, reason: str, finished_at: str) -> RunData | None:
        if self._path is None:
            return None
        return RunData(
            np.asarray(self._times), np.asarray(self._disp), np.asarray(self._force),
            specimen=self.specimen, method=self.method.name, machine=self.machine_name,
            started_at=self._started_at, finished_at=finished_at, status=status, abort_reason=reason,
            source=str(self._path),
            metadata={"sampling_hz": self.method.sampling_hz, "speedup": self.speedup,
                      "contact_position_mm": self._contact, "preload_N": self.method.contact.preload_N},
        )

    def _fit(self, run: RunData) -> tuple[Any, str, Path | None]:
        if importlib.util.find_spec("foamlab.identification") is None:
            return None, "", None
        try:
            identification = importlib.import_module("foamlab.identification")
            fit = identification.fit_run(run)
        except FoamlabError as exc:
            return None, str(exc), None
        except Exception as exc:   # a fitting bug must not cost the run: it is saved already
            log.debug("automatic fit failed", exc_info=True)
            return None, f"fit failed: {type(exc).__name__}: {exc}", None
        fit_path = None
        if self._path is not None:
            try:   # the sidecar beside the run (the catalog indexes it, the simulator loads it)
                from foamlab.identification.store import store_fit

                fit_path = store_fit(fit, self._path).path
            except Exception as exc:
                log.warning("could not save the fit: %s", exc)
        return fit, "", fit_path
