"""What happens after a run is decided once (pipeline.AfterRun) for `foamlab run` and the window."""

from __future__ import annotations

import numpy as np

from foamlab.acquisition.events import RunResult
from foamlab.acquisition.schedule import ScheduleStats
from foamlab.acquisition.settings import DEFAULT
from foamlab.commands.run import _report
from foamlab.methods import load_method
from foamlab.pipeline import AfterRun
from foamlab.rundata import RunData


def _result(n: int, missed: int, status: str = "finished", path=None) -> RunResult:
    t = np.arange(n) / 16.0
    run = RunData(t, 0.1 * t, 0.01 * t, status=status)
    timing = ScheduleStats.from_arrays(1 / 16.0, np.zeros(n), np.full(n, 3.0), missed, 0, missed)
    return RunResult(path, status, "" if status == "finished" else "stopped", n, missed, timing=timing, run=run)


def test_a_run_on_schedule_is_fitted_without_a_flag():
    plan = AfterRun.of(_result(1000, 2))
    assert plan.fit and plan.gaps == ""


def test_gaps_are_flagged_above_the_warning_share_and_the_run_still_analysed():
    plan = AfterRun.of(_result(1000, int(1000 * 2 * DEFAULT.gaps_warn_fraction)))
    assert plan.gaps.startswith("1.0% of the samples missed") and plan.fit


def test_an_aborted_run_is_not_fitted():
    plan = AfterRun.of(_result(100, 0, status="aborted"))
    assert not plan.fit and "did not finish" in plan.fit_note


def test_the_command_line_flags_the_gaps_as_the_window_does(tmp_path, capsys):
    result = _result(200, 40, path=tmp_path / "run.csv")
    _report(result, load_method("paper-3cycle"), tmp_path, fit=False, diagnose=False)
    assert "16.7% of the deadlines were missed" in capsys.readouterr().out
