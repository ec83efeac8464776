"""How finely a crosshead reads position: from its device file into the run file (issue 24, item 4).

Each crosshead driver states its resolution (the ESM303's reading decimals in its unit, one
CS2RS pulse) and the engine writes it into the run file's header. What the diagnosis should do
with it is open: on clean runs read to 0.01 mm at the ESM303's 120 mm/min it names a force lag
(5 of 6 serial HIL recordings, and the independent run below), and the noise model docs/devices.md
designed - (dF/dx)^2 q^2 / 12 a sample added to the load cell's variance, as per-sample weights in
the comparison - did not remove it (it raised the lag's Delta BIC: docs/devices.md). The runs here
come from tests/independent_model.py with the default specimen's parameters.
"""

from __future__ import annotations

import copy

import independent_effects as ie
import independent_model as im
import pytest

from drivers.profile import load_profile, open_machine
from foamlab import FoamlabError
from foamlab.diagnosis import diagnose
from foamlab.runformat import RESOLUTION_KEY, position_resolution_mm
from foamlab.storage.runfile import read_run_file, write_run_file

#: The ESM303's travel readings in mm carry 2 decimals (configs/devices/mark10-esm303.toml).
ESM303_MM = 0.01
#: configs/specimens/default.toml (what the simulated stand holds) in independent_model's terms:
#: 25 % strain of 72.5 mm at 120 mm/min, elastic scale 58 mm -> the stroke, noise 0.054 N.
STROKE_MM, DEFAULT_SCALE_MM = 0.25 * 72.5, 58.0
DEFAULT_K = (0.0, 520.5222461, -3089.598636, 9742.59045, -17507.04396, 18417.46785, -10292.71764, 2384.911416)
DEFAULT_R = ((-0.3048616426, 0.4584756607, 11.12015646), (-0.01524308213, 0.02292378303, 0.5560078232),
             (-0.007621541066, 0.01146189152, 0.2780039116))
#: Seeds 410-415 of the clean run read to 0.01 mm named a lag in 412 (channel_lag, Delta BIC 61,
#: far from the edge); 420 (set before running) hides a 100 ms lag.
CLEAN_SEED, LAG_SEED = 412, 420
LAGS = ("channel_lag", "memory_lag")


def test_each_crosshead_driver_states_its_resolution_from_its_device_file_and_profile():
    serial = load_profile("sim-serial")
    assert open_machine(serial, connect=False).crosshead.position_resolution_mm == pytest.approx(0.01)
    inches = copy.deepcopy(serial)
    inches["crosshead"]["travel_unit"] = "in"            # 3 decimals of an inch
    assert open_machine(inches, connect=False).crosshead.position_resolution_mm == pytest.approx(0.0254)
    # one pulse: lead 4 mm / (gear 10 x 10 000 pulses a revolution)
    assert open_machine("sim-modbus-rtu", connect=False).crosshead.position_resolution_mm == pytest.approx(4e-5)


def test_the_run_file_carries_the_resolution_and_a_run_without_it_is_unknown(tmp_path):
    run = ie.independent_run("A", 1)
    path = tmp_path / "run.csv"
    write_run_file(path, run, extra={RESOLUTION_KEY: ESM303_MM})
    assert position_resolution_mm(read_run_file(path).metadata) == ESM303_MM
    assert position_resolution_mm(run.metadata) == 0.0
    with pytest.raises(FoamlabError, match=RESOLUTION_KEY):
        position_resolution_mm({RESOLUTION_KEY: "fine"})


def esm303_run(seed: int, lag_ms: float = 0.0):
    """The default specimen to 25 % strain at 120 mm/min, positions read to 0.01 mm, the
    resolution in the metadata as the run file carries it."""
    regime = im.REGIME_A.with_(
        name="default", height_mm=72.5, strain=0.25, speed_mm_min=120.0, quantum_mm=ESM303_MM,
        k=tuple(k * (STROKE_MM / DEFAULT_SCALE_MM) ** i for i, k in enumerate(DEFAULT_K)),
        a=(0.01262626263, 0.01), alpha=(1 / 30 + 0j, 0.15 + 0.25j), r=DEFAULT_R, beta=((-0.1, 0.4, 0.8),) * 3,
        noise_N=0.054, zero_offset_N=0.0)
    run = ie.independent_run(regime, seed, {"channel_lag": lag_ms} if lag_ms else None)
    run.metadata[RESOLUTION_KEY] = ESM303_MM
    return run


def _tested(d) -> list:
    return [(c.name, round(c.delta_bic, 1), c.reason) for r in d.tested for c in r]


@pytest.mark.xfail(strict=True, reason="open: rounding to 0.01 mm is taken for a force lag (docs/devices.md)")
def test_a_clean_run_read_to_001_mm_names_no_lag():
    d = diagnose([esm303_run(CLEAN_SEED)])
    assert not {c.name for c in d.findings} & set(LAGS), _tested(d)


def test_a_genuine_100_ms_lag_on_the_same_quantised_run_is_named():
    d = diagnose([esm303_run(LAG_SEED, lag_ms=100.0)])
    assert d.verdict == "channel_lag", _tested(d)
