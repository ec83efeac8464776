"""Acquisition: run a test method on a testing machine, safely, losing nothing.

- engine.py: RunEngine, the run's state machine on its worker thread (connect, tare,
  contact search, the method's steps, stop, park);
- sampling.py: Sampler, one sample per deadline (read, record, check the limits, tell the
  listeners) and the drive's status between samples;
- safety.py: Limits (force, travel, speed), the crosshead's alarms, stop / e-stop / park,
  the stall watchdog; the travel check before a run and the tare refusal (window and engine);
- schedule.py: SampleSchedule (fixed deadlines, misses counted and attributed),
  ScheduleStats, real-time priority, CPU wake-up latency;
- events.py: what a run reports - states, Sample, Progress, RunResult, listeners.

The samples go to foamlab.storage.recorder; the analysis after the run is foamlab.pipeline.
See docs/acquisition.md.
"""

from foamlab.acquisition.engine import RunEngine
from foamlab.acquisition.events import Progress, RunResult, Sample
from foamlab.acquisition.safety import Limits
from foamlab.acquisition.schedule import SampleSchedule, ScheduleStats

__all__ = ["Limits", "Progress", "RunEngine", "RunResult", "Sample", "SampleSchedule", "ScheduleStats"]
