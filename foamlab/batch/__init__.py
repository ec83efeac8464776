"""An archive of runs fitted and diagnosed on Dask distributed: `foamlab batch`, and from Python

    from foamlab import batch
    table = batch.process(["archive/"], out="results.parquet")   # pandas.DataFrame, one row per run
    batch.write_summary(table, "summary.html")                   # verdicts, parameters, odd runs out

Each run goes through foamlab.pipeline (the same stages as `foamlab run`) in its own Dask task,
on a LocalCluster of processes by default or on any cluster (client= or scheduler=). See
docs/batch.md. Modules: engine (find, hash, submit, collect), task (one run on a worker), rows
(BatchRow: one row), store (journal, output file, catalog), summary (the HTML page).
"""

from foamlab.batch.engine import find_runs, process
from foamlab.batch.rows import BatchRow
from foamlab.batch.summary import write_summary

__all__ = ["BatchRow", "find_runs", "process", "write_summary"]
