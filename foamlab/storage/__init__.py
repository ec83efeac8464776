"""Where runs live: run files written as they are acquired, and the run catalog.

- foamlab.storage.recorder: Recorder, what the run engine hands each sample to (file naming,
  header, step and cycle columns, flush + fsync thread, full-disk handling, the run's arrays);
- foamlab.storage.runfile: RunWriter (one flushed line per sample, self-describing
  ``#`` header, status trailer), read_run_file, write_run_file;
- foamlab.storage.catalog: Catalog (SQLite/WAL index of runs, fits, diagnoses,
  rebuildable from the files), data_dir(), sidecar_path().
"""

from foamlab.storage.catalog import Catalog, data_dir, sidecar_path
from foamlab.storage.recorder import Recorder, RecordingFailed
from foamlab.storage.runfile import RunWriter, read_run_file, write_run_file

__all__ = ["Catalog", "Recorder", "RecordingFailed", "RunWriter", "data_dir", "read_run_file", "sidecar_path",
           "write_run_file"]
