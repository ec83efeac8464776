"""The acquisition's thresholds in frozen objects, passed explicitly (the defaults unless given).

AcquisitionSettings: RunEngine(settings=...) hands it to the sampler, the crosshead and stall
watches, the stopper and the park; the tare refusal takes it too. CommissioningSettings: the
probe's move and read-back (`foamlab probe`). Why each value: docs/settings.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields


def _setting(default, meaning: str):
    return field(default=default, metadata={"meaning": meaning})


class _Listed:
    def lines(self) -> list[str]:
        """`name = value  meaning`, one line each, in declaration order."""
        width = max(len(f.name) for f in fields(self))
        return [f"{f.name:<{width}} = {getattr(self, f.name):<8g} {f.metadata['meaning']}" for f in fields(self)]


@dataclass(frozen=True)
class AcquisitionSettings(_Listed):
    # -- moves
    at_target_mm: float = _setting(0.003, "a move is complete this close to its target (drives report um)")
    near_target_mm: float = _setting(0.05, "this close, the drive is asked whether the move arrived")
    stall_window_s: float = _setting(1.0, "stall watch window (machine s)")
    stall_fraction: float = _setting(0.2, "stalled: moved less than this share of the commanded travel")
    # -- the link
    command_attempts: int = _setting(3, "sends of an idempotent command whose reply was lost")
    max_failed_reads: int = _setting(3, "failed readings in a row tolerated before the run aborts")
    max_failed_status_polls: int = _setting(2, "failed crosshead status polls in a row that end the run")
    status_interval_s: float = _setting(0.1, "crosshead status read between samples at most this often (wall s)")
    status_forced_interval_s: float = _setting(1.0, "...and at least this often, even without slack (wall s)")
    # -- stopping
    stop_confirm_s: float = _setting(2.0, "wait for the crosshead at rest after a stop (wall s)")
    stop_retry_s: float = _setting(3.0, "cleanup keeps sending stop / e-stop over a failing link (wall s)")
    # -- tare
    unloaded_fraction: float = _setting(0.01, "unloaded: within this share of the load cell's capacity")
    # -- after the run (foamlab.pipeline.AfterRun: both front ends)
    gaps_warn_fraction: float = _setting(0.005, "a run missing more than this share of its deadlines is flagged")


#: The values every run uses unless given others.
DEFAULT = AcquisitionSettings()


@dataclass(frozen=True)
class CommissioningSettings(_Listed):
    jog_mm: float = _setting(1.0, "the commissioning move: at most this far up (away from a specimen) and back")
    jog_speed_mm_min: float = _setting(30.0, "its speed (mm/min), under the profile's limit")
    jog_tolerance_mm: float = _setting(0.05, "the move arrives within this of where it was sent")
    jog_force_fraction: float = _setting(0.02, "the force may change by at most this share of the force limit")
    limit_tolerance_mm: float = _setting(0.011, "travel limits read back match what was written (display step)")


#: The values every probe uses unless given others.
COMMISSIONING = CommissioningSettings()
