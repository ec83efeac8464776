"""One row per run of a batch: what the pipeline found, flat enough for a table.

A row is a BatchRow; in the output file (CSV or Parquet) and its journal it is a flat record
whose columns are the fields below plus one ``p_<name>`` column per fitted model parameter.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from foamlab import __version__

NAN = float("nan")
PARAMETER_PREFIX = "p_"

#: error_kind values: "" (no error), "read" (the file is not a run foamlab reads), "fit",
#: "diagnosis" (that stage failed; the row keeps what came before) and "task" (the batch
#: machinery lost the run: its worker died too often, or no result came in time). Rows of
#: the first four are results (a re-run with the same content skips them); "task" rows are retried.
ERROR_KINDS = ("", "read", "fit", "diagnosis", "task")


@dataclass
class BatchRow:
    file: str                          # the path as found (absolute)
    sha256: str                        # of the file's bytes: the key of a result
    format: str = ""                   # foamlab.importers' name of the file's format
    specimen: str = ""
    started_at: str = ""               # the test date, when the file records one
    status: str = ""                   # RunData.status (finished, imported, aborted, ...)
    cycles: int = 0
    samples: int = 0
    orders: str = ""                   # "N,M,P": damping modes, residual terms per cycle, elastic order
    form: str = ""                     # the residual form the fit kept: causal or paper
    rmse: float = NAN                  # N, the fit's, on all recorded samples (first cycle's start to last's end)
    rmse_samples: int = 0              # how many samples rmse covers
    dropped: int = 0                   # samples left out before the fit: taken off the sampling schedule
    noise: float = NAN                 # N, the load cell's noise level estimated from the data
    verdict: str = ""                  # a catalogue cause, "unexplained" or "none"
    effect: str = ""                   # the top finding ("" when the verdict is none)
    rmse_before: float = NAN           # the top finding's gain: RMSE before and after the extension, on
    rmse_after: float = NAN            # the diagnosis's evidence samples (not rmse's set: turn samples out)
    evidence_samples: int = 0          # how many samples rmse_before and rmse_after cover
    gain: float = NAN                  # rmse_before / rmse_after (> 1: the extension helps)
    elapsed_s: float = NAN             # on the worker: read, fit, diagnosis, files
    error: str = ""                    # one line
    error_kind: str = ""               # see ERROR_KINDS
    note: str = ""                     # a side matter: sidecar files or catalog not written
    version: str = __version__         # foamlab's, which made the row
    parameters: dict[str, float] = field(default_factory=dict)   # fitted model parameters by name

    @property
    def is_result(self) -> bool:
        """A result of this content (kept on a re-run), not a run the batch machinery lost."""
        return self.error_kind != "task"

    def to_record(self) -> dict[str, Any]:
        record = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "parameters"}
        record.update({PARAMETER_PREFIX + k: float(v) for k, v in self.parameters.items()})
        return record

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> "BatchRow":
        """The row of a record read back from the output file or the journal (missing or
        empty cells take the defaults; NaN text cells of a CSV become "")."""
        kwargs: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name == "parameters" or f.name not in record:
                continue
            kwargs[f.name] = _typed(record[f.name], f.default)
        kwargs["parameters"] = {k[len(PARAMETER_PREFIX):]: float(v) for k, v in record.items()
                                if k.startswith(PARAMETER_PREFIX) and _finite(v)}
        return cls(**kwargs)


def _finite(value: Any) -> bool:
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def _typed(value: Any, default: Any) -> Any:
    if isinstance(default, str) or default is dataclasses.MISSING:
        return "" if value is None or (isinstance(value, float) and math.isnan(value)) else str(value)
    if isinstance(default, int):
        return int(value) if _finite(value) else default
    return float(value) if _finite(value) else NAN
