"""LivePredictor: the run predicted while it runs, off the acquisition thread.

    predictor = LivePredictor(engine.plan, method.sampling_hz, method.n_cycles)
    predictor.add_listener(display)     # on_forecast, on_compared, on_departure, on_score, on_note
    engine.add_listener(predictor)      # before engine.start()
    predictor.start()
    ...
    scores = predictor.finish(timeout_s)  # after the run: each cycle's forecast score

Threads and processes: the engine's acquisition thread only puts each sample in a queue
(on_sample: one SimpleQueue.put). The predictor's own thread takes them from there, notices
when a cycle is complete, and hands the fit to a worker *process* (one, at low priority): a fit
is seconds of Python that, in a thread, would hold the interpreter lock the acquisition needs
at every deadline (measured in docs/prediction.md). The thread compares every sample with the
latest forecast (foamlab.prediction.departure) and tells its listeners, from its own thread
(a window queues what it hears into its GUI thread).

A cycle k >= MIN_CYCLES that is complete starts a forecast identified on cycles 1..k (while one
is being made, only the latest complete cycle waits: a long run's fits may take longer than a
cycle); when both the forecast from cycles 1..k-1 and cycle k's samples are at hand, cycle k is
scored with it. When the run ends, a forecast still being made is abandoned (nothing is left
to predict) and only the scores already under way are waited for.
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
import os
import queue
import threading
import time
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any

import numpy as np

from foamlab import FoamlabError
from foamlab.acquisition.events import Listeners
from foamlab.methods import PlannedStep
from foamlab.prediction.departure import Departure, DepartureWatch
from foamlab.prediction.forecast import MIN_CYCLES, CycleScore, Forecast, ForecastScores, make_forecast, score_cycle
from foamlab.rundata import RunData

log = logging.getLogger(__name__)

#: Niceness of the worker process: the fit yields the CPU to the acquisition and the machine.
WORKER_NICE = 10
_END = object()


def _lower_priority() -> None:
    try:
        os.nice(WORKER_NICE)
    except (AttributeError, OSError):
        pass


def _warm() -> bool:
    """Runs first in the worker: its imports are done before the first cycle ends."""
    import foamlab.prediction.forecast  # noqa: F401, PLC0415
    return True


def worker_pool() -> Executor:
    """One low-priority process (spawned: the caller has threads, and fork would copy their locks)."""
    return concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                                  initializer=_lower_priority)


def _stop_workers(executor: Executor) -> None:
    """End a fit still running in the worker: shutdown(wait=False) leaves it running, and the
    interpreter's exit then waits for it (a long run's fit: a minute of a CLI that has finished)."""
    terminate = getattr(executor, "terminate_workers", None)       # Python >= 3.14
    if terminate is not None:
        terminate()
        return
    for process in list((getattr(executor, "_processes", None) or {}).values()):
        if process.is_alive():
            process.terminate()


@dataclass(frozen=True)
class ForecastJob:
    after_cycle: int
    submitted: float          # monotonic
    end_of_cycle_s: float     # machine time of the cycle's last sample


class _Samples:
    """The run's samples as the predictor keeps them (appended by its thread only)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.x: list[float] = []
        self.f: list[float] = []
        self.cycle: list[int] = []
        self.step: list[int] = []
        self.step_start: dict[int, float] = {}   # machine time of each step's first sample

    def add(self, s) -> None:
        self.t.append(s.time_s)
        self.x.append(s.displacement_mm)
        self.f.append(s.force_N)
        self.cycle.append(s.cycle)
        self.step.append(s.step)
        self.step_start.setdefault(s.step, s.time_s)

    def upto_cycle(self, k: int) -> RunData:
        n = int(np.searchsorted(np.asarray(self.cycle), k, side="right"))
        return RunData(np.asarray(self.t[:n]), np.asarray(self.x[:n]), np.asarray(self.f[:n]),
                       source=f"live prediction, cycles 1-{k}")

    def rows_of_cycle(self, k: int) -> np.ndarray:
        return np.flatnonzero(np.asarray(self.cycle) == k)

    def first_of_cycle(self, k: int) -> int:
        return int(np.searchsorted(np.asarray(self.cycle), k, side="left"))


