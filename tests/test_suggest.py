"""`foamlab diagnose --suggest` (issue 16, item 3): a close call or a cause that needs another run
gets the test that best tells the contenders apart, written as a method file `foamlab run
--method` accepts; that test, run on the specimen with the true cause hidden and diagnosed
together with the first run, decides for the true cause."""

from __future__ import annotations

import json
import tomllib

import pytest

from foamlab import cli
from foamlab.diagnosis import diagnose
from foamlab.diagnosis.suggest import CLOSE_DELTA_BIC, suggest
from foamlab.diagnosis.synthetic import hidden_effect_run
from foamlab.methods import load_method, method_toml, parse_method

#: The default specimen's height: the paper's protocol compresses it to 80 % (58 mm).
HEIGHT = 72.5
#: The test protocol of tests/test_diagnosis.py: the paper's three cycles at 2 Hz.
FAST = {"sampling_hz": 2.0}


def _settles(effects: dict[str, float], seeds, tmp_path, pair: set[str] | None = None):
    """The first run diagnosed, the suggestion made and written, the suggested method run on
    the same specimen (true cause hidden), both runs diagnosed together. seeds: the first run's
    seed, or several: the first whose suggestion is between ``pair`` (a close call is a matter
    of a few units of Delta BIC, which one CPU's rounding moves: seed 5 here is 31.8 vs 9.1)."""
    for seed in (seeds if isinstance(seeds, tuple) else (seeds,)):
        first = hidden_effect_run(effects, seed=seed, height_mm=HEIGHT, **FAST)
        d = diagnose([first])
        s = suggest(d, HEIGHT)
        assert s.made, s.why
        names = {c.name for c in s.contenders}
        if pair is None or names == pair:
            break
    else:
        raise AssertionError(f"no seed of {seeds} made a suggestion between {pair}: last {s.why}, {names}")
    assert [p.over_noise for p in s.ranking] == sorted((p.over_noise for p in s.ranking), reverse=True)
    path = s.write(tmp_path / "next.toml")
    method = load_method(path)                              # what `foamlab run --method FILE` loads
    assert method.steps == s.best.protocol.method.steps
    assert s.best.over_noise > 1.0, s.lines()
    second = hidden_effect_run(effects, seed=seed + 1, method=method, height_mm=HEIGHT)
    both = diagnose([first, second])
    return d, s, both


def test_rate_dependence_with_one_run_gets_another_speed(tmp_path):
    """One run at one speed cannot show a rate dependence (the factor is 1 at the reference
    speed): the suggestion is a run at another speed, and the two runs name it."""
    d, s, both = _settles({"rate_dependence": 0.5}, 62, tmp_path, {"no rate_dependence", "rate_dependence"})
    assert "rate_dependence" in d.skipped and "rate_dependence" not in [c.name for c in d.findings]
    assert s.best.protocol.key in ("faster", "slower"), s.lines()
    assert both.verdict == "rate_dependence", [(c.name, c.reason) for c in both.tested[0]]
    assert both.findings[0].values["values"]["m"] == pytest.approx(0.5, abs=0.15)


def test_friction_or_damping_change_settled(tmp_path):
    """A friction of 1 N at one speed: direction_friction and damping_cycle_change within 10 of
    Delta BIC (31.6 vs 23.1 at seed 5 on one CPU, 11.6 vs 8.3 at seed 8 on another); the suggested
    test (more cycles: a damping change per cycle grows) names the friction."""
    _, s, both = _settles({"direction_friction": 1.0}, (5, 8, 11, 4), tmp_path,
                          {"direction_friction", "damping_cycle_change"})
    assert "within" in s.why
    assert both.verdict == "direction_friction", [(c.name, c.delta_bic, c.reason) for c in both.tested[0]]


def test_method_file_round_trip_and_cli(tmp_path, capsys):
    """`--suggest FILE --json`: the JSON carries the suggestion, FILE is a method that loads."""
    run = hidden_effect_run({"rate_dependence": 0.5}, seed=62, height_mm=HEIGHT, sampling_hz=1.0)
    csv = tmp_path / "run.csv"
    with open(csv, "w", encoding="utf-8") as fh:
        fh.write("time_s,displacement_mm,force_N\n")
        fh.writelines(f"{t:.5f},{x:.6f},{f:.5f}\n" for t, x, f in zip(run.time_s, run.displacement_mm, run.force_N))
    out = tmp_path / "next.toml"
    assert cli.main(["diagnose", str(csv), "--json", "--suggest", str(out), "--no-store"]) == 0
    obj = json.loads(capsys.readouterr().out)
    sug = obj["suggestion"]
    assert sug["made"] and sug["method_file"] == str(out) and sug["ranking"][0]["protocol"] == sug["best"]
    method = load_method(out)
    assert parse_method(tomllib.loads(method_toml(method)), source="again").steps == method.steps
    # --suggest with a data file as FILE would overwrite it: refused in one line
    assert cli.main(["diagnose", str(csv), "--suggest", str(csv)]) == 2
    assert "must end in .toml" in capsys.readouterr().err


def test_no_close_call_no_suggestion():
    """Two runs at two speeds of a clean specimen: nothing close, nothing waiting for a run."""
    runs = [hidden_effect_run(None, seed=63, height_mm=HEIGHT, **FAST),
            hidden_effect_run(None, seed=64, speed_mm_min=47.2, height_mm=HEIGHT, **FAST)]
    s = suggest(diagnose(runs), HEIGHT)
    assert not s.made and f"{CLOSE_DELTA_BIC:g}" in s.why
    assert s.to_dict() == {"made": False, "why": s.why}
