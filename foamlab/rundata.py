"""One type for a compression run: the samples and what describes them.

Conventions used everywhere in foamlab:
- displacement_mm is compression, positive when the plate moves into the specimen,
  zero where the plate first touches the specimen (or the machine's zero);
- force_N is compressive force, positive when the specimen pushes back;
- time_s is monotonic, starting at (about) zero.
Importers convert whatever the file uses (negative compression, kN, ms) to this.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from foamlab import FoamlabError
from foamlab.segmentation import Segmentation, segment


@dataclass
class Specimen:
    label: str = ""
    height_mm: float | None = None
    width_mm: float | None = None
    depth_mm: float | None = None

    @property
    def area_mm2(self) -> float | None:
        if self.width_mm and self.depth_mm:
            return self.width_mm * self.depth_mm
        return None


@dataclass
class RunData:
    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_N: np.ndarray
    specimen: Specimen = field(default_factory=Specimen)
    method: str = ""
    machine: str = ""
    started_at: str = ""          # ISO 8601, local time with offset when known
    finished_at: str = ""
    status: str = "finished"      # finished | aborted | running | imported
    abort_reason: str = ""
    source: str = ""              # file the run was read from, if any
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.time_s = np.asarray(self.time_s, dtype=float)
        self.displacement_mm = np.asarray(self.displacement_mm, dtype=float)
        self.force_N = np.asarray(self.force_N, dtype=float)
        n = len(self.time_s)
        if len(self.displacement_mm) != n or len(self.force_N) != n:
            raise FoamlabError("run data: time, displacement and force have different lengths")

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def sampling_hz(self) -> float:
        if len(self) < 2:
            return float("nan")
        return float(1.0 / np.median(np.diff(self.time_s)))

    def slice(self, start: int, stop: int) -> "RunData":
        """A copy restricted to samples [start, stop)."""
        return dataclasses.replace(
            self,
            time_s=self.time_s[start:stop].copy(),
            displacement_mm=self.displacement_mm[start:stop].copy(),
            force_N=self.force_N[start:stop].copy(),
            metadata=dict(self.metadata),
        )

    def segments(self) -> Segmentation:
        """Cycles and half-cycles of this run (see foamlab.segmentation)."""
        return segment(self)
