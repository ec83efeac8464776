"""foamlab.prediction: the forecast of a run's next cycle from its first ones, the departure rule
that says in words when the specimen leaves it, the live predictor off the acquisition thread,
and each cycle's forecast score. Runs are made by the model itself (the paper's strokes at
50 mm/min, the simulator's load-cell noise); the window and `foamlab run` are tested with the
simulated machine in tests/test_gui_prediction.py."""

from __future__ import annotations

import io
import threading
import types

import numpy as np
import pytest

from foamlab import FoamlabError
from foamlab.commands.run import PredictionLines, ProgressLine
from foamlab.methods import parse_method
from foamlab.model import ModelParameters, label_history, triangular_history
from foamlab.model.effects import CycleSoftening, EffectChain
from foamlab.prediction import DepartureWatch, StepForecast, forecast_scores, make_forecast, score_cycle
from foamlab.prediction.departure import RELATIVE_FLOOR
from foamlab.prediction.live import LivePredictor
from foamlab.rundata import RunData

NOISE_N = 0.05              # the simulated load cell's
HZ = 16.0
SPEED = 50.0                # mm/min
AMPLITUDE = 58.0            # 80 % of the default 72.5 mm block
METHOD = parse_method({
    "name": "three", "sampling_hz": HZ,
    "contact": {"preload_N": 0.5, "search_speed_mm_min": 20.0, "max_search_mm": 30.0},
    "park": {"speed_mm_min": 400.0},
    "sequence": [{"repeat": 3, "steps": [{"action": "compress", "strain": AMPLITUDE / 72.5, "speed_mm_min": SPEED},
                                         {"action": "return", "speed_mm_min": SPEED}]}]})
PLAN = METHOD.plan(72.5)


def model_run(effects=(), seed=1) -> tuple[RunData, np.ndarray]:
    """Three triangular cycles through the model (and `effects`), with the load cell's noise;
    and the plan step of each sample (the turn's sample belongs to the step that ends there)."""
    t, x = triangular_history(AMPLITUDE, SPEED / 60.0, 3, HZ)
    force = EffectChain(list(effects)).measured_force(ModelParameters.default(), t, x, labels=label_history(x))
    force = force + np.random.default_rng(seed).normal(0.0, NOISE_N, len(t))
    half = AMPLITUDE / (SPEED / 60.0)
    step = np.clip(np.ceil(t / half).astype(int) - 1, 0, 5)
    return RunData(t, x, force, source=f"model seed {seed}"), step


def through_cycle(run: RunData, step: np.ndarray, k: int) -> RunData:
    return run.slice(0, int(np.searchsorted(step, 2 * k - 1, side="right")))


def watch_cycle_3(forecast, run: RunData, step: np.ndarray):
    watch = DepartureWatch(forecast.noise_N, HZ)
    found = []
    for s in (4, 5):
        rows = np.flatnonzero(step == s)
        t = run.time_s[rows]
        _, departures = watch.compare(forecast.step(s), forecast.from_cycles, run.displacement_mm[rows],
                                      t - t[0], run.force_N[rows], t)
        found += departures
    return found


def flat_step(force_per_mm=3.0, sigma=0.0) -> StepForecast:
    x = np.linspace(0.0, 58.0, 1393)
    return StepForecast(4, 3, "loading", x / (SPEED / 60.0), x, force_per_mm * x, np.full_like(x, sigma),
                        np.zeros_like(x))


# --------------------------------------------------------------------------- the departure rule

def test_a_departure_is_said_in_words_with_where_it_began():
    step = flat_step()
    rng = np.random.default_rng(0)
    x = step.displacement_mm
    measured = step.force_N + rng.normal(0.0, NOISE_N, len(x)) - np.where(x >= 31.0, 4.0, 0.0)
    watch = DepartureWatch(NOISE_N, HZ)
    compared, found = watch.compare(step, 2, x, step.time_s, measured, step.time_s)
    assert len(found) == 1
    d = found[0]
    assert d.message.startswith("cycle 3 loading: 4.0 N below the prediction since 3")
    assert 30.0 <= d.since_mm <= 31.5 and d.at_mm > d.since_mm and d.below
    assert len(compared.residual_N) == len(x)
    # once per half-cycle: the rest of the loading stays below without a second message
    assert not watch.compare(step, 2, x, step.time_s, measured, step.time_s)[1]


def test_noise_and_a_one_percent_misreading_are_not_departures():
    step = flat_step()
    x = step.displacement_mm
    for seed in range(20):
        noisy = step.force_N + np.random.default_rng(seed).normal(0.0, NOISE_N, len(x))
        assert not DepartureWatch(NOISE_N, HZ).compare(step, 2, x, step.time_s, noisy, step.time_s)[1]
    gain = step.force_N * (1 - 0.8 * RELATIVE_FLOOR)           # a load cell reading 0.8 % low
    assert not DepartureWatch(NOISE_N, HZ).compare(step, 2, x, step.time_s, gain, step.time_s)[1]


def test_the_watch_refuses_a_noise_level_that_is_not_a_number():
    with pytest.raises(ValueError, match="noise level must be a positive number"):
        DepartureWatch(float("nan"), HZ)


