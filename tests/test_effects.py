"""The diagnosis catalogue's effects: batch form == online form (inside SimulatedMachine),
each effect does what its docstring says, and the batch form is smooth in its parameters."""

import numpy as np
import pytest

from foamlab.model import ModelParameters, ModelResponse, SpecimenState, evaluate, label_history, triangular_history
from foamlab.model.effects import (
    EFFECTS,
    EffectChain,
    magnitude_for_ratio,
    make_effects,
    motion_direction,
    estimate_velocity,
    frame_force,
    parse_effect_option,
    relative_magnitude,
)
from simulator.clock import ManualClock
from simulator.machine import SPECIMEN_T_MAX_S, SimulatedMachine

pytestmark = pytest.mark.timeout(120)

CATALOGUE = ["cycle_softening", "damping_cycle_change", "channel_lag", "force_zero_drift",
             "machine_compliance", "direction_friction", "rate_dependence", "memory_lag"]
AMPLITUDE, SPEED = 20.0, 120.0          # a short protocol: 2 cycles, 10 s per half-cycle


@pytest.fixture(scope="module")
def params():
    return ModelParameters.default()


def online_model(params):
    """The base model stepped exactly as SimulatedMachine steps it (same operators, same steps)."""
    def model(t, x, labels=None):
        state = SpecimenState(params, t_max=SPECIMEN_T_MAX_S)
        comps = [state.step(ti, xi) for ti, xi in zip(t, x)]
        e, d, r = (np.array([getattr(c, k) for c in comps]) for k in ("elastic", "damping", "residual"))
        return ModelResponse(np.asarray(t), np.asarray(x), e, d, r, labels or label_history(x))
    return model


def run_machine(params, effects, speed=SPEED, cycles=2, max_step_s=0.05):
    """Two triangular cycles from contact, with a 1 s hold at each peak; the noise-free trace."""
    clock = ManualClock()
    m = SimulatedMachine(clock=clock, specimen=params, effects=effects, noise_sigma_N=0.0,
                         specimen_top_mm=0.0, max_step_s=max_step_s)
    m.start_trace()
    for _ in range(cycles):
        for target in (AMPLITUDE, 0.0):
            m.move_to(target, speed)
            clock.set(m.motion_eta())
            m.advance()
            clock.advance(1.0)
            m.advance()
    m.close()
    return m.trace()


@pytest.fixture(scope="module")
def base_trace(params):
    return run_machine(params, None)


def test_catalogue_is_complete():
    assert sorted(EFFECTS) == sorted(CATALOGUE)
    for name, cls in EFFECTS.items():
        assert cls.name == name and cls.__doc__ and len(cls.__doc__) > 80
        assert cls.parameters and all(p.unit for p in cls.parameters)
        lo, hi = cls.bounds()
        assert np.all(lo < cls().vector()) and np.all(cls().vector() < hi)
        e = cls(0.123)
        assert e.magnitude == 0.123 and e.with_vector(e.vector()).values == e.values


#: Online forms that are exact between physics steps only: a turn's jump read as a line across one
#: step, where the batch form reads it at the turn (model.turns; test_..._converges_... below).
ACROSS_TURNS = ("memory_lag",)


@pytest.mark.parametrize("name", [n for n in CATALOGUE if n not in ACROSS_TURNS])
def test_batch_equals_online(name, params, base_trace):
    effect = EFFECTS[name]()
    tr = run_machine(params, EffectChain([effect]))
    t, x, v = tr["t"], tr["x_crosshead_mm"], tr["velocity_mm_s"]
    online = tr["sensor_force_N"]
    # the effect is really there (against the same run without it)
    change = np.sqrt(np.mean((online - np.interp(t, base_trace["t"], base_trace["sensor_force_N"])) ** 2))
    assert change > 0.05, change                        # at least the load-cell noise
    # batch form on the machine's samples, with the machine's own stepping of the base model
    batch = effect.measured_force(online_model(params), t, x, velocity=v)
    assert np.abs(batch - online).max() < 1e-7 * np.abs(online).max() + 1e-9


