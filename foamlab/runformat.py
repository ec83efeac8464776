"""The run-file format's shared definitions: what its writer and its readers both know.

The writer (foamlab.storage.runfile, which documents the layout) and the readers
(foamlab.importers: a run file is a plain CSV with a richer ``#`` header) import
these from here, so neither imports the other to learn the format: storage uses
importers to read a run file back, importers never use storage.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

from foamlab import FoamlabError
from foamlab.rundata import Specimen

MAGIC = "# foamlab run file v1"
BASE_COLUMNS = ("time_s", "displacement_mm", "force_N")
#: Each sample's method step (0-based index in the plan) and cycle (1-based): RunData.step / .cycle.
LABEL_COLUMNS = ("step", "cycle")
META_PREFIX = "meta."
#: Metadata keys of what the engine knew of the run: the machine profile's name (header), the
#: schedule's statistics and how the run ended (trailer; `abort_reason` says why).
PROFILE_KEY = "machine_profile"
SCHEDULE_KEY = "schedule"
END_KEY = "end"
#: Header metadata: the crosshead's position resolution in mm (drivers' Crosshead.position_resolution_mm);
#: absent (imports, older files) or 0: unknown.
RESOLUTION_KEY = "position_resolution_mm"
_KEY_VALUE = re.compile(r"^#\s*([A-Za-z_][\w.\-]*)\s*:\s?(.*)$")

#: Header keys that map onto RunData fields (the rest is metadata).
RUN_FIELDS = ("method", "machine", "started_at", "finished_at", "status", "abort_reason")
SPECIMEN_FIELDS = {"specimen_label": "label", "specimen_height_mm": "height_mm",
                   "specimen_width_mm": "width_mm", "specimen_depth_mm": "depth_mm"}
NO_TRAILER_REASON = "the file has no status line: the run was interrupted (or is still being written)"


def is_run_file(first_line: str) -> bool:
    """The first line of a foamlab run file (what a reader already holds)."""
    return first_line.lstrip("\ufeff").startswith("# foamlab run file")


def is_run_file_path(path: str | Path) -> bool:
    """A foamlab run file on disk: its analyses may be kept beside it, it is catalogued; a
    vendor export is not ours. An unreadable file is not one."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            return is_run_file(fh.readline())
    except OSError:
        return False


def header_value(line: str) -> tuple[str, str] | None:
    """(key, value) of a ``# key: value`` line, None for any other line."""
    m = _KEY_VALUE.match(line)
    return (m.group(1), m.group(2).strip()) if m else None


def position_resolution_mm(metadata: dict[str, Any]) -> float:
    """The run's position resolution (RESOLUTION_KEY), mm; 0 when the run does not say."""
    value = metadata.get(RESOLUTION_KEY, 0.0)
    try:
        q = float(value)
    except (TypeError, ValueError):
        q = math.nan
    if not (math.isfinite(q) and q >= 0):
        raise FoamlabError(f"{RESOLUTION_KEY} must be a number >= 0 (mm), got {value!r}")
    return q


def runfile_fields(header: dict[str, str]) -> dict[str, Any]:
    """RunData keyword arguments from ``# key: value`` lines (run files and plain CSVs)."""
    fields: dict[str, Any] = {}
    specimen: dict[str, Any] = {}
    metadata: dict[str, Any] = {}
    for key, value in header.items():
        if key in RUN_FIELDS:
            fields[key] = value
        elif key in SPECIMEN_FIELDS:
            name = SPECIMEN_FIELDS[key]
            if name == "label":
                specimen[name] = value
            else:
                try:
                    number = float(value)
                except ValueError:
                    number = None
                specimen[name] = number if number is not None and math.isfinite(number) else None
        elif key.startswith(META_PREFIX):
            try:
                metadata[key[len(META_PREFIX):]] = json.loads(value)
            except ValueError:
                metadata[key[len(META_PREFIX):]] = value
        else:
            metadata[key] = value
    if specimen:
        fields["specimen"] = Specimen(**specimen)
    fields["metadata"] = metadata
    return fields