# --------------------------------------------------------------------------- forecast and score

def test_two_cycles_predict_the_third_within_what_the_noise_allows():
    run, step = model_run(seed=1)
    forecast = make_forecast(through_cycle(run, step, 2), PLAN, 2, HZ, 3)
    assert sorted(forecast.steps) == [4, 5] and {s.cycle for s in forecast.steps.values()} == {3}
    assert forecast.describe().startswith("cycle 3 predicted from cycles 1-2 (fit RMSE")
    assert forecast.fit_rmse_N < 1.2 * NOISE_N
    assert not watch_cycle_3(forecast, run, step)
    score = score_cycle(forecast, run, np.flatnonzero(step >= 4), 3)
    assert score.cycle == 3 and score.from_cycles == 2 and score.n_samples == np.count_nonzero(step >= 4)
    # a forecast, not a fit: worse than the noise, far better than the force (~175 N at the peak)
    assert 1.0 < score.ratio < 60 and score.rmse_N < 3.0


def test_a_specimen_softening_from_cycle_3_leaves_the_prediction_in_its_loading():
    run, step = model_run([CycleSoftening(0.1, from_cycle=3)], seed=1)
    forecast = make_forecast(through_cycle(run, step, 2), PLAN, 2, HZ, 3)
    found = watch_cycle_3(forecast, run, step)
    assert found and found[0].phase == "loading" and found[0].below
    assert found[0].message.startswith("cycle 3 loading: ")


def test_no_forecast_from_a_fit_that_misses_its_own_cycles():
    run, step = model_run([CycleSoftening(0.1)], seed=1)          # softer from cycle 2 on: the model cannot
    with pytest.raises(FoamlabError, match=r"the model misses cycles 1-2 by \d+(\.\d)? x the noise"):
        make_forecast(through_cycle(run, step, 2), PLAN, 2, HZ, 3)


def test_offline_scores_predict_each_cycle_from_the_ones_before():
    run, step = model_run(seed=2)
    scores = forecast_scores(run)
    assert [(s.cycle, s.from_cycles) for s in scores.scores] == [(3, 2)] and not scores.live
    assert scores.scores[0].ratio < 60
    two = forecast_scores(through_cycle(run, step, 2))
    assert not two and "needs 2 cycles before the one it predicts" in two.note


# --------------------------------------------------------------------------- live

class Heard:
    def __init__(self) -> None:
        self.events: list[tuple[str, object]] = []
        self.threads: set[str] = set()
        self.forecast = threading.Event()

    def _add(self, kind, value) -> None:
        self.events.append((kind, value))
        self.threads.add(threading.current_thread().name)

    def on_forecast(self, f):
        self._add("forecast", f)
        self.forecast.set()

    def on_departure(self, d):
        self._add("departure", d)

    def on_score(self, s):
        self._add("score", s)

    def on_note(self, text):
        self._add("note", text)


def test_the_live_predictor_works_beside_the_run_and_scores_it():
    """The engine's side is one queue put per sample; the fits run in the worker process."""
    run, step = model_run([CycleSoftening(0.1, from_cycle=3)], seed=3)
    predictor = LivePredictor(PLAN, HZ, 3)
    heard = Heard()
    predictor.add_listener(heard)
    predictor.start()
    first_of_3 = int(np.searchsorted(step, 4))
    try:
        for i in range(len(run)):
            predictor.on_sample(types.SimpleNamespace(time_s=run.time_s[i], displacement_mm=run.displacement_mm[i],
                                                      force_N=run.force_N[i], cycle=int(step[i]) // 2 + 1,
                                                      step=int(step[i])))
            if i == first_of_3:     # cycle 2 is complete: its forecast comes while cycle 3 is measured
                assert heard.forecast.wait(120.0), predictor.notes
        predictor.on_finished(types.SimpleNamespace(status="finished"))
        scores = predictor.finish(120.0)
    finally:
        predictor.close()
    kinds = [k for k, _ in heard.events]
    assert kinds[0] == "forecast" and heard.events[0][1].from_cycles == 2
    assert "departure" in kinds and kinds.index("departure") > 0
    d = next(v for k, v in heard.events if k == "departure")
    assert d.cycle == 3 and d.phase == "loading"
    assert [(s.cycle, s.from_cycles) for s in scores.scores] == [(3, 2)] and scores.live
    assert heard.threads == {"foamlab-prediction"}        # never the caller's (the engine's) thread


def test_foamlab_run_says_a_departure_at_once_on_its_own_line():
    stream = io.StringIO()
    lines = PredictionLines(ProgressLine(stream))
    d = types.SimpleNamespace(message="cycle 3 loading: 4.1 N below the prediction since 31 mm")
    lines.on_departure(d)
    lines.on_note("no prediction from cycles 1-2: the model misses cycles 1-2 by 8.4 x the noise")
    assert stream.getvalue().splitlines() == [
        "prediction: cycle 3 loading: 4.1 N below the prediction since 31 mm",
        "prediction: no prediction from cycles 1-2: the model misses cycles 1-2 by 8.4 x the noise"]