def test_memory_lag_online_converges_to_the_batch_form_as_its_step_shrinks(params):
    """The simulator's memory_lag reads a turn's jump as a line across its physics step; the batch
    form reads it at the turn. Their difference is the online step's error: first order in it."""
    effect = EFFECTS["memory_lag"]()
    errors, largest = [], 0.0
    for step in (0.05, 0.0125):
        tr = run_machine(params, EffectChain([effect]), max_step_s=step)
        t, x, v, online = tr["t"], tr["x_crosshead_mm"], tr["velocity_mm_s"], tr["sensor_force_N"]
        batch = effect.measured_force(online_model(params), t, x, velocity=v)
        errors.append(np.abs(batch - online).max())
        largest = max(largest, np.abs(online).max())
    assert errors[0] < 0.03 * largest and errors[1] < 0.4 * errors[0], (errors, largest)


@pytest.mark.parametrize("name", CATALOGUE)
def test_vectorised_batch_on_a_uniform_clock(name, params):
    """With the library's vectorised evaluate (what diagnosis fits with) on a uniform clock,
    the batch form gives the same force as with the online stepping of the model."""
    t, x = triangular_history(AMPLITUDE, SPEED / 60, 2, 16.0)
    effect = EFFECTS[name]()
    fast = effect.measured_force(params, t, x)
    stepped = effect.measured_force(online_model(params), t, x)
    assert np.abs(fast - stepped).max() < 1e-4 * np.abs(stepped).max()


def test_compliance_loop_is_stable_and_closed_by_the_data(params):
    """At any physics step the simulator's force loop settles (no chatter), the specimen sees
    x - C G (G: the frame force), and diagnosis's one-pass form, fed the measured force,
    reproduces the simulator sample for sample."""
    c = EFFECTS["machine_compliance"].parameters[0].upper          # the worst case
    for step in (0.002, 0.05, 0.2, 0.5):
        clock = ManualClock()
        m = SimulatedMachine(clock=clock, specimen=params, effects={"machine_compliance": c},
                             noise_sigma_N=0.0, specimen_top_mm=0.0, max_step_s=step)
        m.start_trace()
        for target in (AMPLITUDE, 0.0):
            m.move_to(target, SPEED)
            clock.set(m.motion_eta())
            m.advance()
        m.close()
        tr = m.trace()
        t, x, f = tr["t"], tr["x_crosshead_mm"], tr["contact_force_N"]
        d = np.diff(f)
        d = d[np.abs(d) > 1e-9]
        assert np.sum(np.diff(np.sign(d)) != 0) <= 4, step                # rises, then falls
        loading = tr["velocity_mm_s"] > 0
        g = frame_force(t, f, EFFECTS["machine_compliance"].parameters[1].typical)
        assert np.allclose((x - tr["x_specimen_mm"])[loading], c * g[loading], atol=1e-12)
        r = make_effects({"machine_compliance": c}).response(
            online_model(params), t, x, velocity=tr["velocity_mm_s"], measured_force=f)
        assert np.abs(r.x_specimen - tr["x_specimen_mm"]).max() < 1e-12
        assert np.abs(r.force - f).max() < 1e-7 * f.max()


def test_a_frame_at_once_is_solved_in_batch_and_by_the_simulator(params):
    """tau_frame_s = 0 (what diagnosis fits): G is the force at the same instant, a loop the plain
    iteration cannot close at the upper bound C (C times the residual's one-step stiffness exceeds
    1). The batch form settles at x_s = x - C F(x_s); the simulator solves each step's loop on
    copies of its state. They agree while loading and in the holds; just after each turn the
    loop has no solution (the force drops as the specimen turns, which un-turns it) and the two
    keep different values there for a few samples (docs/analysis.md, "The frame at once")."""
    c = EFFECTS["machine_compliance"].parameters[0].upper
    frame = EFFECTS["machine_compliance"](c, tau_frame_s=0.0)
    tr = run_machine(params, EffectChain([frame]))
    t, x, v = tr["t"], tr["x_crosshead_mm"], tr["velocity_mm_s"]
    online = tr["sensor_force_N"]
    d = np.diff(online)
    d = d[np.abs(d) > 1e-9]
    assert np.sum(np.diff(np.sign(d)) != 0) <= 4                      # no chatter
    loading = v > 0
    assert np.abs((x - tr["x_specimen_mm"] - c * tr["contact_force_N"])[loading]).max() < 1e-8
    r = EffectChain([frame]).response(online_model(params), t, x, velocity=v)
    assert np.abs((x - r.x_specimen - c * r.contact_force)[loading]).max() < 1e-8
    assert np.abs(r.force - online)[v >= 0].max() < 1e-4
    assert np.abs(r.force - online).max() < 0.03 * online.max()
    # the frame is there: the specimen is compressed less (0.7 mm of 20) and reads lower
    plain = EffectChain().measured_force(online_model(params), t, x, velocity=v)
    assert online.max() < plain.max() - 0.3
    # fed its own force, the one-pass form (diagnosis's) gives the same specimen displacement
    again = EffectChain([frame]).response(online_model(params), t, x, velocity=v, measured_force=r.contact_force)
    assert np.abs(again.x_specimen - r.x_specimen).max() < 1e-8


