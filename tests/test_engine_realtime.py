"""Real time: a short method at speedup 1 (the simulated machine's clock is the wall clock),
Modbus TCP through the real drivers. The 16 Hz schedule must miss nothing and wake on its
deadlines. benchmarks/bench_schedule.py measures the same over longer runs and all transports."""

from __future__ import annotations

import pytest

from foamlab.methods import load_method
from tests.hil_support import (approach, assert_keeps_the_schedule, machine_for, make_engine,
                               short_method, simulated, skip_if_stolen, wait_at_rest)

pytestmark = [pytest.mark.realtime, pytest.mark.hil, pytest.mark.schedule, pytest.mark.timeout(60)]

#: Target of the issue: p99 deviation from the deadlines <= 2 ms at 16 Hz, zero missed.
P99_TARGET_MS = 2.0


#: Deadlines in the run: at least MIN_DEADLINES for the p99 to be a percentile (with 59, as
#: before, np.percentile's p99 was 58 % the largest lateness: one VM stall of ~4 ms failed CI).
MIN_DEADLINES = 105


def test_16_hz_schedule_in_real_time(tmp_path):
    # one cycle to 8 % (5.8 mm) at 100 mm/min: ~7 s of sampling, ~111 samples
    method = load_method(short_method(tmp_path, strain=0.08, speed=100.0, cycles=1))
    with simulated("modbus-tcp", speedup=1.0) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, method, tmp_path, speedup=1.0)
        result = engine.wait(40) if engine.start() is None else None
        assert result is not None, "the run did not end"
        wait_at_rest(sim)
    assert result.status == "finished", result.reason
    timing = result.timing
    expected = method.expected_samples(72.5)
    skip_if_stolen(result)         # a stalled host stretches the run too
    assert expected <= result.n_samples + result.missed <= expected + 4
    assert result.n_samples + result.missed >= MIN_DEADLINES
    assert_keeps_the_schedule(result)
    assert timing.period_s == pytest.approx(1 / 16)
    # without a real-time slot the OS may wake us late on a busy machine: the run then still
    # misses nothing (checked above) but the lateness target is the OS's, not ours
    if not engine.scheduling.startswith("SCHED_FIFO"):
        pytest.skip(f"lateness not asserted: {engine.scheduling}; missed 0, p99 {timing.lateness_p99_ms:.2f} ms")
    assert timing.lateness_p99_ms <= P99_TARGET_MS, timing
