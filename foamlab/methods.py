"""Test methods: what the crosshead does during a run and which results it yields.

A method is a TOML file in configs/methods/ (see paper-3cycle.toml for the format):
sampling rate, contact search (preload), park speed, a list of `[[sequence]]`
blocks whose `steps` are

    { action = "compress", strain = 0.80, speed_mm_min = 23.6 }  # move down to strain x height
    { action = "dwell", duration_s = 60.0 }                       # hold the position
    { action = "return", speed_mm_min = 23.6 }                    # move back to displacement 0

(a block may `repeat`), and the results to compute. Every `compress` starts a new
cycle (1-based). Strains are fractions of the specimen height measured before the
run; displacement 0 is the contact point found by the contact search.

Results come from a RunData: per cycle the hysteresis loss (%), the loading and
unloading energies (J) and the residual strain (displacement at which the plate
loses contact on unloading / height), plus named values such as ISO 3386-1 CV40
(`stress_at_strain`) or ASTM D3574-C CFD (`stress_at_dwell_end`), in kPa.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

from foamlab import CONFIG_DIR, FoamlabError
from foamlab.rundata import RunData

METHODS_DIR = CONFIG_DIR / "methods"
DEFAULT_METHOD = "paper-3cycle"

ACTIONS = ("compress", "return", "dwell")
PER_CYCLE_QUANTITIES = ("hysteresis_loss", "energy", "residual_strain")
VALUE_QUANTITIES = ("stress_at_strain", "stress_at_dwell_end")
MAX_STRAIN = 0.95          # beyond this the plates would meet the densified foam
MAX_SAMPLING_HZ = 1000.0


@dataclass(frozen=True)
class ContactSearch:
    preload_N: float
    search_speed_mm_min: float
    max_search_mm: float


@dataclass(frozen=True)
class Step:
    action: str                    # compress | return | dwell
    cycle: int                     # 1-based; a dwell/return belongs to the last compress
    label: str = ""                # the sequence it came from ("preflex", "cycle", ...)
    strain: float | None = None    # compress only: fraction of the specimen height
    speed_mm_min: float | None = None
    duration_s: float | None = None  # dwell only

    def target_mm(self, height_mm: float, current_mm: float) -> float:
        """Displacement (from contact) at the end of this step."""
        if self.action == "compress":
            return self.strain * height_mm
        if self.action == "return":
            return 0.0
        return current_mm

    def describe(self) -> str:
        if self.action == "compress":
            return f"compress to {self.strain:.0%} at {self.speed_mm_min:g} mm/min"
        if self.action == "return":
            return f"return to 0 at {self.speed_mm_min:g} mm/min"
        return f"dwell {self.duration_s:g} s"


@dataclass(frozen=True)
class PlannedStep:
    """A step with its displacements and its nominal duration for one specimen height."""

    index: int
    step: Step
    start_mm: float
    end_mm: float
    duration_s: float              # nominal, machine (virtual) seconds


@dataclass(frozen=True)
class ValueSpec:
    name: str
    quantity: str                  # stress_at_strain | stress_at_dwell_end
    cycle: int
    strain: float | None = None
    phase: str = "loading"
    unit: str = "kPa"
    description: str = ""
    dwell_s: float | None = None   # stress_at_dwell_end: the programmed dwell


@dataclass(frozen=True)
class ResultValue:
    name: str
    value: float | None            # None when it cannot be computed (see note)
    unit: str
    cycle: int | None = None
    description: str = ""
    note: str = ""

    def format(self) -> str:
        where = f" (cycle {self.cycle})" if self.cycle else ""
        if self.value is None:
            return f"{self.name}{where}: n/a - {self.note}"
        return f"{self.name}{where}: {self.value:.4g} {self.unit}"


@dataclass
class MethodResults:
    values: list[ResultValue] = field(default_factory=list)

    def __iter__(self):
        return iter(self.values)

    def __len__(self) -> int:
        return len(self.values)

    def get(self, name: str, cycle: int | None = None) -> ResultValue | None:
        for v in self.values:
            if v.name == name and (cycle is None or v.cycle == cycle):
                return v
        return None

    def to_dict(self) -> list[dict[str, Any]]:
        return [
            {"name": v.name, "value": v.value, "unit": v.unit, "cycle": v.cycle,
             "description": v.description, "note": v.note}
            for v in self.values
        ]

    def summary(self) -> str:
        return "\n".join(v.format() for v in self.values)


@dataclass(frozen=True)
class Method:
    name: str
    title: str
    sampling_hz: float
    contact: ContactSearch
    park_speed_mm_min: float
    steps: tuple[Step, ...]
    per_cycle: tuple[str, ...] = ()
    values: tuple[ValueSpec, ...] = ()
    reference: str = ""
    source: str = ""

    @property
    def n_cycles(self) -> int:
        return max((s.cycle for s in self.steps), default=0)

    @property
    def max_strain(self) -> float:
        return max((s.strain for s in self.steps if s.action == "compress"), default=0.0)

    @property
    def max_speed_mm_min(self) -> float:
        speeds = [s.speed_mm_min for s in self.steps if s.speed_mm_min]
        return max(speeds + [self.contact.search_speed_mm_min, self.park_speed_mm_min])

    def plan(self, height_mm: float) -> list[PlannedStep]:
        """Each step's displacements and nominal duration for a specimen of `height_mm`."""
        if not height_mm or height_mm <= 0:
            raise FoamlabError(f"method {self.name}: the specimen height must be > 0 mm")
        planned, position = [], 0.0
        for i, step in enumerate(self.steps):
            end = step.target_mm(height_mm, position)
            if step.action == "dwell":
                duration = float(step.duration_s)
            else:
                duration = abs(end - position) / step.speed_mm_min * 60.0
            planned.append(PlannedStep(i, step, position, end, duration))
            position = end
        return planned

    def duration_s(self, height_mm: float) -> float:
        """Nominal duration of the steps (machine seconds; contact search and park excluded)."""
        return sum(p.duration_s for p in self.plan(height_mm))

    def expected_samples(self, height_mm: float) -> int:
        return int(round(self.duration_s(height_mm) * self.sampling_hz))

    def describe(self) -> str:
        return f"{self.title} ({self.n_cycles} cycles, {self.sampling_hz:g} Hz)"

    def history(self, height_mm: float, sampling_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The nominal displacement history of the steps (t in s from the first step, x in mm
        from contact), sampled at `sampling_hz` (default the method's): what the crosshead
        is told to do, without the contact search and the park."""
        plan = self.plan(height_mm)
        corners_t = np.cumsum([0.0] + [p.duration_s for p in plan])
        corners_x = np.array([plan[0].start_mm] + [p.end_mm for p in plan])
        hz = sampling_hz or self.sampling_hz
        t = np.arange(0.0, corners_t[-1] + 0.5 / hz, 1.0 / hz)
        return t, np.interp(t, corners_t, corners_x)

    def compute_results(self, run: RunData) -> MethodResults:
        return compute_results(self, run)


# --------------------------------------------------------------------------- writing

def method_toml(method: Method, comment: str = "") -> str:
    """The method as a TOML file load_method reads back (steps, contact, park, per-cycle results).

    Consecutive identical cycles become one `[[sequence]]` with `repeat`; named result values
    are not written (a suggested method has none)."""
    lines = [f"# {line}".rstrip() for line in comment.splitlines()]
    lines += [f"name = {_toml_str(method.name)}", f"title = {_toml_str(method.title)}"]
    if method.reference:
        lines.append(f"reference = {_toml_str(method.reference)}")
    c = method.contact
    lines += [f"sampling_hz = {method.sampling_hz:g}", "", "[contact]", f"preload_N = {c.preload_N:g}",
              f"search_speed_mm_min = {c.search_speed_mm_min:g}", f"max_search_mm = {c.max_search_mm:g}",
              "", "[park]", f"speed_mm_min = {method.park_speed_mm_min:g}"]
    for label, repeat, steps in _sequences(method.steps):
        lines += ["", "[[sequence]]", f"label = {_toml_str(label)}"] + ([f"repeat = {repeat}"] if repeat > 1 else [])
        lines += ["steps = ["] + [f"  {_step_toml(s)}," for s in steps] + ["]"]
    lines += ["", "[results]", "per_cycle = [" + ", ".join(_toml_str(q) for q in method.per_cycle) + "]"]
    return "\n".join(lines) + "\n"


def _sequences(steps: tuple[Step, ...]) -> list[tuple[str, int, list[Step]]]:
    """Steps grouped by cycle and label (a leading dwell with the first), consecutive equal
    groups counted."""
    cycles: list[list[Step]] = []
    for s in steps:
        if s.action == "compress" or not cycles or s.label != cycles[-1][0].label:
            cycles.append([])
        cycles[-1].append(s)
    out: list[tuple[str, int, list[Step]]] = []
    for cyc in cycles:
        key = [(s.action, s.strain, s.speed_mm_min, s.duration_s) for s in cyc]
        if out and out[-1][0] == cyc[0].label and \
                [(s.action, s.strain, s.speed_mm_min, s.duration_s) for s in out[-1][2]] == key:
            out[-1] = (out[-1][0], out[-1][1] + 1, out[-1][2])
        else:
            out.append((cyc[0].label or "cycle", 1, cyc))
    return out


def _step_toml(s: Step) -> str:
    # every digit the step holds: the file loads back the very steps (4 digits read 243.091 as 243.1)
    if s.action == "compress":
        return f'{{ action = "compress", strain = {s.strain:.10g}, speed_mm_min = {s.speed_mm_min:.10g} }}'
    if s.action == "return":
        return f'{{ action = "return", speed_mm_min = {s.speed_mm_min:.10g} }}'
    return f'{{ action = "dwell", duration_s = {s.duration_s:.10g} }}'


def _toml_str(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


# --------------------------------------------------------------------------- loading

def available_methods(methods_dir: str | Path | None = None) -> list[str]:
    folder = Path(methods_dir) if methods_dir else METHODS_DIR
    return sorted(p.stem for p in folder.glob("*.toml") if not p.name.startswith("_"))


def _resolve(name_or_path: str | Path, methods_dir: str | Path | None) -> Path:
    candidate = Path(name_or_path)
    if candidate.suffix == ".toml" or len(candidate.parts) > 1:
        if candidate.is_file():
            return candidate
        raise FoamlabError(f"method file not found: {candidate}")
    folder = Path(methods_dir) if methods_dir else METHODS_DIR
    path = folder / f"{name_or_path}.toml"
    if path.is_file():
        return path
    names = ", ".join(available_methods(methods_dir)) or "none"
    raise FoamlabError(f"unknown method {str(name_or_path)!r} (available: {names})")


def load_method(name_or_path: str | Path = DEFAULT_METHOD, methods_dir: str | Path | None = None) -> Method:
    """Load and validate a method by name (configs/methods/NAME.toml) or path."""
    path = _resolve(name_or_path, methods_dir)
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise FoamlabError(f"cannot read method {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise FoamlabError(f"method {path.name}: not valid TOML: {exc}") from None
    return parse_method(data, source=str(path))


#: Header key of a foamlab run file: the method file the run was made with (acquisition.engine).
METHOD_FILE_KEY = "method_file"
#: Header key of a foamlab run file: the method itself, as method_record() gives it.
METHOD_KEY = "method_definition"


def method_record(method: Method) -> dict[str, Any]:
    """The resolved method as plain data (JSON in the run file's header): read back by
    method_from_record, it is the method the run was made with, wherever its file went."""
    return dataclasses.asdict(method)


def method_from_record(record: Any) -> Method:
    """The Method of a method_record (FoamlabError, one line, when it is not one)."""
    try:
        data = dict(record)
        data["contact"] = ContactSearch(**data["contact"])
        data["steps"] = tuple(Step(**s) for s in data["steps"])
        data["values"] = tuple(ValueSpec(**v) for v in data.get("values", ()))
        data["per_cycle"] = tuple(data.get("per_cycle", ()))
        return Method(**data)
    except (TypeError, KeyError, ValueError) as exc:
        raise FoamlabError(f"the method recorded with the run is not readable ({exc})") from None


def method_of_run(run: RunData) -> Method:
    """The method a run was made with: the one recorded in the run file (a run foamlab made
    records it), else the file recorded with it while that file still holds a method of the
    run's name, else the built-in method of that name."""
    if not run.method:
        raise FoamlabError("no test method recorded with the run")
    if run.metadata.get(METHOD_KEY):
        return method_from_record(run.metadata[METHOD_KEY])
    recorded = str(run.metadata.get(METHOD_FILE_KEY) or "")
    if recorded and Path(recorded).is_file():
        try:
            method = load_method(recorded)
            if method.name == run.method:
                return method
        except FoamlabError:
            pass            # an unreadable file: the built-in method of the name, else the error below
    try:
        return load_method(run.method)
    except FoamlabError as exc:
        if not recorded:
            raise
        raise FoamlabError(f"{exc}; the method file recorded with the run ({recorded}) is gone or now holds "
                           "another method: give the method file") from None


class _Reader:
    """Typed access to one TOML table; every error names the file and the place."""

    def __init__(self, table: Any, where: str, file: str):
        if not isinstance(table, dict):
            raise FoamlabError(f"method {file}: {where} must be a table")
        self.table, self.where, self.file = table, where, file
        self.used: set[str] = set()

    def fail(self, msg: str):
        raise FoamlabError(f"method {self.file}: {self.where}: {msg}")

    def _get(self, key: str, default: Any, required: bool) -> Any:
        self.used.add(key)
        if key not in self.table:
            if required:
                self.fail(f"missing `{key}`")
            return default
        return self.table[key]

    def number(self, key: str, default: float | None = None, *, required: bool = True,
               low: float | None = None, high: float | None = None, low_open: bool = False) -> float:
        value = self._get(key, default, required and default is None)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.fail(f"`{key}` must be a number, got {value!r}")
        if low is not None and (value <= low if low_open else value < low):
            self.fail(f"`{key}` must be {'>' if low_open else '>='} {low:g}, got {value!r}")
        if high is not None and value > high:
            self.fail(f"`{key}` must be <= {high:g}, got {value!r}")
        return float(value)

    def integer(self, key: str, default: int | None = None, *, low: int = 1) -> int:
        value = self._get(key, default, default is None)
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(f"`{key}` must be an integer, got {value!r}")
        if value < low:
            self.fail(f"`{key}` must be >= {low}, got {value}")
        return value

    def text(self, key: str, default: str | None = None, choices=None) -> str:
        value = self._get(key, default, default is None)
        if not isinstance(value, str):
            self.fail(f"`{key}` must be text, got {value!r}")
        if choices and value not in choices:
            self.fail(f"`{key}` must be one of {', '.join(choices)}, got {value!r}")
        return value

    def array(self, key: str, default: list | None = None) -> list:
        value = self._get(key, default, default is None)
        if not isinstance(value, list):
            self.fail(f"`{key}` must be an array, got {value!r}")
        return value

    def done(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            self.fail(f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join('`%s`' % k for k in unknown)}")


def parse_method(data: dict, source: str = "<method>") -> Method:
    """Validate a method's TOML content (a dict) and build the Method."""
    file = Path(source).name
    top = _Reader(data, "top level", file)
    name = top.text("name", Path(source).stem)
    title = top.text("title", name)
    reference = top.text("reference", "")
    sampling_hz = top.number("sampling_hz", low=0, low_open=True, high=MAX_SAMPLING_HZ)

    contact_r = _Reader(top._get("contact", None, True), "[contact]", file)
    contact = ContactSearch(
        preload_N=contact_r.number("preload_N", low=0, low_open=True),
        search_speed_mm_min=contact_r.number("search_speed_mm_min", low=0, low_open=True),
        max_search_mm=contact_r.number("max_search_mm", low=0, low_open=True),
    )
    contact_r.done()
    park_r = _Reader(top._get("park", {}, False), "[park]", file)
    park_speed = park_r.number("speed_mm_min", 100.0, low=0, low_open=True)
    park_r.done()

    steps = _parse_sequences(top.array("sequence"), file)

    results_r = _Reader(top._get("results", {}, False), "[results]", file)
    per_cycle = tuple(results_r.array("per_cycle", list(PER_CYCLE_QUANTITIES)))
    for q in per_cycle:
        if q not in PER_CYCLE_QUANTITIES:
            results_r.fail(f"`per_cycle` entry {q!r} is not one of {', '.join(PER_CYCLE_QUANTITIES)}")
    values = tuple(_parse_value(v, i, file, steps) for i, v in enumerate(results_r.array("values", []), 1))
    results_r.done()
    top.done()
    return Method(name=name, title=title, sampling_hz=sampling_hz, contact=contact,
                  park_speed_mm_min=park_speed, steps=steps, per_cycle=per_cycle,
                  values=values, reference=reference, source=source)


def _parse_sequences(sequences: list, file: str) -> tuple[Step, ...]:
    if not sequences:
        raise FoamlabError(f"method {file}: needs at least one [[sequence]] with steps")
    steps: list[Step] = []
    cycle, position = 0, "zero"           # where the plate is: zero | compressed
    for si, seq in enumerate(sequences, 1):
        r = _Reader(seq, f"[[sequence]] {si}", file)
        label = r.text("label", "")
        repeat = r.integer("repeat", 1)
        raw_steps = r.array("steps")
        r.done()
        if not raw_steps:
            r.fail("`steps` is empty")
        parsed = []
        for ti, raw in enumerate(raw_steps, 1):
            sr = _Reader(raw, f"[[sequence]] {si} step {ti}", file)
            action = sr.text("action", choices=ACTIONS)
            if action == "compress":
                parsed.append(("compress", sr.number("strain", low=0, low_open=True, high=MAX_STRAIN),
                               sr.number("speed_mm_min", low=0, low_open=True), None, sr))
            elif action == "return":
                parsed.append(("return", None, sr.number("speed_mm_min", low=0, low_open=True), None, sr))
            else:
                parsed.append(("dwell", None, None, sr.number("duration_s", low=0, low_open=True), sr))
            sr.done()
        for _ in range(repeat):
            for action, strain, speed, duration, sr in parsed:
                if action == "compress":
                    cycle += 1
                    position = "compressed"
                elif action == "return":
                    if position != "compressed":
                        sr.fail("`return` without a `compress` before it")
                    position = "zero"
                steps.append(Step(action, max(cycle, 1), label, strain, speed, duration))
    if cycle == 0:
        raise FoamlabError(f"method {file}: no `compress` step")
    if position != "zero":
        raise FoamlabError(f"method {file}: the last cycle must end with a `return` step")
    return tuple(steps)


def _parse_value(raw: Any, index: int, file: str, steps: tuple[Step, ...]) -> ValueSpec:
    r = _Reader(raw, f"[[results.values]] {index}", file)
    name = r.text("name")
    quantity = r.text("quantity", choices=VALUE_QUANTITIES)
    cycle = r.integer("cycle")
    unit = r.text("unit", "kPa", choices=("kPa",))
    description = r.text("description", "")
    cycle_steps = [s for s in steps if s.cycle == cycle]
    if not cycle_steps:
        r.fail(f"cycle {cycle} does not exist (the method has {max(s.cycle for s in steps)} cycles)")
    peak = max(s.strain for s in cycle_steps if s.action == "compress")
    strain = dwell = None
    if quantity == "stress_at_strain":
        strain = r.number("strain", low=0, low_open=True, high=MAX_STRAIN)
        if strain > peak:
            r.fail(f"strain {strain:g} is beyond cycle {cycle}'s peak strain {peak:g}")
    else:
        dwell = _dwell_at_peak(cycle_steps)
        if dwell is None:
            r.fail(f"`stress_at_dwell_end` needs a dwell right after the compress of cycle {cycle}")
    r.done()
    return ValueSpec(name, quantity, cycle, strain, "loading", unit, description, dwell)


def _dwell_at_peak(cycle_steps: list[Step]) -> float | None:
    for a, b in zip(cycle_steps, cycle_steps[1:]):
        if a.action == "compress" and b.action == "dwell":
            return b.duration_s
    return None


# --------------------------------------------------------------------------- results

@dataclass(frozen=True)
class CycleSpan:
    """Sample index ranges of one cycle, aligned on the method's plan ([start, stop)).

    loading ends on the first sample of the peak plateau; unloading starts there too
    (a dwell at the peak adds nothing to the work, x being constant), so the two
    share that sample; hold is the plateau after it (the dwell, for CFD).
    """

    cycle: int
    loading: tuple[int, int]
    hold: tuple[int, int]          # dwell at peak (empty when there is none)
    unloading: tuple[int, int]
    peak_mm: float
    complete: bool                 # the unloading reached displacement 0


#: A sample within this of the peak displacement is on the peak plateau (drives report um).
PLATEAU_MM = 0.005


def _peak_tolerance_mm(peak_mm: float) -> float:
    """A programmed peak is reached within this (the contact zero and noise)."""
    return max(0.02, 0.002 * peak_mm)


def cycle_spans(method: Method, run: RunData) -> list[CycleSpan]:
    """Split a run made with `method` into its cycles.

    A run foamlab recorded has its cycles in its labels (RunData.segments: each sample's
    step and cycle as the engine ran them). A run without them (an export of another
    machine's software run with this method) follows a known plan all the same, so a cycle
    is found where the displacement reaches the programmed peak (within max(0.02 mm, 0.2 %))
    and comes back to zero: the plan places a dwell's ends to the sample, which generic
    turning points (foamlab.segmentation) do not. Either way cycles the run did not reach
    are left out and an aborted cycle is returned with `complete=False`.
    """
    height = run.specimen.height_mm
    if len(run) == 0 or not height:
        return []
    if run.has_labels:
        return _labelled_spans(method, run, height)
    x = run.displacement_mm
    n = len(x)
    spans: list[CycleSpan] = []
    i = 0
    for cycle in range(1, method.n_cycles + 1):
        steps = [s for s in method.steps if s.cycle == cycle]
        peak = max(s.strain for s in steps if s.action == "compress") * height
        tol = _peak_tolerance_mm(peak)
        reached = np.flatnonzero(x[i:] >= peak - tol)
        if len(reached) == 0:
            break
        first = i + int(reached[0])
        leaves = np.flatnonzero(x[first:] < peak - tol)
        region_end = first + int(leaves[0]) if len(leaves) else n
        region = x[first:region_end]
        top = first + int(np.flatnonzero(region >= region.max() - PLATEAU_MM)[0])
        below = np.flatnonzero(x[top + 1:] < x[top] - PLATEAU_MM)
        hold_end = top + 1 + int(below[0]) if len(below) else n
        before = x[i:top + 1]
        start = i + int(np.flatnonzero(before <= before.min())[-1])
        back = np.flatnonzero(x[top:] <= tol)
        end = top + int(back[0]) + 1 if len(back) else n
        spans.append(CycleSpan(cycle, (start, top + 1), (top + 1, hold_end), (top, end),
                               float(x[top]), bool(len(back))))
        i = end
        if i >= n:
            break
    return spans


def _labelled_spans(method: Method, run: RunData, height: float) -> list[CycleSpan]:
    """cycle_spans of a run with the engine's labels: its cycles and holds as segments() has them."""
    seg = run.segments()
    x, n = run.displacement_mm, len(run)
    spans: list[CycleSpan] = []
    for cycle in seg.cycles:
        steps = [s for s in method.steps if s.cycle == cycle.number and s.action == "compress"]
        if not steps:
            continue
        peak = max(s.strain for s in steps) * height
        tol = _peak_tolerance_mm(peak)
        top = cycle.loading.stop - 1            # a compress step ends at its target
        if x[top] < peak - tol:
            break                               # the run stopped before the peak
        hold = next(((a, b) for a, b in seg.holds if a == top + 1), (top + 1, top + 1))
        end = cycle.unloading.stop if cycle.unloading is not None else n
        complete = cycle.unloading is not None and bool(x[end - 1] <= tol)
        spans.append(CycleSpan(cycle.number, (cycle.loading.start, top + 1), hold, (top, end),
                               float(x[top]), complete))
    return spans


def _energy_J(x: np.ndarray, f: np.ndarray) -> float:
    """Work of the force over the path, J (N.mm / 1000); positive for a loading path."""
    if len(x) < 2:
        return 0.0
    return float(np.trapezoid(f, x) / 1000.0)


def compute_results(method: Method, run: RunData) -> MethodResults:
    """The method's results from a run (values that cannot be computed say why)."""
    out = MethodResults()
    height = run.specimen.height_mm
    if not height:
        note = "specimen height unknown"
        out.values += [ResultValue(v.name, None, v.unit, v.cycle, v.description, note) for v in method.values]
        return out
    x, f = run.displacement_mm, run.force_N
    spans = cycle_spans(method, run)
    for span in spans:
        lo, hi = span.loading
        ulo, uhi = span.unloading
        loading_J = _energy_J(x[lo:hi], f[lo:hi])
        unloading_J = -_energy_J(x[ulo:uhi], f[ulo:uhi])
        note = "" if span.complete else "cycle incomplete"
        if "energy" in method.per_cycle:
            out.values.append(ResultValue("loading_energy", loading_J, "J", span.cycle,
                                          "work done on the specimen while loading"))
            out.values.append(ResultValue("unloading_energy", unloading_J if span.complete else None, "J",
                                          span.cycle, "work returned by the specimen while unloading", note))
        if "hysteresis_loss" in method.per_cycle:
            value = None
            if span.complete and loading_J > 0:
                value = 100.0 * (loading_J - unloading_J) / loading_J
            out.values.append(ResultValue("hysteresis_loss", value, "%", span.cycle,
                                          "(loading - unloading energy) / loading energy",
                                          note or ("" if value is not None else "no loading energy")))
        if "residual_strain" in method.per_cycle:
            value = _residual_strain(x[ulo:uhi], f[ulo:uhi], method.contact.preload_N, height) \
                if span.complete else None
            out.values.append(ResultValue("residual_strain", value, "", span.cycle,
                                          "displacement where the plate loses contact on unloading / height", note))
    for spec in method.values:
        out.values.append(_value(spec, spans, run))
    return out


def _residual_strain(x: np.ndarray, f: np.ndarray, contact_N: float, height_mm: float) -> float:
    """Displacement where the unloading force first falls to the contact threshold, / height.

    The force is median-filtered over 5 samples first so that load-cell noise near
    the threshold neither ends contact early nor prolongs it. 0 when the foam keeps
    touching the plate down to displacement 0.
    """
    if len(x) < 2:
        return 0.0
    smooth = median_filter(f, size=min(5, len(f)), mode="nearest")
    below = np.flatnonzero(smooth <= contact_N)
    if len(below) == 0:
        return 0.0
    k = int(below[0])
    if k == 0:
        return float(max(x[0], 0.0) / height_mm)
    # linear interpolation between the last sample in contact and the first one out
    f0, f1, x0, x1 = smooth[k - 1], smooth[k], x[k - 1], x[k]
    xc = x0 + (contact_N - f0) * (x1 - x0) / (f1 - f0) if f1 != f0 else x1
    return float(max(xc, 0.0) / height_mm)


def _value(spec: ValueSpec, spans: list[CycleSpan], run: RunData) -> ResultValue:
    def missing(note: str) -> ResultValue:
        return ResultValue(spec.name, None, spec.unit, spec.cycle, spec.description, note)

    area = run.specimen.area_mm2
    if not area:
        return missing("specimen width and depth unknown")
    span = next((s for s in spans if s.cycle == spec.cycle), None)
    if span is None:
        return missing(f"the run did not reach cycle {spec.cycle}")
    x, f = run.displacement_mm, run.force_N
    if spec.quantity == "stress_at_strain":
        lo, hi = span.loading
        xs, fs = x[lo:hi], f[lo:hi]
        target = spec.strain * run.specimen.height_mm
        if len(xs) < 2 or target > xs.max():
            return missing(f"cycle {spec.cycle} loading did not reach {spec.strain:.0%}")
        # loading is monotone up to noise; np.interp needs increasing x
        order = np.argsort(xs, kind="stable")
        force = float(np.interp(target, xs[order], fs[order]))
    else:
        lo, hi = span.hold
        held_s = float(run.time_s[hi - 1] - run.time_s[lo - 1]) if hi > lo else 0.0
        # the standard reads the force after the full dwell (ASTM D3574-C: 60 +- 3 s)
        if held_s < 0.95 * spec.dwell_s:
            return missing(f"cycle {spec.cycle} held its peak {held_s:.1f} s of the {spec.dwell_s:g} s dwell")
        force = float(f[hi - 1])
    return ResultValue(spec.name, force / area * 1000.0, spec.unit, spec.cycle, spec.description)