def test_effects_do_what_their_docstrings_say(params, base_trace):
    t, x, v = base_trace["t"], base_trace["x_crosshead_mm"], base_trace["velocity_mm_s"]
    model = online_model(params)
    base = EffectChain().response(model, t, x, velocity=v)
    cyc = base.base.cycle
    # cycle_softening: cycle 1 untouched, cycle 2 elastic scaled by (1 - s)
    soft = EffectChain([EFFECTS["cycle_softening"](0.1)]).response(model, t, x, velocity=v)
    assert np.allclose(soft.force[cyc == 1], base.force[cyc == 1])
    c2 = (cyc == 2) & (base.contact_force > 0)
    expected = np.maximum(base.force[c2] - 0.1 * base.base.elastic[c2], 0)
    assert np.allclose(soft.force[c2], expected)
    # channel_lag: the force read tau seconds late
    lag = EFFECTS["channel_lag"](0.5).measured_force(model, t, x, velocity=v)
    assert np.allclose(lag, np.interp(t - 0.5, t, base.force))
    # force_zero_drift: + r t, visible where there is no contact
    drift = EFFECTS["force_zero_drift"](0.01).measured_force(model, t, x, velocity=v)
    assert np.allclose(drift - base.force, 0.01 * (t - t[0]))
    # direction_friction: +f loading, -f unloading, in contact, away from the turns
    fr = EFFECTS["direction_friction"](2.0).measured_force(model, t, x, velocity=v)
    loading = (v > 1.0) & (base.force > 5)
    unloading = (v < -1.0) & (base.force > 5)
    assert np.allclose((fr - base.force)[loading], 2.0) and np.allclose((fr - base.force)[unloading], -2.0)
    # damping_cycle_change: only loading half-cycles after the first change
    dc = EFFECTS["damping_cycle_change"](0.5).measured_force(model, t, x, velocity=v)
    changed = np.abs(dc - base.force) > 1e-9
    assert not changed[cyc == 1].any() and not changed[base.base.direction == -1].any()
    assert changed[(cyc == 2) & (base.base.direction == 1)].any()


def test_rate_dependence_is_invisible_at_the_reference_speed(params):
    slow = run_machine(params, {"rate_dependence": 0.5}, speed=23.6, cycles=1)
    plain = run_machine(params, None, speed=23.6, cycles=1)
    ramp = slow["t"] <= AMPLITUDE / (23.6 / 60) + 0.01          # the first loading, before the hold
    assert np.abs(slow["sensor_force_N"] - plain["sensor_force_N"])[ramp].max() < 1e-3
    during_hold = (slow["direction"] == 1) & ~ramp                # a pause lowers the mean rate
    assert np.all(slow["sensor_force_N"][during_hold] < plain["sensor_force_N"][during_hold])
    fast = run_machine(params, {"rate_dependence": 0.5}, speed=2 * 23.6, cycles=1)
    fast_plain = run_machine(params, None, speed=2 * 23.6, cycles=1)
    loading = fast["direction"] == 1
    ratio = (fast["sensor_force_N"] - fast_plain["sensor_force_N"])[loading]
    assert ratio.max() > 0.5          # damping x (2^0.5 - 1): visible at another speed


