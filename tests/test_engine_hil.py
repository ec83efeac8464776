"""A run against the simulated machine over Modbus TCP (real drivers) whose method comes from a
file. The engine's exit paths (stop, e-stop, limits, park, faults, a broken listener) are tested
in-process, in virtual time: tests/test_engine_inprocess.py."""

from __future__ import annotations

import numpy as np
import pytest

from foamlab import pipeline
from foamlab.storage.runfile import read_run_file
from tests.hil_support import approach, machine_for, make_engine, short_method, simulated, wait_at_rest

pytestmark = [pytest.mark.hil, pytest.mark.timeout(60)]

SPEEDUP = 10.0


def _assert_file_matches(result):
    """Every sample the engine took is in the file, unchanged, with the status and reason."""
    on_disk = read_run_file(result.path)
    assert on_disk.status == result.status
    assert on_disk.abort_reason == result.reason
    assert len(on_disk) == result.n_samples == len(result.run)
    np.testing.assert_allclose(on_disk.time_s, result.run.time_s, atol=1e-9)
    np.testing.assert_allclose(on_disk.displacement_mm, result.run.displacement_mm, atol=1e-9)
    np.testing.assert_allclose(on_disk.force_N, result.run.force_N, atol=1e-9)
    return on_disk


def test_a_run_made_with_a_method_file_finds_its_method_again(tmp_path):
    """A method file that is not built in: the run file records the method itself, so the
    method's results are computed from the file alone, the same after the method file moved."""
    methods = tmp_path / "methods"
    methods.mkdir()
    method_file = short_method(methods, strain=0.05, speed=100.0, cycles=2, name="lab-own")
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        result = make_engine(sim, method_file, tmp_path, speedup=SPEEDUP).run()
        wait_at_rest(sim)
    assert result.status == "finished", result.reason
    on_disk = _assert_file_matches(result)
    assert on_disk.method == "lab-own" and on_disk.metadata["method_file"] == str(method_file.resolve())
    analysis = pipeline.method_stage(pipeline.Analysis(on_disk, result.path))
    assert analysis.method_error == "" and analysis.method_results is not None
    assert {v.cycle for v in analysis.method_results.values if v.cycle} == {1, 2}
    method_file.rename(methods / "elsewhere.toml")
    moved = pipeline.method_stage(pipeline.Analysis(read_run_file(result.path), result.path))
    assert moved.method_error == "", moved.method_error     # the file holds the method itself
    assert moved.method_results == analysis.method_results
