"""Settings in the open: the diagnosis decides by the settings object it is given, and
`foamlab diagnose --full` prints the values it used."""

from __future__ import annotations

import dataclasses

import pytest

from foamlab import cli
from foamlab.diagnosis import CAUSES, diagnose
from foamlab.diagnosis.limits import clearing_on_top
from foamlab.diagnosis.settings import DEFAULT, DiagnosisSettings
from foamlab.diagnosis.synthetic import hidden_effect_run

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def softened():
    # a clear hidden effect (tests/test_diagnosis_cli.py names it with the default settings)
    return hidden_effect_run({"cycle_softening": 0.05}, sampling_hz=1.0, seed=3)


def test_settings_are_frozen_records_with_a_meaning_each():
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULT.delta_bic_min = 0.0
    for f in dataclasses.fields(DiagnosisSettings):
        assert f.metadata["meaning"], f.name
    assert dataclasses.replace(DEFAULT, max_findings=1) != DEFAULT


@pytest.fixture(scope="module")
def named(softened):
    return diagnose([softened])


def test_the_diagnosis_decides_by_the_settings_given(softened, named):
    assert named.verdict == "cycle_softening" and named.settings is DEFAULT
    # evidence out of reach: the same run, nothing named
    strict = DiagnosisSettings(delta_bic_min=1e12)
    held_back = diagnose([softened], causes=["cycle_softening"], settings=strict)
    assert held_back.settings is strict
    assert held_back.verdict != "cycle_softening" and not held_back.findings
    assert any("delta BIC" in c.reason and "1e+12" in c.reason for c in held_back.tested[0])


def test_a_quiet_model_is_not_searched_again_for_an_effect_the_data_pull_below_its_bound(named):
    """The score test of the causes left is one-sided for an effect bounded at zero: on this run's
    final model (softening and a memory lag, below the noise estimate) the frame's linearised gain
    is 110 noise variances, but for a negative compliance; fitted, a frame gains nothing (Delta BIC
    -3.8), so no round is spent on it."""
    assert [f.name for f in named.findings] == ["cycle_softening", "memory_lag"]
    assert clearing_on_top(named.series, named.final, [CAUSES["machine_compliance"]], DEFAULT) == []
    assert len(named.tested) == 2


def test_diagnose_full_prints_the_settings(softened, tmp_path, capsys):
    path = tmp_path / "soft.csv"
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("time_s,displacement_mm,force_N\n")
        for t, x, f in zip(softened.time_s, softened.displacement_mm, softened.force_N):
            fh.write(f"{t:.5f},{x:.6f},{f:.5f}\n")
    assert cli.main(["diagnose", str(path), "--full", "--causes", "cycle_softening", "--no-store"]) == 0
    out = capsys.readouterr().out
    for f in dataclasses.fields(DiagnosisSettings):
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(f.name + " "))
        shown, value = line.split("=", 1)[1].split()[0], getattr(DEFAULT, f.name)
        assert shown == str(value).lower() if isinstance(value, bool) else float(shown) == value, line