@pytest.mark.parametrize("name", CATALOGUE)
def test_batch_form_is_smooth_in_its_parameter(name, params, base_trace):
    t, x, v = base_trace["t"], base_trace["x_crosshead_mm"], base_trace["velocity_mm_s"]
    cls = EFFECTS[name]
    m0 = cls.parameters[0].typical
    h = 1e-3 * abs(m0)

    def f(m):
        return cls(m).measured_force(params, t, x, velocity=v)

    d1 = (f(m0 + h) - f(m0 - h)) / (2 * h)
    d2 = (f(m0 + h / 2) - f(m0 - h / 2)) / h
    assert np.linalg.norm(d1) > 0
    assert np.linalg.norm(d1 - d2) <= 0.02 * np.linalg.norm(d1)


def test_magnitude_relative_to_noise(params, base_trace):
    t, x, v = base_trace["t"], base_trace["x_crosshead_mm"], base_trace["velocity_mm_s"]
    m = magnitude_for_ratio("direction_friction", 3.0, params, t, x, noise_sigma_N=0.05, velocity=v)
    assert relative_magnitude(EFFECTS["direction_friction"](m), params, t, x, 0.05,
                              velocity=v) == pytest.approx(3.0, rel=1e-6)
    m = magnitude_for_ratio("cycle_softening", 5.0, params, t, x, noise_sigma_N=0.05, velocity=v)
    assert 0 < m < 0.9


def test_machine_applies_effects_from_names(params):
    clock = ManualClock()
    m = SimulatedMachine(clock=clock, specimen=params, effects={"force_zero_drift": 0.01},
                         noise_sigma_N=0.0, max_step_s=0.5)
    clock.set(100.0)
    assert m.read_load_cell().gross_N == pytest.approx(1.0, abs=0.01)   # no contact, 100 s of drift
    m.zero_load_cell()
    assert m.read_load_cell().gross_N == 0.0
    m.close()
    with pytest.raises(ValueError, match="unknown effect"):
        SimulatedMachine(clock=ManualClock(), effects={"gremlins": 1.0})
    with pytest.raises(ValueError, match=r"outside \[0, 0.01\] mm/N"):
        SimulatedMachine(clock=ManualClock(), effects={"machine_compliance": 0.05})
    with pytest.raises(ValueError, match="tau_s >= 0"):
        SimulatedMachine(clock=ManualClock(), effects={"channel_lag": -0.1})


def test_effect_options_parse_with_one_line_errors():
    assert parse_effect_option("channel_lag=0.25") == ("channel_lag", 0.25)
    for bad in ("channel_lag", "lag=1", "channel_lag=fast", "channel_lag=nan"):
        with pytest.raises(ValueError) as info:
            parse_effect_option(bad)
        assert "\n" not in str(info.value)


def test_motion_direction_and_velocity_estimate():
    x = np.array([0, 1, 2, 2, 2, 1, 0, 0, 1.0])
    assert list(motion_direction(x)) == [0, 1, 1, 1, 1, -1, -1, -1, 1]
    t = np.arange(0, 20, 0.0625)
    x = np.round(0.4 * t, 3)                              # 1 um encoder resolution
    v = estimate_velocity(t, x)
    assert np.abs(v[5:-5] - 0.4).max() < 0.01


