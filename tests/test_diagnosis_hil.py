"""Hidden effects through the simulator and the real drivers: one cause per transport.

The simulated machine (its own process) hides an effect in its physics (the online form
of foamlab.model.effects); the run engine records a short cyclic test through the real
driver of each wire protocol; the diagnosis of the recorded run must name the effect.
"""

from __future__ import annotations

import os

import pytest

from foamlab.diagnosis import diagnose
from foamlab.methods import load_method
from tests.hil_support import approach, machine_for, make_engine, short_method, simulated, wait_at_rest

pytestmark = [
    pytest.mark.hil,
    # Opt-in until diagnosis drives its model with identification's displacement path
    # (corner nodes): with the raw sampled displacement these runs were named correctly in
    # one clean-clone CI run and `unexplained` in the next (force_zero_drift not named).
    pytest.mark.skipif(os.environ.get("FOAMLAB_FULL_HIL") != "1",
                       reason="hidden effects through the drivers: set FOAMLAB_FULL_HIL=1 (flaky, see module)"),
]

#: transport -> (hidden effect, magnitude, speedup the transport sustains at 16 Hz).
#: The recorded runs also carry the transports' own skew: force and position are read by
#: separate requests, ~4 ms of wall time apart, i.e. ~35 ms of machine time at speedup 8
#: (the diagnosis finds it as `channel_lag`, force early); the hidden effects are sized
#: to stand above it.
CASES = {
    "modbus-tcp": ("force_zero_drift", 0.5, 8.0),
    "serial": ("force_zero_drift", 0.5, 4.0),
    "modbus-rtu-pty": ("force_zero_drift", 0.5, 2.0),
}


@pytest.mark.timeout(150)
@pytest.mark.parametrize("transport", list(CASES))
def test_hidden_effect_through_the_real_drivers_is_named(tmp_path, transport):
    name, magnitude, speedup = CASES[transport]
    # three cycles to 30 % strain at 100 mm/min: ~80 s of machine time, ~1250 samples at 16 Hz
    method = load_method(short_method(tmp_path, strain=0.30, speed=100.0, cycles=3))
    with simulated(transport, speedup=speedup, effects={name: magnitude}, seed=7) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, method, tmp_path, speedup=speedup, fit=False)
        engine.start()
        result = engine.wait(100)
        assert result is not None, "the run did not end"
        wait_at_rest(sim)
    assert result.status == "finished", result.reason
    d = diagnose([result.run])
    assert d.verdict == name, [(c.name, round(c.delta_bic, 1), c.reason) for r in d.tested for c in r]
    gain = d.findings[0].gain()
    assert gain["heldout_rmse_after"] < gain["heldout_rmse_before"]
    rate = d.findings[0].values["values"]["rate_N_per_s"]
    assert rate == pytest.approx(magnitude, rel=0.2)