class LivePredictor:
    """Engine listener that predicts the rest of the run (see the module docstring)."""

    def __init__(self, plan: list[PlannedStep], sampling_hz: float, n_cycles: int, *,
                 executor: Executor | None = None, min_cycles: int = MIN_CYCLES) -> None:
        if not sampling_hz > 0:
            raise FoamlabError(f"live prediction: the sampling rate must be > 0 Hz, got {sampling_hz!r}")
        self.plan, self.sampling_hz, self.n_cycles = plan, float(sampling_hz), int(n_cycles)
        self.min_cycles = max(1, int(min_cycles))
        self._executor = executor
        self._listeners = Listeners()
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._done = threading.Event()
        self.samples = _Samples()
        self.forecasts: dict[int, Forecast] = {}      # by from_cycles
        self.current: Forecast | None = None
        self.scores: list[CycleScore] = []
        self.departures: list[Departure] = []
        self.notes: list[str] = []
        self.arrivals: list[tuple[int, float, float]] = []   # (from_cycles, wall s after the cycle, machine t then)
        self._watch: DepartureWatch | None = None
        self._compared = 0                             # samples compared with `current`
        self._pending: dict[Future, Any] = {}
        self._scored: set[int] = set()
        self._said: set[tuple[int, str]] = set()
        self._completed = 0                            # highest cycle known complete
        self._waiting: int | None = None               # a complete cycle whose forecast waits for the worker
        self._finished_run = False
        self._ended = False                            # the run's end has been seen
        self._own_executor = executor is None

    def add_listener(self, listener: Any) -> None:
        """`listener` may implement on_forecast, on_compared, on_departure, on_score, on_note."""
        self._listeners.add(listener)

    # -- engine side (acquisition thread: a queue put, nothing else) -------------------------
    def on_sample(self, sample) -> None:
        self._inbox.put(sample)

    def on_finished(self, result) -> None:
        self._inbox.put((_END, bool(result is not None and result.status == "finished")))

    # -- control ---------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            raise FoamlabError("this live prediction has already been started")
        if self._executor is None:
            self._executor = worker_pool()
        self._executor.submit(_warm)
        self._thread = threading.Thread(target=self._run, name="foamlab-prediction", daemon=True)
        self._thread.start()

    def finish(self, timeout_s: float = 60.0) -> ForecastScores:
        """After the run: wait (at most timeout_s) for the last scores, stop the worker; the scores."""
        if self._thread is not None and not self._done.wait(timeout_s):
            self.notes.append(f"the last forecast scores did not come within {timeout_s:g} s")
            self._inbox.put((_END, False))
        self.close()
        return ForecastScores(sorted(self.scores, key=lambda s: s.cycle), "; ".join(self.notes), live=True)

    def close(self) -> None:
        """Stop the thread and the worker process now (idempotent)."""
        self._inbox.put(None)
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            if self._own_executor:
                _stop_workers(self._executor)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)

    # -- the predictor's thread ---------------------------------------------------------------
    def _run(self) -> None:
        ending = False
        try:
            while True:
                item = self._inbox.get()
                if item is None:
                    return
                batch = [item]
                while True:                      # everything queued meanwhile, in one pass
                    try:
                        batch.append(self._inbox.get_nowait())
                    except queue.Empty:
                        break
                ending = self._take(batch) or ending
                if ending and not self._still_needed():
                    self._abandon()
                    return
        except Exception:   # a prediction bug must never touch the run; say it once
            log.error("live prediction failed", exc_info=True)
            self._note("live prediction stopped: internal error (see the log)")
        finally:
            self._done.set()

    def _take(self, batch: list) -> bool:
        ending = False
        for item in batch:
            if item is None:
                continue
            if isinstance(item, tuple) and item and item[0] is _END:
                ending = self._ended = True
                self._finished_run = item[1]
                if self._finished_run:
                    self._cycle_complete(max(self.samples.cycle, default=0))
            elif isinstance(item, Future):
                self._job_done(item)
            else:
                if self.samples.cycle and item.cycle > self.samples.cycle[-1]:
                    self._cycle_complete(self.samples.cycle[-1])
                self.samples.add(item)
        self._compare_new()
        return ending

    def _cycle_complete(self, k: int) -> None:
        if k <= self._completed:
            return
        self._completed = k
        if self.min_cycles <= k < self.n_cycles:
            self._waiting = k
            self._forecast_next()
        self._maybe_score(k)

    def _forecast_next(self) -> None:
        """Start the forecast from the latest complete cycle, unless one is being made."""
        k = self._waiting
        if k is None or self._ended or any(isinstance(w, ForecastJob) for w in self._pending.values()):
            return          # after the run's end no new forecast: one in progress still scores its cycle
        self._waiting = None
        prefix = self.samples.upto_cycle(k)
        job = ForecastJob(k, time.monotonic(), float(prefix.time_s[-1]))
        self._submit(job, make_forecast, prefix, self.plan, k, self.sampling_hz, self.n_cycles)

    def _still_needed(self) -> bool:
        """After the run's end: a score being made, or a forecast in progress of a measured cycle.

        A forecast that a slower computer delivers after the run still scores the cycle it
        predicts (and says where that cycle left it): the result does not depend on the race.
        No new forecast starts after the end (on a 20-cycle run it would cost the user a fit of
        19 cycles for one score)."""
        return any(
            not isinstance(w, ForecastJob) or w.after_cycle + 1 <= self._completed for w in self._pending.values())

    def _abandon(self) -> None:
        for future, what in list(self._pending.items()):
            if isinstance(what, ForecastJob):
                future.cancel()
                self._pending.pop(future, None)
                if what.after_cycle + 1 <= self._completed and what.after_cycle + 1 not in self._scored:
                    self.notes.append(f"cycle {what.after_cycle + 1} not scored: its forecast was still being "
                                      "made when the run ended")

    def _maybe_score(self, k: int) -> None:
        """Score cycle k once it is complete and the forecast from cycles 1..k-1 is here."""
        forecast = self.forecasts.get(k - 1)
        if forecast is None or k > self._completed or k in self._scored:
            return
        self._scored.add(k)
        self._submit(("score", k), score_cycle, forecast, self.samples.upto_cycle(k), self.samples.rows_of_cycle(k), k)

    def _submit(self, what: Any, fn, *args) -> None:
        try:
            future = self._executor.submit(fn, *args)
        except RuntimeError:          # shut down: the run is over
            return
        self._pending[future] = what
        future.add_done_callback(self._inbox.put)     # wakes this thread with the result

    def _job_done(self, future: Future) -> None:
        what = self._pending.pop(future, None)
        if what is None or future.cancelled():
            return
        try:
            self._take_result(what, future)
        finally:
            if isinstance(what, ForecastJob):
                # after the result: its score job goes to the one worker before the next fit
                self._forecast_next()

    def _take_result(self, what: Any, future: Future) -> None:
        try:
            value = future.result()
        except FoamlabError as exc:
            self._note(f"no prediction from cycles 1-{getattr(what, 'after_cycle', '?')}: {exc}")
            return
        except Exception as exc:       # a broken worker process, a bug in the fit
            log.warning("live prediction job failed: %s", exc, exc_info=True)
            self._note(f"live prediction: {type(exc).__name__}: {exc}")
            return
        if isinstance(value, CycleScore):
            self.scores.append(value)
            self._listeners.emit("on_score", value)
        elif isinstance(value, Forecast):
            self._install(value, what)

    def _install(self, forecast: Forecast, job: ForecastJob) -> None:
        self.forecasts[forecast.from_cycles] = forecast
        now_t = self.samples.t[-1] if self.samples.t else 0.0
        self.arrivals.append((forecast.from_cycles, time.monotonic() - job.submitted, now_t - job.end_of_cycle_s))
        if self.current is None or forecast.from_cycles > self.current.from_cycles:
            self.current = forecast
            self._watch = DepartureWatch(forecast.noise_N, self.sampling_hz) if forecast.noise_N > 0 else None
            # the samples of the cycles it predicts that came while it was made: compared now
            self._compared = self.samples.first_of_cycle(forecast.from_cycles + 1)
            self._listeners.emit("on_forecast", forecast)
            self._compare_new()
        self._maybe_score(forecast.from_cycles + 1)

    def _compare_new(self) -> None:
        forecast, watch, s = self.current, self._watch, self.samples
        if forecast is None or watch is None:
            return
        n = len(s.t)
        i = self._compared
        while i < n:                  # one group of samples per step
            step = s.step[i]
            j = i
            while j < n and s.step[j] == step:
                j += 1
            predicted = forecast.step(step)
            if predicted is not None:
                t = np.asarray(s.t[i:j])
                compared, found = watch.compare(predicted, forecast.from_cycles, np.asarray(s.x[i:j]),
                                                t - s.step_start[step], np.asarray(s.f[i:j]), t)
                self._listeners.emit("on_compared", compared)
                for d in found:
                    if (d.cycle, d.phase) not in self._said:
                        self._said.add((d.cycle, d.phase))
                        self.departures.append(d)
                        self._listeners.emit("on_departure", d)
            i = j
        self._compared = n

    def _note(self, text: str) -> None:
        self.notes.append(text)
        self._listeners.emit("on_note", text)