def test_memory_lag_releases_the_force_after_a_turning_point(params, base_trace):
    """memory_lag: the damping and residual forces through a first-order response of time tau;
    the elastic force is not delayed; the model's jump at the turning point becomes a release."""
    t, x, v = base_trace["t"], base_trace["x_crosshead_mm"], base_trace["velocity_mm_s"]
    model = online_model(params)
    tau = 0.5
    base = EffectChain().response(model, t, x, velocity=v)
    lagged = EffectChain([EFFECTS["memory_lag"](tau)]).response(model, t, x, velocity=v)
    b = base.base
    memory = b.damping + b.residual
    expected = np.where(base.contact_force > 0, b.elastic + _first_order_along_the_path(params, t, x, tau), 0.0)
    inside = (lagged.contact_force > 0) & (base.contact_force > 0)
    # (the reference is an independent explicit stepping, first-order accurate, of the model's
    # memory along the path 200 x finer than the samples: the jump at the turn where it happens;
    # the library's operators there, the machine's SOE ones in the batch form: 0.063 N of 39 apart.
    # The jump as a line across the sampling step, as the batch form had it before: 0.47 N)
    err = np.abs(lagged.contact_force - np.maximum(expected, 0.0))[inside]
    assert err.max() < 3e-3 * np.abs(memory).max(), (err.max(), np.abs(memory).max())
    # the jump at the first turning point (end of the first loading, then a 1 s hold) is released
    peak = int(np.flatnonzero((b.cycle == 1) & (b.direction == 1))[-1])
    around = slice(peak, int(np.searchsorted(t, t[peak] + 3 * tau)))
    jump = np.abs(np.diff(base.contact_force[around])).max()
    release = np.abs(np.diff(lagged.contact_force[around])).max()
    assert jump > 5.0 and release < 0.3 * jump, (jump, release)
    later = (t > t[peak] + 10 * tau) & (b.cycle == 1) & (base.contact_force > 0)
    assert np.abs(lagged.contact_force - base.contact_force)[later].max() < 0.05 * np.abs(memory).max()


def _first_order_along_the_path(params, t, x, tau, refine=200):
    """Reference: the model's damping + residual on a uniform grid refine x finer than the samples
    (the path piecewise linear between them), stepped explicitly through y' = (u - y)/tau there."""
    fine = np.linspace(t[0], t[-1], refine * len(t))
    xf = np.interp(fine, t, x)
    comps = evaluate(params, fine, xf, label_history(xf))
    return _stepped(t, fine, comps.damping + comps.residual, tau)


def _first_order(t, u, tau):
    """Reference: y' = (u - y)/tau by fine explicit stepping of the linear interpolant."""
    fine = np.linspace(t[0], t[-1], 200 * len(t))
    return _stepped(t, fine, np.interp(fine, t, u), tau)


def _stepped(t, fine, uf, tau):
    """Explicit Euler of y' = (u - y)/tau on the fine grid, read at t."""
    y = np.empty_like(uf)
    y[0] = uf[0]
    dt = fine[1] - fine[0]
    for i in range(1, len(fine)):
        y[i] = y[i - 1] + dt * (uf[i - 1] - y[i - 1]) / tau
    return np.interp(t, fine, y)


@pytest.mark.parametrize("tau", [1e-5, 1.5e-3, 2.1e-3, 0.05])
def test_first_order_response_is_the_step_by_step_recursion(tau):
    """The exact response of y' = (u - y)/tau to u linear between samples, on a jittered 16 Hz clock
    with a repeated instant: y_i = a_i y_(i-1) + (1 - b_i) u_i + (b_i - a_i) u_(i-1), a = exp(-dt/tau),
    b = tau/dt (1 - a), written as the plain loop. Where every step is longer than the stretches
    first_order_response sums at once (tau < 2 ms), its result is this loop's to the bit."""
    from foamlab.model.effects import first_order_response

    rng = np.random.default_rng(11)
    dt = (1 + rng.uniform(-0.3, 0.3, 299)) / 16.0
    dt[40] = 0.0
    t = np.concatenate([[0.0], np.cumsum(dt)])
    u = rng.normal(size=(300, 3)) * 50.0
    y = np.empty_like(u)
    y[0] = u[0]
    for i in range(1, len(t)):
        h = t[i] - t[i - 1]
        if h <= 0:
            y[i] = y[i - 1]                  # no time: the state kept
            continue
        a = np.exp(-h / tau)
        b = -np.expm1(-h / tau) * tau / h
        y[i] = a * y[i - 1] + ((1 - b) * u[i] + (b - a) * u[i - 1])
    got = first_order_response(t, u, tau)
    if tau < 2e-3:
        assert np.array_equal(got, y)
    else:
        np.testing.assert_allclose(got, y, rtol=1e-9, atol=1e-9 * np.abs(u).max())
    np.testing.assert_array_equal(first_order_response(t, u[:, 1], tau), got[:, 1])
