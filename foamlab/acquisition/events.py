"""What a run reports: its states, why it ended, its samples, its progress and its result.

Listeners (the window, the CLI) receive on_sample / on_progress / on_state / on_finished
from the engine's worker thread: keep them short (queue the data for a GUI).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from foamlab.acquisition.schedule import ScheduleStats
from foamlab.methods import PlannedStep
from foamlab.rundata import RunData

log = logging.getLogger(__name__)

# States, in the order a run goes through them.
IDLE, CONNECTING, TARING, CONTACT_SEARCH, RUNNING = "idle", "connecting", "taring", "contact_search", "running"
STOPPING, PARKING, FINISHED, ABORTED = "stopping", "parking", "finished", "aborted"

# Why a run ended. The crosshead is parked only after FINISHED, STOP, LIMIT and STORAGE exits
# (the machine is sound; parking unloads the specimen): after an e-stop, an overload or a
# device fault the operator looks first.
END_FINISHED, END_STOP, END_LIMIT, END_STORAGE = "finished", "stop", "limit", "storage"
END_ESTOP, END_OVERLOAD, END_FAULT, END_LINK, END_ERROR = "estop", "overload", "fault", "link", "error"
PARK_AFTER = (END_FINISHED, END_STOP, END_LIMIT, END_STORAGE)


class RunAborted(Exception):
    """Internal: ends the run's main phase with a reason (kind is one of END_*)."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind, self.reason = kind, reason


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


@dataclass
class RunResult:
    """What the acquisition produced; the analysis (foamlab.pipeline) takes it from here."""

    path: Path | None         # the run file (None when the run ended before contact)
    status: str               # finished | aborted
    reason: str               # why it was aborted ("" when finished): one line
    n_samples: int
    missed: int
    end: str = END_FINISHED   # END_* kind
    park: str = ""            # what happened to the crosshead after the run
    contact_position_mm: float | None = None
    timing: ScheduleStats | None = None
    run: RunData | None = None
    safety: str = ""          # a stop not acknowledged, a crosshead not confirmed at rest, failed status polls

    @property
    def ok(self) -> bool:
        return self.status == FINISHED


class ProgressReporter:
    """Progress of the method's plan for the listeners, at most every `interval_s` (wall)."""

    def __init__(self, listeners: "Listeners", plan: list[PlannedStep], n_cycles: int, speedup: float,
                 interval_s: float, clock: Callable[[], float] = time.monotonic):
        self.listeners, self.plan, self.n_cycles = listeners, plan, n_cycles
        self.speedup, self.interval_s = speedup, interval_s
        self.nominal_s = sum(p.duration_s for p in plan)
        self._last = -math.inf
        self._clock = clock     # the run's (acquisition.clock): virtual time gives the same progress

    def report(self, step: PlannedStep | None, in_step_s: float, disp: float, force: float, state: str,
               fraction: float | None = None, immediate: bool = False) -> None:
        """`in_step_s`: machine time since `step` began; `fraction` overrides the plan's."""
        now = self._clock()
        if not immediate and now - self._last < self.interval_s:
            return
        self._last = now
        if fraction is None:
            fraction = 0.0
            if step is not None:
                done = sum(p.duration_s for p in self.plan[:step.index])
                in_step = min(max(0.0, in_step_s), step.duration_s)
                fraction = (done + in_step) / self.nominal_s if self.nominal_s else 1.0
        left = max(0.0, (1.0 - fraction) * self.nominal_s / self.speedup)
        self.listeners.emit("on_progress", Progress(step.step.cycle if step else 0, self.n_cycles,
                                                    min(max(fraction, 0.0), 1.0), disp, force, left, state))


class Listeners:
    """The engine's listeners; a broken one is logged once and never stops a run."""

    def __init__(self) -> None:
        self._listeners: list[Any] = []
        self._failed: set[tuple[int, str]] = set()

    def add(self, listener: Any) -> None:
        self._listeners.append(listener)

    def __bool__(self) -> bool:
        return bool(self._listeners)

    def emit(self, name: str, *args) -> None:
        for listener in self._listeners:
            handler = getattr(listener, name, None)   # a listener implements any subset
            if handler is None:
                continue
            try:
                handler(*args)
            except Exception:
                # A broken display must not abort a test in progress; say it once per handler.
                key = (id(listener), name)
                if key not in self._failed:
                    self._failed.add(key)
                    log.error("listener %r.%s failed (further errors of it are not logged)", listener, name,
                              exc_info=True)
