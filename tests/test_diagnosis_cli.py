"""`foamlab diagnose`: the JSON object, the report, several files, bad input."""

from __future__ import annotations

import json

import independent_effects as ie
import pytest

from foamlab import cli
from foamlab.diagnosis.limits import UNCHECKED
from foamlab.diagnosis.settings import DEFAULT


def _write_csv(path, run):
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# synthetic run\ntime_s,displacement_mm,force_N\n")
        for t, x, f in zip(run.time_s, run.displacement_mm, run.force_N):
            fh.write(f"{t:.5f},{x:.6f},{f:.5f}\n")
    return path


@pytest.fixture(scope="module")
def softened(tmp_path_factory):
    """5 %/cycle softening hidden by tests/independent_effects.py in regime A at 4 Hz (seed 3)."""
    return _write_csv(tmp_path_factory.mktemp("d") / "soft.csv",
                      ie.independent_run("A", 3, {"cycle_softening": 5.0}, hz=4.0))


def test_json_is_the_design_object_and_the_report_has_its_figures(softened, tmp_path, capsys):
    assert cli.main(["diagnose", str(softened), "--json", "--report", str(tmp_path / "rep")]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert set(obj) == {"verdict", "findings", "base", "skipped", "detection_limits"}  # base: the form and why
    assert all(isinstance(why, str) and why for why in obj["skipped"].values())   # cause -> why not tested
    # what the run could have seen: every cause it tests, in physical units and in words
    limits = {item["cause"]: item for item in obj["detection_limits"]}
    assert set(limits) == {"cycle_softening", "damping_cycle_change", "channel_lag", "force_zero_drift",
                           "machine_compliance", "direction_friction", "memory_lag"}
    assert all(item["limit"] > 0 and item["text"].startswith("no ") for item in limits.values())
    # a cause is named, so no injection checked them: the limits of causes the base can hold say so
    assert {c for c, item in limits.items() if item["unchecked"]} == set(limits) - {"force_zero_drift"}
    assert obj["base"]["form"] in ("causal", "paper") and "held-out" in obj["base"]["why"]
    assert obj["verdict"] == "cycle_softening"
    first = obj["findings"][0]
    assert first["effect"] == "cycle_softening"
    assert set(first["gain"]) == {"rmse_before", "rmse_after", "heldout_rmse_before",
                                  "heldout_rmse_after", "heldout_gain_se", "delta_bic"}
    g = first["gain"]     # a clear softening: its held-out gain many standard errors beyond chance
    # the gain beyond the rule's margin of its block-to-block spread, both reported
    margin = DEFAULT.heldout_margin_z * g["heldout_gain_se"]
    assert 0 < g["heldout_gain_se"] and g["heldout_rmse_after"] < g["heldout_rmse_before"] - margin
    for name in ("index.html", "measurement.png", "base_simulation.png", "residual_map.png",
                 "cause.png", "extended_simulation.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 0


def test_table_output_and_causes_subset(softened, capsys):
    assert cli.main(["diagnose", str(softened), "--causes", "channel_lag,force_zero_drift"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("verdict: ")
    assert "cycle_softening" not in out.splitlines()[0]


def test_linearised_limits_skip_the_check_and_say_so(tmp_path, capsys):
    """--linearised-limits: a clean run (A, seed 7, 4 Hz, fixed before looking) reports its limits
    from the slope at the base, without the refits that check them (limits.checked), and every
    limit of a cause the base can hold says it is unchecked (limits.UNCHECKED)."""
    clean = _write_csv(tmp_path / "clean.csv", ie.independent_run("A", 7, {}, hz=4.0))
    assert cli.main(["diagnose", str(clean), "--linearised-limits", "--json", "--no-store"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert obj["verdict"] == "none"       # where a run names nothing the check would otherwise run
    limits = {item["cause"]: item for item in obj["detection_limits"]}
    assert all(not item["injections"] for item in limits.values())
    held = set(limits) - {"force_zero_drift"}
    assert {c for c, item in limits.items() if item["unchecked"]} == held
    assert all(limits[c]["text"].endswith(UNCHECKED) for c in held)


@pytest.mark.parametrize("argv,message", [
    (["diagnose", "/no/such/file.csv"], "not found"),
    (["diagnose", "{x}", "--causes", "bogus"], "unknown cause"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message, softened):
    argv = [a.replace("{x}", str(softened)) for a in argv]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_garbage_file_is_refused(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("hello,world\n1,2\n", encoding="utf-8")
    assert cli.main(["diagnose", str(bad)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
