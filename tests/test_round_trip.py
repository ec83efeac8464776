"""Hardware in the loop, round trip: fit a run -> the simulated machine with that fit as its
specimen -> the paper's protocol through the real Modbus TCP drivers and the run engine ->
fit again. The second fit must describe the same specimen: the parameters the data
determine agree within their standard errors, and the fit reaches the load cell's noise.

What fits the CI budget, and why:
- the first run is the same protocol on the same simulated machine with a manual clock
  (every sample an exact instant: an ideal acquisition, in ~1 s); the second is the real
  thing, the simulator in its own process behind Modbus TCP, sampled by the run engine;
- the engine runs at a speedup Modbus TCP sustains on a busy 2-core machine (three
  requests per sample - drivers.base brackets the force with two positions; with two
  requests: ~2-4 ms loaded p50, 7-15 ms p99 at 16 Hz x S), S = 4. The full paper protocol (72.5 mm specimen, 885 s of machine time) would take
  3.7 min there, so the specimen is 8 mm high: the paper's protocol (3 cycles to 80 %,
  23.6 mm/min, 16 Hz, back to zero between cycles) on a shorter block, 98 s of machine
  time, ~25 s of wall time;
- orders: the paper's (3, 3, 7) are not identifiable term by term from one run of this
  protocol - fits of two runs of the same specimen, both at the noise level, differ by
  many of their own standard errors (|z| up to ~200 measured on the full protocol), because equivalent sets
  of memory terms exist, which local standard errors cannot see. A parameter-by-parameter
  round trip is meaningful for orders whose every parameter the data determine: one
  damping mode, one residual term per cycle and the order-7 elastic polynomial (N, M, P) =
  (1, 1, 7), what tests/test_identification.py identifies from the default specimen.
"""

from __future__ import annotations

import numpy as np
import pytest

from foamlab.identification import Orders, fit_run
from foamlab.methods import Method, load_method
from foamlab.model import ModelParameters
from foamlab.rundata import RunData, Specimen
from foamlab.segmentation import segment
from simulator.clock import ManualClock
from simulator.machine import MachineSettings, SimulatedMachine
from tests.hil_support import (SPECIMEN_TOP_MM, approach, assert_keeps_the_schedule, machine_for,
                               make_engine, simulated, wait_at_rest)

pytestmark = [pytest.mark.hil, pytest.mark.schedule]   # it asserts the 16 Hz schedule

HEIGHT_MM = 8.0
SPEEDUP = 4.0
ORDERS = Orders(1, 1, 7)
NOISE_N = MachineSettings().noise_sigma_N
POSITION_RESOLUTION_MM = 0.001          # the drive's position register counts um
COMMAND_DELAY = 0.25                    # of a period: the engine's at-rest check before a move
SPECIMEN = Specimen("round-trip", HEIGHT_MM, 100.0, 100.0)


def exact_run(method: Method, specimen=None, seed: int = 0) -> RunData:
    """The method on the simulated machine with a manual clock: force and position at
    the same exact instant, every 1/f of machine time. As the run engine does it: jog to
    the preload (displacement 0 where the force crossed it), then each planned move at
    its speed, the next one once the crosshead is at rest."""
    clock = ManualClock()
    machine = SimulatedMachine(clock=clock, specimen=specimen, seed=seed)
    period = 1.0 / method.sampling_hz

    def tick(dt=period):
        clock.advance(dt)
        machine.advance()
        position = round(machine.position_mm() / POSITION_RESOLUTION_MM) * POSITION_RESOLUTION_MM
        return position, machine.read_load_cell().net_N

    def settle():
        while machine.motion_eta() is not None:
            tick()

    machine.move_to(SPECIMEN_TOP_MM - 0.3, method.park_speed_mm_min)
    settle()
    machine.tare()
    machine.jog(+1, method.contact.search_speed_mm_min)
    previous = tick()
    while True:
        position, force = tick()
        if force >= method.contact.preload_N:
            break
        previous = position, force
    machine.stop()
    crossing = (method.contact.preload_N - previous[1]) / (force - previous[1])
    contact = previous[0] + crossing * (position - previous[0])
    settle()
    t0, rows = clock.now(), []
    for planned in method.plan(HEIGHT_MM):
        # the engine moves on once a sample and the drive's status (a round trip later)
        # show it at rest: the next move starts a little after that sample
        clock.advance(COMMAND_DELAY * period)
        machine.move_to(contact + planned.end_mm, planned.step.speed_mm_min)
        dt = (1.0 - COMMAND_DELAY) * period                  # back on the sampling grid
        while True:
            position, force = tick(dt)
            dt = period
            rows.append((clock.now() - t0, round(position - contact, 6), force))
            if machine.motion_eta() is None:
                break
    machine.close()
    t, x, f = (np.array(c) for c in zip(*rows))
    return RunData(t, x, f, specimen=SPECIMEN, method=method.name, source=f"manual clock, seed {seed}")


