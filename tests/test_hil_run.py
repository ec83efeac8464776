"""Hardware in the loop: the paper's protocol runs in full through the real drivers, over
each wire protocol, against the simulated machine in its own process.

Throughput sets the speedup. A sample costs one request over ASCII and three over Modbus
(force and position are separate devices: position, force, position - drivers.base); at 16 Hz
of machine time a speedup S needs 16*S samples per wall second, and the paper's protocol is
14 156 samples whatever the speedup. Each transport runs at a speedup whose wall period
(62.5 ms / S) is about three times its p99 sample time (measured in clean-clone CI runs: a
Modbus sample's p99 5.2-5.4 ms, max 9.7 ms, one start 6.3 ms late: at speedup 5 their sum
cost one deadline; ASCII ~3 ms with stalls to 17 ms), so the engine keeps the schedule
without a quiet computer (hil_support.assert_keeps_the_schedule: its own work p99 <= 25 % of
the period, <= 0.5 % missed); on a specimen a quarter of the default height (~3 500 samples):
~1 min each over Modbus, ~0.5 min over ASCII.
`foamlab run --speedup 15` (the README's main job) runs the same protocol over Modbus TCP at
3.75x the sample rate of the per-transport test: it must keep >= 97 % of the deadlines and fit.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from foamlab import cli, pipeline
from foamlab.methods import cycle_spans, load_method
from foamlab.storage.runfile import read_run_file
from tests.hil_support import (SPECIMEN, approach, assert_keeps_the_schedule, machine_for, make_engine,
                               simulated, skip_if_overloaded, wait_at_rest)

pytestmark = [pytest.mark.hil]

#: Speedup per transport for the full protocol (see the module docstring).
#: Serial at x4 since session 12: phase 2 runs beside phase 1 (scripts/test.sh), and at x8 (a 7.8 ms
#: period) a reply p99 of 5.5 ms skipped a run as overloaded (ci16); phase 2 still ends first.
FULL_SPEEDUP = {"modbus-tcp": 4.0, "serial": 4.0, "modbus-rtu-pty": 4.0}
#: The per-transport runs test a specimen a quarter of the default height: the same protocol,
#: the same sample rate and speedups, a quarter of the samples (~3 500; the CI suite has 20
#: minutes, and the schedule statistics of 3 500 deadlines are as telling as of 7 000).
QUARTER_HEIGHT = replace(SPECIMEN, height_mm=SPECIMEN.height_mm / 4)


def _expected(method, height=72.5):
    return method.expected_samples(height)


def _check_run(result, method, *, cycles):
    """3 cycles reached their peaks and came back, every sample is on disk."""
    assert result.status == "finished", result.reason
    spans = cycle_spans(method, result.run)
    assert [s.cycle for s in spans] == list(range(1, cycles + 1)) and all(s.complete for s in spans)
    on_disk = read_run_file(result.path)
    assert on_disk.status == "finished" and len(on_disk) == result.n_samples
    np.testing.assert_array_equal(on_disk.force_N, result.run.force_N)
    # 16 Hz of machine time, sample after sample
    assert np.median(np.diff(on_disk.time_s)) == pytest.approx(1 / method.sampling_hz, rel=0.05)
    return on_disk


#: The README job's run is sped up this much (16 Hz -> a 4.2 ms period).
SPEEDUP = 15


@pytest.mark.timeout(150)
@pytest.mark.schedule
def test_paper_protocol_through_foamlab_run(tmp_path, capsys):
    """The README's main job: `foamlab run --speedup S` on the built-in machine, to the fit."""
    out = tmp_path / "data"
    # (the diagnosis, ~20 s, is foamlab.diagnosis' own tests' business)
    code = cli.main(["run", "--speedup", str(SPEEDUP), "--out", str(out), "--quiet", "--specimen-label", "hil",
                     "--no-diagnose"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    run_file = next(out.glob("*_hil_paper-3cycle.csv"))
    assert f"run file: {run_file}" in printed.out
    method = load_method("paper-3cycle")
    run = read_run_file(run_file)
    assert run.status == "finished" and run.specimen.height_mm == 72.5
    spans = cycle_spans(method, run)
    assert len(spans) == 3 and all(s.complete for s in spans)
    assert all(s.peak_mm == pytest.approx(0.8 * 72.5, abs=0.05) for s in spans)   # a missed peak sample
    summary_line = next(line for line in printed.out.splitlines() if line.startswith("foamlab run: finished"))
    n_samples, missed = (int(w) for w in summary_line.replace(",", "").split()[3:6:2])
    assert n_samples == len(run)
    # Every deadline is a sample or a counted miss (plus the turning points, where the drive
    # is confirmed at rest: slower on a busy machine). At 240 samples/s (three requests each)
    # Modbus TCP missed 0.3 % on a quiet computer (`foamlab run`); the bound leaves room for other jobs' load
    # (the zero-miss requirement is the per-transport test's, at a speedup with margin).
    expected = _expected(method)
    assert expected <= n_samples + missed <= 1.01 * expected + 20
    if missed > 0.03 * expected:     # session 31's CI, host load ~4: 472 missed, request p99 8.0 of 4.2 ms
        request_p99_ms = float(summary_line.split("request p99 ")[1].split(" ms")[0])
        skip_if_overloaded(missed, request_p99_ms, 1e3 / (method.sampling_hz * SPEEDUP))
    assert missed <= 0.03 * expected, summary_line
    assert "hysteresis_loss (cycle 1)" in printed.out
    fit_file = run_file.with_name(f"{run_file.stem}.fit.json")
    assert fit_file.is_file() and "fit:" in printed.out
    fit = json.loads(fit_file.read_text())
    assert fit["rmse"] < 0.05 * run.force_N.max()
    from foamlab.storage.catalog import Catalog

    with Catalog.for_folder(out, sync=False) as catalog:
        assert [r.path for r in catalog.runs()] == [str(run_file.resolve())]


@pytest.mark.timeout(400)
@pytest.mark.schedule
def test_twenty_cycles_through_foamlab_run(tmp_path, capsys):
    """A long run through the drivers (configs/methods/cyclic-20.toml on a 10 mm specimen:
    20 cycles, ~1 500 samples), fitted with the later cycles sharing the third's terms.

    A schedule test: the run keeps its real-time deadlines, and a device that does not answer
    within its reply timeout twice aborts it (the safety path). In phase 1's idle class the
    client could be starved past its 40 ms timeout with the reply already waiting (ci36: "no
    reply to read of motor_position (2 attempts of 40 ms)", the late replies then read as
    stale transaction ids)."""
    out = tmp_path / "data"
    code = cli.main(["run", "--method", "cyclic-20", "--specimen-height", "10", "--speedup", "2",
                     "--out", str(out), "--quiet", "--specimen-label", "long", "--no-diagnose", "--no-predict"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    run_file = next(out.glob("*_long_cyclic-20.csv"))
    method = load_method("cyclic-20")
    run = read_run_file(run_file)
    spans = cycle_spans(method, run)
    assert len(spans) == 20 and all(s.complete for s in spans)
    assert all(s.peak_mm == pytest.approx(0.6 * 10, abs=0.05) for s in spans)
    fit = json.loads(run_file.with_name(f"{run_file.stem}.fit.json").read_text())
    assert fit["orders"]["C"] == 3 and len(fit["model"]["residual"]["r"]) == 3
    # ci45 (x20): the hypervisor took 13 s of CPU; a 150 ms stall was 3 s of machine time, over
    # which the crosshead reached a peak and waited unseen, and the fit (6.3 N) followed a straight
    # line it did not take. This host stalls the VM ~140 ms at a time even when idle (7 stalls in a
    # 15 s run, on a 100 ms grid): at x2 that is under 3 samples. A run with a longer gap ending at
    # a turn is said by its fit (the warning) and not held to its RMSE; a gap elsewhere is.
    gaps = [w for w in fit["warnings"] if "gap(s) without samples" in w and "ends at a turning point" in w]
    if gaps:
        assert run.metadata["schedule"]["missed"] > 0, gaps
        pytest.skip(f"the loaded computer left gaps in the run ({run.metadata['schedule']}): {gaps[0]}")
    assert fit["rmse"] < 0.05 * run.force_N.max()


#: Modbus TCP runs the full protocol at full height in the README main job's test above.
PER_TRANSPORT = [t for t in FULL_SPEEDUP if t != "modbus-tcp"]


@pytest.mark.timeout(400)
@pytest.mark.schedule
@pytest.mark.parametrize("transport", PER_TRANSPORT)
def test_full_paper_protocol_through_each_transport(tmp_path, transport):
    speedup = FULL_SPEEDUP[transport]
    method = load_method("paper-3cycle")
    with simulated(transport, speedup=speedup) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, method, tmp_path, speedup=speedup, specimen=QUARTER_HEIGHT)
        result = engine.wait(350) if engine.start() is None else None
        assert result is not None, "the run did not end"
        wait_at_rest(sim)
    _check_run(result, method, cycles=3)
    expected = _expected(method, QUARTER_HEIGHT.height_mm)
    assert expected <= result.n_samples + result.missed <= 1.01 * expected + 20
    analysis = pipeline.fit_stage(pipeline.Analysis(result.run, result.path))
    assert analysis.fit is not None, analysis.fit_error
    assert analysis.fit.rmse < 0.05 * result.run.force_N.max()
    assert_keeps_the_schedule(result)
