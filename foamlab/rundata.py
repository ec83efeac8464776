"""One type for a compression run: the samples and what describes them.

Conventions used everywhere in foamlab:
- displacement_mm is compression, positive when the plate moves into the specimen,
  zero where the plate first touches the specimen (or the machine's zero);
- force_N is compressive force, positive when the specimen pushes back;
- time_s is monotonic, starting at (about) zero;
- step and cycle, when the run was acquired by foamlab, are each sample's method step (0-based
  index in the plan) and cycle (1-based), as the engine labelled it; None for a vendor file.
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
    step: np.ndarray | None = None    # per sample, the engine's labels (see the module docstring)
    cycle: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.time_s = np.asarray(self.time_s, dtype=float)
        self.displacement_mm = np.asarray(self.displacement_mm, dtype=float)
        self.force_N = np.asarray(self.force_N, dtype=float)
        n = len(self.time_s)
        if len(self.displacement_mm) != n or len(self.force_N) != n:
            raise FoamlabError("run data: time, displacement and force have different lengths")
        if (self.step is None) != (self.cycle is None):
            raise FoamlabError("run data: step and cycle labels come together")
        if self.step is not None:
            self.step = np.asarray(self.step, dtype=int)
            self.cycle = np.asarray(self.cycle, dtype=int)
            if len(self.step) != n or len(self.cycle) != n:
                raise FoamlabError("run data: the step and cycle labels do not match the samples")

    @property
    def has_labels(self) -> bool:
        """The samples carry the engine's step and cycle (a run foamlab acquired)."""
        return self.step is not None

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def sampling_hz(self) -> float:
        if len(self) < 2:
            return float("nan")
        return float(1.0 / np.median(np.diff(self.time_s)))

    def slice(self, start: int, stop: int) -> "RunData":
        """A copy restricted to samples [start, stop)."""
        return self.take(slice(start, stop))

    def take(self, which: slice | np.ndarray) -> "RunData":
        """A copy with the samples `which` selects (a slice, a boolean mask or indices)."""
        def part(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else np.array(a[which])

        return dataclasses.replace(
            self, time_s=part(self.time_s), displacement_mm=part(self.displacement_mm),
            force_N=part(self.force_N), step=part(self.step), cycle=part(self.cycle),
            metadata=dict(self.metadata))

    def segments(self) -> Segmentation:
        """Cycles and half-cycles of this run: the engine's labels where the run has them, found
        in the displacement otherwise (see foamlab.segmentation; the one place for both)."""
        return segment(self)