def round_trip_specimen() -> ModelParameters:
    """The first run's specimen: the default's elastic law, its slow damping mode and its
    strongest residual term (beta = 0.8), whose amplitude falls to 30 % and 15 % in cycles
    2 and 3. (The default's own cycles 2 and 3 keep 5 % and 2.5 %: on 6.4 mm of stroke at
    0.05 N such a term has two orders that fit about equally well - beta ~ 0.8 or a
    fractional integral, beta ~ -1.2 - and a fit takes either, ~1 in 8 seeds measured; its
    local standard error cannot say so. A round trip compares what the data determine.)"""
    d = ModelParameters.default()
    fade = np.array([1.0, 0.3, 0.15])
    return ModelParameters(d.x_scale_mm, d.elastic_k, d.damping_a[:1], d.damping_alpha[:1],
                           d.residual_r[0, -1] * fade[:, None], np.full((3, 1), d.residual_beta[0, -1]))


def determined(fit) -> np.ndarray:
    """Parameters with a finite standard error that the fit does not flag as undetermined
    (or hold fixed)."""
    flagged = {item.split(" = ", 1)[0] for w in fit.warnings if "not determined" in w
               for item in w.split(" not determined")[0].rsplit(" ", 1)[0].split(", ")}
    flagged |= {n.split(" ", 1)[0] for n in fit.notes if "(fixed)" in n}
    se = np.asarray(fit.stderr_autocorr, float)
    return np.isfinite(se) & (se > 0) & np.array([n not in flagged for n in fit.names])


@pytest.mark.timeout(120)
def test_fit_simulate_run_fit_agrees(tmp_path):
    method = load_method("paper-3cycle")
    truth = round_trip_specimen()
    first = fit_run(exact_run(method, specimen=truth, seed=1), ORDERS)
    assert first.rmse <= 1.1 * NOISE_N, first.summary()
    sidecar = first.save(tmp_path / "first.fit.json")
    assert ModelParameters.load(sidecar).order_N == ORDERS.N

    with simulated("modbus-tcp", speedup=SPEEDUP, specimen=str(sidecar), seed=2) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, method, tmp_path, speedup=SPEEDUP, specimen=SPECIMEN)
        engine.start()
        result = engine.wait(90)
        assert result is not None, "the run did not end"
        wait_at_rest(sim)
    assert result.status == "finished", result.reason
    # the engine kept the schedule (at most 0.5 % missed; an overloaded computer skips the test:
    # a request stalled for S x its wall time leaves its sample's instant, and the fit there, unsure)
    assert_keeps_the_schedule(result)
    second = fit_run(result.run, ORDERS)

    compared = determined(first) & determined(second)
    z = (second.values - first.values) / np.hypot(first.stderr_autocorr, second.stderr_autocorr)
    table = "\n".join(f"{n:10s} {a:12.5g} {b:12.5g}  z = {zi:+.2f}" for n, a, b, zi, c in
                      zip(first.names, first.values, second.values, z, compared) if c)
    print(f"round trip: first fit RMSE {first.rmse / NOISE_N:.3f} x noise; "
          f"{compared.sum()} of {len(first.names)} parameters compared; refit RMSE "
          f"{second.rmse:.4f} N = {second.rmse / NOISE_N:.3f} x the load cell's noise; "
          f"missed samples {result.missed} ({result.path})\n{table}")
    assert compared.sum() >= 0.8 * len(first.names)
    # k0 is the force where each run put displacement 0: where the preload was crossed, between two
    # samples of the contact search. Its uncertainty is that step times the stiffness there, not the
    # fit's standard error (measured: 0.557 vs 0.455 N, z = -3.7, once the drive's move starts a
    # sample sooner after the contact - the CS2RS's one PR0 write + trigger).
    step_mm = method.contact.search_speed_mm_min / 60.0 / method.sampling_hz
    k0_tolerance = step_mm * first.value("k1") / first.params.x_scale_mm
    k0 = first.names.index("k0")
    assert abs(second.values[k0] - first.values[k0]) <= k0_tolerance, (k0_tolerance, table)
    outside = [n for n, zi, c in zip(first.names, z, compared) if c and abs(zi) > 3 and n != "k0"]
    assert not outside, f"outside 3 combined standard errors: {outside}\n{table}"
    # The refit reaches the load cell's noise - away from the reversals. At a reversal the
    # model's force jumps (damping off, the cycle's residual force on: Eq. 10's switching),
    # and where between two 16 Hz samples the crosshead turned is known only from the
    # displacement around it: the sample just after a reversal was once predicted 2.4 N off
    # (the other 1566 at 0.055 N). Those samples are held to a looser bound, the rest to the
    # noise within 20 % (each sample's instant is a request's midpoint: at speedup 4 on a loaded
    # computer its jitter adds ~0.02 N rms - 1.09 x the noise measured in that run).
    turning = segment(result.run).turning_points
    near_reversal = np.zeros(len(second.residual_N), bool)
    for i in turning:
        near_reversal[max(i - 1, 0):i + 2] = True
    away = np.sqrt(np.mean(second.residual_N[~near_reversal] ** 2))
    assert away <= 1.2 * NOISE_N, f"{result.path}\n{second.summary()}"
    assert second.rmse <= 2.0 * NOISE_N, f"{result.path}\n{second.summary()}"
