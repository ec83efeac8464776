"""Test methods: loading/validation of configs/methods/*.toml and the method results
(hysteresis loss, energies, residual strain, CV40, CFD) on synthetic runs whose
answers are known in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from foamlab import FoamlabError
from foamlab.methods import available_methods, cycle_spans, load_method, parse_method
from foamlab.rundata import RunData, Specimen

HEIGHT = 72.5
AREA_SIDE = 100.0


def synthetic_run(method, height=HEIGHT, *, stiffness=None, unload_ratio=0.6, residual_mm=2.0,
                  relax=0.3, tau_s=10.0, noise=0.0, seed=0, stop_after_s=None):
    """Run the method's plan on an ideal crosshead at its sampling rate; piecewise linear foam.

    loading of cycle c: F = k_c * (x - r_{c-1})+    (r_0 = 0: the first touch is at zero)
    unloading:          F = unload_ratio * k_c * (x - r_c)+ with r_c = residual_mm (contact loss)
    dwell at the peak:  F relaxes to (1 - relax) of its peak value with time constant tau_s.
    """
    stiffness = stiffness or {}
    dt = 1.0 / method.sampling_hz
    t_all, x_all, f_all = [0.0], [0.0], [0.0]
    t = 0.0
    peak_force = 0.0
    for planned in method.plan(height):
        step = planned.step
        k = stiffness.get(step.cycle, 4.0)
        r_prev = 0.0 if step.cycle == 1 else residual_mm
        n = max(int(round(planned.duration_s / dt)), 1)
        for i in range(1, n + 1):      # each step's samples end on its target
            t += dt
            frac = i / n
            x = planned.start_mm + frac * (planned.end_mm - planned.start_mm)
            if step.action == "compress":
                f = k * max(x - r_prev, 0.0)
                peak_force = f
            elif step.action == "dwell" and planned.start_mm > 0:
                f = peak_force * (1 - relax * (1 - np.exp(-(i * dt) / tau_s)))
            elif step.action == "dwell":
                f = 0.0
            else:
                f = unload_ratio * k * max(x - residual_mm, 0.0)
            t_all.append(t)
            x_all.append(x)
            f_all.append(f)
    t_all, x_all, f_all = map(np.asarray, (t_all, x_all, f_all))
    if noise:
        f_all = f_all + np.random.default_rng(seed).normal(0, noise, len(f_all))
    if stop_after_s is not None:
        keep = t_all <= stop_after_s
        t_all, x_all, f_all = t_all[keep], x_all[keep], f_all[keep]
    return RunData(t_all, x_all, f_all, Specimen("synthetic", height, AREA_SIDE, AREA_SIDE), method=method.name)


# --------------------------------------------------------------------------- the shipped methods

def test_shipped_methods_load():
    assert {"paper-3cycle", "iso3386-1", "astm-d3574-c"} <= set(available_methods())
    paper = load_method("paper-3cycle")
    assert paper.sampling_hz == 16
    assert paper.n_cycles == 3
    assert [s.action for s in paper.steps] == ["compress", "return"] * 3
    assert all(s.speed_mm_min == 23.6 for s in paper.steps)
    assert all(s.strain == 0.80 for s in paper.steps if s.action == "compress")
    # 58 mm down and up three times at 23.6 mm/min: 6 x 147.46 s
    assert paper.duration_s(HEIGHT) == pytest.approx(6 * 58.0 / 23.6 * 60)
    assert paper.expected_samples(HEIGHT) == round(6 * 58.0 / 23.6 * 60 * 16)

    iso = load_method("iso3386-1")
    assert iso.n_cycles == 4 and iso.max_strain == 0.70 and iso.max_speed_mm_min >= 100
    assert [v.name for v in iso.values] == ["CV40"] and iso.values[0].cycle == 4

    astm = load_method("astm-d3574-c")
    assert astm.n_cycles == 3
    assert astm.values[0].name == "CFD" and astm.values[0].dwell_s == 60
    measure = [s for s in astm.steps if s.cycle == 3]
    assert [s.action for s in measure] == ["compress", "dwell", "return"]
    assert measure[0].strain == 0.5 and measure[0].speed_mm_min == 50


def test_plan_durations_include_dwells():
    astm = load_method("astm-d3574-c")
    plan = astm.plan(50.0)
    dwell = [p for p in plan if p.step.action == "dwell"]
    assert [p.duration_s for p in dwell] == [360.0, 60.0]
    assert dwell[1].start_mm == dwell[1].end_mm == pytest.approx(25.0)


# --------------------------------------------------------------------------- results

def test_paper_results_match_closed_forms():
    method = load_method("paper-3cycle")
    run = synthetic_run(method, stiffness={1: 4.0, 2: 3.0, 3: 2.8}, unload_ratio=0.6, residual_mm=2.0)
    spans = cycle_spans(method, run)
    assert [s.cycle for s in spans] == [1, 2, 3] and all(s.complete for s in spans)
    res = method.compute_results(run)
    X = 0.8 * HEIGHT
    r = 2.0
    for cycle, k in ((1, 4.0), (2, 3.0), (3, 2.8)):
        r_prev = 0.0 if cycle == 1 else r
        loading = k * (X - r_prev) ** 2 / 2 / 1000
        unloading = 0.6 * k * (X - r) ** 2 / 2 / 1000
        assert res.get("loading_energy", cycle).value == pytest.approx(loading, rel=2e-3)
        assert res.get("unloading_energy", cycle).value == pytest.approx(unloading, rel=2e-3)
        assert res.get("hysteresis_loss", cycle).value == pytest.approx(100 * (1 - unloading / loading), abs=0.1)
        # contact is lost where the unloading force falls to the method's preload (0.5 N)
        lost_at = r + method.contact.preload_N / (0.6 * k)
        assert res.get("residual_strain", cycle).value == pytest.approx(lost_at / HEIGHT, rel=1e-6)
    assert "hysteresis_loss (cycle 1)" in res.summary()


def test_results_are_robust_to_load_cell_noise():
    method = load_method("paper-3cycle")
    clean = method.compute_results(synthetic_run(method))
    noisy = method.compute_results(synthetic_run(method, noise=0.2, seed=3))
    for name in ("loading_energy", "unloading_energy", "hysteresis_loss"):
        assert noisy.get(name, 2).value == pytest.approx(clean.get(name, 2).value, rel=0.01)
    # the contact threshold (preload 0.5 N) is above the noise: residual strain within ~0.1 mm
    assert noisy.get("residual_strain", 2).value == pytest.approx(clean.get("residual_strain", 2).value,
                                                                  abs=0.1 / HEIGHT)


def test_iso_cv40():
    method = load_method("iso3386-1")
    run = synthetic_run(method, stiffness={4: 2.5}, residual_mm=1.0)
    cv40 = method.compute_results(run).get("CV40")
    # cycle 4 loading: F = 2.5 (x - 1.0) at x = 0.4 h; area 100 x 100 mm; N/mm^2 -> kPa x 1000
    expected = 2.5 * (0.4 * HEIGHT - 1.0) / (AREA_SIDE * AREA_SIDE) * 1000
    assert cv40.unit == "kPa" and cv40.cycle == 4
    assert cv40.value == pytest.approx(expected, rel=1e-3)


def test_astm_cfd_reads_the_force_at_the_end_of_the_dwell():
    method = load_method("astm-d3574-c")
    run = synthetic_run(method, stiffness={3: 3.0}, residual_mm=1.0, relax=0.3, tau_s=10.0)
    cfd = method.compute_results(run).get("CFD")
    peak = 3.0 * (0.5 * HEIGHT - 1.0)
    dt = 1 / 16
    n = int(round(60 / dt))
    end_force = peak * (1 - 0.3 * (1 - np.exp(-((n - 1) * dt) / 10.0)))
    assert cfd.value == pytest.approx(end_force / 1e4 * 1000, rel=1e-4)
    # well below the peak stress: the dwell relaxation is in it
    assert cfd.value < 0.75 * peak / 1e4 * 1000


def test_results_of_an_aborted_run_say_what_is_missing():
    method = load_method("astm-d3574-c")
    full = synthetic_run(method)
    dwell_start = full.time_s[cycle_spans(method, full)[2].hold[0]]
    run = synthetic_run(method, stop_after_s=dwell_start + 30)      # stopped half-way through the dwell
    res = method.compute_results(run)
    cfd = res.get("CFD")
    assert cfd.value is None and "dwell" in cfd.note
    assert res.get("hysteresis_loss", 3).value is None
    assert res.get("hysteresis_loss", 1).value is not None
    short = method.compute_results(synthetic_run(method, stop_after_s=10))
    assert short.get("CFD").value is None and "cycle 3" in short.get("CFD").note


def test_stress_results_need_the_area():
    method = load_method("iso3386-1")
    run = synthetic_run(method)
    run.specimen = Specimen("no area", HEIGHT)
    cv40 = method.compute_results(run).get("CV40")
    assert cv40.value is None and "width and depth" in cv40.note
    assert "n/a" in cv40.format()


# --------------------------------------------------------------------------- validation

BASE = {
    "name": "t", "sampling_hz": 16.0,
    "contact": {"preload_N": 0.5, "search_speed_mm_min": 20.0, "max_search_mm": 50.0},
    "sequence": [{"steps": [{"action": "compress", "strain": 0.5, "speed_mm_min": 10.0},
                            {"action": "return", "speed_mm_min": 10.0}]}],
}


def _with(**changes):
    import copy

    data = copy.deepcopy(BASE)
    for key, value in changes.items():
        if value is None:
            data.pop(key)
        else:
            data[key] = value
    return data


@pytest.mark.parametrize("data, message", [
    (_with(sampling_hz=None), "missing `sampling_hz`"),
    (_with(sampling_hz=0), "`sampling_hz` must be > 0"),
    (_with(sampling_hz="16"), "`sampling_hz` must be a number"),
    (_with(contact=None), "missing `contact`"),
    (_with(speling=1), "unknown key `speling`"),
    (_with(sequence=[]), "needs at least one [[sequence]]"),
    (_with(sequence=[{"steps": [{"action": "compress", "strain": 1.2, "speed_mm_min": 10}]}]), "`strain` must be <= 0.95"),
    (_with(sequence=[{"steps": [{"action": "return", "speed_mm_min": 10}]}]), "`return` without a `compress`"),
    (_with(sequence=[{"steps": [{"action": "compress", "strain": 0.5, "speed_mm_min": 10}]}]), "must end with a `return`"),
    (_with(sequence=[{"steps": [{"action": "jump"}]}]), "`action` must be one of compress, return, dwell"),
    (_with(sequence=[{"steps": [{"action": "dwell", "duration_s": -1}]}]), "`duration_s` must be > 0"),
    (_with(sequence=[{"repeat": 0, "steps": [{"action": "dwell", "duration_s": 1}]}]), "`repeat` must be >= 1"),
    (_with(results={"values": [{"name": "X", "quantity": "stress_at_strain", "cycle": 2, "strain": 0.4}]}),
     "cycle 2 does not exist"),
    (_with(results={"values": [{"name": "X", "quantity": "stress_at_strain", "cycle": 1, "strain": 0.6}]}),
     "beyond cycle 1's peak strain"),
    (_with(results={"values": [{"name": "X", "quantity": "stress_at_dwell_end", "cycle": 1}]}),
     "needs a dwell right after the compress"),
    (_with(results={"per_cycle": ["bogus"]}), "`per_cycle` entry 'bogus'"),
])
def test_invalid_methods_give_one_clear_line(data, message):
    with pytest.raises(FoamlabError) as err:
        parse_method(data, source="bad.toml")
    text = str(err.value)
    assert message in text and text.startswith("method bad.toml") and "\n" not in text


def test_unknown_method_lists_the_available_ones(tmp_path):
    with pytest.raises(FoamlabError, match="unknown method 'nope' .*paper-3cycle"):
        load_method("nope")
    bad = tmp_path / "broken.toml"
    bad.write_text("name = [\n")
    with pytest.raises(FoamlabError, match="broken.toml: not valid TOML"):
        load_method(bad)
    with pytest.raises(FoamlabError, match="method file not found"):
        load_method(tmp_path / "missing.toml")


def test_method_from_a_path(tmp_path):
    path = tmp_path / "quick.toml"
    path.write_text(
        'name = "quick"\nsampling_hz = 16.0\n'
        '[contact]\npreload_N = 0.5\nsearch_speed_mm_min = 100.0\nmax_search_mm = 20.0\n'
        '[[sequence]]\nrepeat = 2\nsteps = [{ action = "compress", strain = 0.1, speed_mm_min = 200.0 },'
        ' { action = "dwell", duration_s = 0.5 }, { action = "return", speed_mm_min = 200.0 }]\n')
    m = load_method(path)
    assert m.n_cycles == 2 and m.per_cycle == ("hysteresis_loss", "energy", "residual_strain")
    assert m.duration_s(50.0) == pytest.approx(4 * 5.0 / 200 * 60 + 1.0)
