"""Live prediction: the rest of a run predicted from its first cycles, while it runs.

- forecast.py: identify the model on the cycles measured so far and predict the rest of the
  method's plan, with the prediction's own uncertainty; score each cycle's forecast;
- departure.py: when the measurement leaves the prediction by more than the noise allows,
  in words ("cycle 3 loading: 4.1 N below the prediction since 31 mm");
- live.py: LivePredictor, a run-engine listener that does both off the acquisition thread
  (the samples are only queued there; the fits run in a worker process).

See docs/prediction.md.
"""

from foamlab.prediction.departure import Departure, DepartureWatch
from foamlab.prediction.forecast import (MIN_CYCLES, CycleScore, Forecast, ForecastScores, StepForecast,
                                         forecast_scores, make_forecast, score_cycle)

__all__ = ["MIN_CYCLES", "CycleScore", "Departure", "DepartureWatch", "Forecast", "ForecastScores",
           "StepForecast", "forecast_scores", "make_forecast", "score_cycle"]
