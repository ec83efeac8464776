"""Shared pieces of every importer: numeric tables with line-numbered errors,
channel names and units, and the conversion to foamlab's conventions."""

from __future__ import annotations

import datetime as _dt
import io
import re
import unicodedata
from dataclasses import dataclass

import numpy as np
import pandas as pd

from foamlab import FoamlabError

# --------------------------------------------------------------------------- numbers

_FIELDS_ERROR = re.compile(r"Expected (\d+) fields in line (\d+), saw (\d+)")


class Rows:
    """The data lines of a file: their text and their 1-based line numbers."""

    def __init__(self, texts: list[str], line_nos: list[int] | range) -> None:
        self.texts = texts
        self.line_nos = line_nos

    @classmethod
    def select(cls, lines: list[str], start: int, comments: bool) -> tuple["Rows", list[tuple[int, str]]]:
        """Non-blank lines from ``lines[start:]``; ``#`` lines apart when ``comments``.

        Returns the rows and the (line number, text) of the comment lines.
        """
        block = lines[start:]
        skip = [i for i, ln in enumerate(block)
                if not ln or ln.isspace() or (comments and ln[0] == "#")]
        if not skip:
            return cls(block, range(start + 1, start + 1 + len(block))), []
        skipped = set(skip)
        keep = [i for i in range(len(block)) if i not in skipped]
        found = [(start + 1 + i, block[i]) for i in skip if block[i].strip()]
        return cls([block[i] for i in keep], [start + 1 + i for i in keep]), found

    def __len__(self) -> int:
        return len(self.texts)

    def drop_last(self) -> int:
        """Forget the last row; return its line number."""
        line_no = self.line_nos[-1]
        self.texts = self.texts[:-1]
        self.line_nos = self.line_nos[:-1]
        return line_no


def parse_rows(rows: Rows, *, source: str, sep: str, decimal: str, ncols: int,
               wanted: dict[str, int], required: tuple[str, ...], ends_with_newline: bool,
               ) -> dict[str, np.ndarray]:
    """Numbers of the ``wanted`` columns (name -> column index) of data rows.

    ``required`` columns must be finite in every row; others may be empty (NaN).
    Errors name the file line, the column and the offending text.
    """
    if not len(rows):
        raise FoamlabError(f"{source}: no data rows after the header")
    width = _check_field_counts(rows, source, sep, ncols)
    joined = "\n".join(rows.texts)
    if '"' in joined:
        _check_quotes(rows, source)
    indices = sorted(set(wanted.values()))
    read = dict(sep=sep, decimal=decimal, header=None, names=list(range(width)),
                skip_blank_lines=False, quotechar='"', engine="c")
    try:
        table = pd.read_csv(io.StringIO(joined), usecols=indices, dtype=float, **read)
    except pd.errors.ParserError as exc:
        _raise_field_count(exc, rows, source, ncols)
        raise FoamlabError(f"{source}: unreadable table ({_first_line(exc)})") from None
    except (ValueError, OverflowError):
        table = _locate_bad_number(joined, rows, source, read, indices, wanted)
    out: dict[str, np.ndarray] = {}
    for name, index in wanted.items():
        values = table[index].to_numpy(dtype=float)
        if name in required:
            bad = ~np.isfinite(values)
            if bad.any():
                _raise_missing(int(np.argmax(bad)), rows, source, sep, ncols, name,
                               ends_with_newline)
        out[name] = values
    return out


def _check_quotes(rows: Rows, source: str) -> None:
    """A quote that never closes would swallow the following lines into one field."""
    for text, line_no in zip(rows.texts, rows.line_nos):
        if text.count('"') % 2:
            raise FoamlabError(f"{source}: line {line_no}: a quote (\") opens a field that "
                               f"does not close on this line")


def _check_field_counts(rows: Rows, source: str, sep: str, ncols: int) -> int:
    """Refuse rows with more fields than the header (trailing empty fields allowed);
    return how many columns pandas must expect.

    pandas silently drops surplus fields of columns it is not asked for, so this
    is checked here; rows with quotes are not judged (a quoted field may hold the
    separator), only made room for.
    """
    counts = [t.count(sep) for t in rows.texts]
    width = max(ncols, max(counts) + 1)
    if width > ncols:
        for i, count in enumerate(counts):
            if count >= ncols:
                text = rows.texts[i]
                fields = text.rstrip().rstrip(sep + " \t").count(sep) + 1
                if fields > ncols and '"' not in text:
                    raise FoamlabError(f"{source}: line {rows.line_nos[i]}: {fields} fields, "
                                       f"expected {ncols}")
    return width


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


def _raise_field_count(exc: pd.errors.ParserError, rows: Rows, source: str,
                       ncols: int) -> None:
    m = _FIELDS_ERROR.search(str(exc))
    if m:
        index = int(m.group(2)) - 1
        line_no = rows.line_nos[index] if 0 <= index < len(rows) else index + 1
        raise FoamlabError(f"{source}: line {line_no}: {m.group(3)} fields, expected {ncols}") from None


def _locate_bad_number(joined: str, rows: Rows, source: str, read: dict,
                       indices: list[int], wanted: dict[str, int]) -> pd.DataFrame:
    try:
        raw = pd.read_csv(io.StringIO(joined), usecols=indices, dtype=str,
                          keep_default_na=False, **{k: v for k, v in read.items() if k != "decimal"})
    except pd.errors.ParserError as exc:
        _raise_field_count(exc, rows, source, len(read["names"]))
        raise FoamlabError(f"{source}: unreadable table ({_first_line(exc)})") from None
    names = {index: name for name, index in wanted.items()}
    table = {}
    for index in indices:
        text = raw[index].fillna("").str.strip()
        if read["decimal"] != ".":
            text = text.str.replace(read["decimal"], ".", regex=False)
        numbers = pd.to_numeric(text, errors="coerce")
        bad = numbers.isna() & (text != "") & ~text.str.lower().isin(["nan", "-nan", "na", "n/a"])
        if bad.any():
            i = int(np.argmax(bad.to_numpy()))
            shown = raw[index].iloc[i]
            shown = shown if len(shown) <= 30 else shown[:27] + "..."
            raise FoamlabError(f"{source}: line {rows.line_nos[i]}: {shown!r} in column "
                               f"'{names.get(index, index)}' is not a number")
        table[index] = numbers.astype(float)
    return pd.DataFrame(table)


def _raise_missing(i: int, rows: Rows, source: str, sep: str, ncols: int, name: str,
                   ends_with_newline: bool) -> None:
    text, line_no = rows.texts[i], rows.line_nos[i]
    fields = len(text.split(sep)) if text.strip() else 0
    if fields < ncols:
        if i == len(rows) - 1 and not ends_with_newline:
            raise FoamlabError(f"{source}: line {line_no}: truncated last line "
                               f"({fields} of {ncols} fields)")
        raise FoamlabError(f"{source}: line {line_no}: {fields} fields, expected {ncols}")
    raise FoamlabError(f"{source}: line {line_no}: no valid number in column '{name}' "
                       f"(empty, NaN or infinite)")


def check_samples(source: str, time_s: np.ndarray, rows: Rows) -> None:
    """Time must increase strictly: samples are in acquisition order."""
    if len(time_s) < 2:
        raise FoamlabError(f"{source}: only {len(time_s)} sample; a run needs at least 2")
    steps = np.diff(time_s)
    bad = np.flatnonzero(steps <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        what = "repeats" if steps[i - 1] == 0 else "goes backwards"
        raise FoamlabError(f"{source}: line {rows.line_nos[i]}: time {what} "
                           f"({time_s[i]:g} s after {time_s[i - 1]:g} s)")


def order_times(source: str, time_s: np.ndarray, line_nos, notes: list[str]) -> np.ndarray:
    """Time as acquired, made strictly increasing where a vendor repeated a timestamp.

    A repeated time (two rows at t = 0 at the start of a Bluehill file, or times
    rounded coarser than the sampling) keeps its samples in file order, spaced
    evenly around it (see _spread_repeats), and a note says so. Time that goes
    backwards is an error naming the line.
    """
    if len(time_s) < 2:
        raise FoamlabError(f"{source}: only {len(time_s)} sample; a run needs at least 2")
    steps = np.diff(time_s)
    back = np.flatnonzero(steps < 0)
    if len(back):
        i = int(back[0]) + 1
        raise FoamlabError(f"{source}: line {line_nos[i]}: time goes backwards "
                           f"({time_s[i]:g} s after {time_s[i - 1]:g} s)")
    repeats = np.flatnonzero(steps == 0)
    if not len(repeats):
        return time_s
    forward = steps[steps > 0]
    if not len(forward):
        raise FoamlabError(f"{source}: line {line_nos[1]}: time never advances "
                           f"(all {len(time_s)} samples at {time_s[0]:g} s)")
    new = _spread_repeats(time_s)
    flat = np.flatnonzero(np.diff(new) <= 0)  # float resolution exhausted (absurd times)
    if len(flat):
        raise FoamlabError(f"{source}: line {line_nos[int(flat[0]) + 1]}: time repeats and "
                           f"cannot be told apart at {time_s[int(flat[0])]:g} s")
    first = int(repeats[0])
    notes.append(f"time repeats at {len(repeats)} of {len(time_s)} samples (first at line "
                 f"{line_nos[first + 1]}, {time_s[first] - time_s[0]:g} s from the start): samples "
                 f"kept in file order, each repeated time given to the middle of its run and "
                 f"the samples around it spaced evenly")
    return new


def _spread_repeats(t: np.ndarray) -> np.ndarray:
    """Each run of equal times is placed around its own time: the time belongs to the
    middle of the run (a rounded clock), and the samples between run middles are
    spaced evenly. Samples away from repeats keep their times."""
    new_run = np.r_[True, np.diff(t) != 0]
    starts = np.flatnonzero(new_run)
    sizes = np.diff(np.r_[starts, len(t)])
    middles = starts + (sizes - 1) / 2.0
    values = t[starts]
    index = np.arange(len(t), dtype=float)
    out = np.interp(index, middles, values)
    # np.interp holds the end values flat: continue the first and last slopes instead
    for ends, (a, b) in ((index < middles[0], (0, 1)), (index > middles[-1], (-2, -1))):
        slope = (values[b] - values[a]) / (middles[b] - middles[a])
        out[ends] = values[b] + (index[ends] - middles[b]) * slope
    return out


# --------------------------------------------------------------------------- channels

def normalize_name(name: str) -> str:
    """Lower-case, NFKC (full-width -> ASCII), quotes and spaces trimmed/collapsed."""
    text = unicodedata.normalize("NFKC", str(name)).strip().strip('"').strip().lower()
    return re.sub(r"\s+", " ", text)


# Names of the channels, best first, in the languages Bluehill and testXpert
# exports are seen in. Matching is exact on the normalised name; a column whose
# name is unknown is still taken when it is the only one with the right unit.
TIME_NAMES = [
    "time", "test time", "total time", "time_s", "running time", "time measurement",
    "elapsed time", "axial time",
    "prüfzeit", "zeit", "testzeit", "versuchszeit", "gesamtzeit", "laufzeit",
    "时间", "试验时间", "测试时间", "时间 (s)",
    "temps", "durée", "tiempo", "tempo", "czas", "czas testu", "čas",
]
DISPLACEMENT_NAMES = [
    "compressive extension", "extension", "standard travel", "displacement",
    "compressive displacement", "deformation", "crosshead", "crosshead position",
    "position", "crosshead travel", "travel", "grip to grip separation",
    "digital position", "actuator position", "axial displacement", "axial position",
    "standardweg", "weg", "verformung", "druckweg", "traversenweg", "traverse",
    "traversenposition", "verlängerung", "stauchung", "position des aktuators",
    "digitale position", "przemieszczenie", "odkształcenie", "wydłużenie",
    "压缩拉伸", "拉伸", "压缩位移", "位移", "变形", "横梁位移", "压缩变形",
    "déplacement", "allongement", "extensión", "desplazamiento", "spostamento",
]
FORCE_NAMES = [
    "compressive load", "load", "standard force", "force", "compressive force",
    "primary load measurement", "load measurement", "axial force", "axial load",
    "test force", "standardkraft", "kraft", "prüfkraft", "druckkraft", "last", "siła",
    "obciążenie",
    "压缩负荷", "负荷", "载荷", "力", "试验力", "压力",
    "charge", "fuerza", "carga", "forza", "síla",
]

TIME_UNITS = {"s": 1.0, "sec": 1.0, "secs": 1.0, "second": 1.0, "seconds": 1.0, "秒": 1.0,
              "ms": 1e-3, "msec": 1e-3, "毫秒": 1e-3, "min": 60.0, "h": 3600.0, "hr": 3600.0,
              "sek": 1.0, "sekunden": 1.0,
              # Excel day numbers (MTS 793 writes a "d" column): days since 1899-12-30
              "d": 86400.0, "day": 86400.0, "days": 86400.0, "tag": 86400.0, "tage": 86400.0}
DAY_UNITS = {"d", "day", "days", "tag", "tage"}
LENGTH_UNITS = {"mm": 1.0, "毫米": 1.0, "m": 1000.0, "米": 1000.0, "cm": 10.0, "厘米": 10.0,
                "µm": 1e-3, "μm": 1e-3, "um": 1e-3, "微米": 1e-3,
                "in": 25.4, "inch": 25.4, "inches": 25.4, "英寸": 25.4}
FORCE_UNITS = {"n": 1.0, "牛": 1.0, "牛顿": 1.0, "kn": 1000.0, "千牛": 1000.0, "mn": 1e-3,
               "lbf": 4.4482216152605, "lb": 4.4482216152605, "lbs": 4.4482216152605,
               "kgf": 9.80665, "kp": 9.80665}
_KINDS = {"time": (TIME_NAMES, TIME_UNITS, "s"),
          "displacement": (DISPLACEMENT_NAMES, LENGTH_UNITS, "mm"),
          "force": (FORCE_NAMES, FORCE_UNITS, "N")}


def normalize_unit(unit: str) -> str:
    text = normalize_name(unit)
    return text.strip("()[]{}<> ").strip()


@dataclass
class Channel:
    index: int
    name: str
    unit: str
    factor: float  # multiply the file's numbers by this to get s / mm / N


def pick_channels(names: list[str], units: list[str] | None, source: str) -> dict[str, Channel]:
    """time/displacement/force columns from the names row and the units row."""
    norm_names = [normalize_name(n) for n in names]
    norm_units = [normalize_unit(u) for u in units] if units is not None else [""] * len(names)
    norm_units += [""] * (len(names) - len(norm_units))
    chosen: dict[str, Channel] = {}
    taken: set[int] = set()
    for kind, (aliases, unit_table, default_unit) in _KINDS.items():
        def factor_of(i: int) -> float | None:
            u = norm_units[i]
            if not u:
                return None
            return unit_table.get(u)

        pick = None
        # 1. a known name with a unit of the right kind (or no unit at all)
        # a time in seconds beats an Excel-day one (whose digits round it coarser)
        ranked = sorted((norm_units[i] in DAY_UNITS, aliases.index(n), i)
                        for i, n in enumerate(norm_names) if n in aliases and i not in taken)
        for *_, i in ranked:
            if norm_units[i] == "" or factor_of(i) is not None:
                pick = i
                break
        # 2. an unknown name, but the only column with a unit of this kind
        if pick is None:
            by_unit = [i for i in range(len(names)) if i not in taken and factor_of(i) is not None]
            if kind == "time" and len(by_unit) > 1:  # e.g. MTS "Datum (d)" beside a time in s
                by_unit = [i for i in by_unit if norm_units[i] not in DAY_UNITS] or by_unit
            if len(by_unit) == 1:
                pick = by_unit[0]
        if pick is None:
            shown = ", ".join(f"{n}" + (f" ({u})" if u else "") for n, u in
                              zip(names, units or [""] * len(names)) if str(n).strip())
            with_unit = [n for i, n in enumerate(names) if factor_of(i) is not None]
            why = (f"several {kind} columns and none with a known name ({', '.join(with_unit)})"
                   if len(with_unit) > 1 else f"no {kind} column")
            raise FoamlabError(f"{source}: {why} among: {shown or '(none)'}")
        taken.add(pick)
        factor = factor_of(pick)
        if factor is None:
            if norm_units[pick]:
                raise FoamlabError(f"{source}: unknown unit '{units[pick]}' for {kind} "
                                   f"column '{names[pick]}'")
            factor = 1.0  # no unit given: the SI unit foamlab uses
        shown_unit = str(units[pick]).strip().strip("()[]{}<> ") if norm_units[pick] else ""
        chosen[kind] = Channel(pick, str(names[pick]).strip().strip('"'),
                               shown_unit or default_unit, factor)
    return chosen


# --------------------------------------------------------------------------- conventions

def to_foamlab_convention(time_s: np.ndarray, disp_mm: np.ndarray, force_N: np.ndarray,
                          metadata: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compression positive, displacement 0 at the first sample, time 0 at the first sample.

    Vendors store compression negative (Bluehill, testXpert in tension setups)
    or positive; the sign is read from the data: the force peak of a compression
    run is compressive, and the force grows with compression.
    """
    force = force_N.copy()
    disp = disp_mm.copy()
    if abs(np.min(force)) > abs(np.max(force)):
        force = -force
        metadata["force_sign"] = "negated: file stores compression negative"
    change = disp - disp[0]
    corr = np.nan
    if np.ptp(change) > 0 and np.ptp(force) > 0:
        corr = float(np.corrcoef(change, force)[0, 1])
    if (np.isfinite(corr) and corr < 0) or (not np.isfinite(corr) and
                                           abs(np.min(change)) > abs(np.max(change))):
        disp = -disp
        metadata["displacement_sign"] = "negated: file stores compression negative"
    if disp[0] != 0:
        metadata["displacement_offset_mm"] = float(disp[0])
    if time_s[0] != 0:
        metadata["time_offset_s"] = float(time_s[0])
    return time_s - time_s[0], disp - disp[0], force


# --------------------------------------------------------------------------- dates

_DATE = re.compile(
    r"^\s*(\d{1,4})\s*[./\-年]\s*(\d{1,2})\s*[./\-月]\s*(\d{1,4})\s*日?"
    r"(?:[ T,]+(上午|下午)?\s*(\d{1,2}):(\d{2})(?::(\d{2}))?\s*([AaPp][Mm]|上午|下午)?)?\s*$")


def parse_date(text: str, day_first: bool | None = None) -> tuple[str, bool]:
    """ISO 8601 local time from a vendor date, and whether day/month was ambiguous.

    Y-M-D is unambiguous; for D/M/Y vs M/D/Y a field > 12 decides, then
    ``day_first`` when the file says (MTS headers do), otherwise day-first is
    assumed (Bluehill and testXpert outside the US) and flagged.
    Returns ("", False) for text that is not a date.
    """
    m = _DATE.match(text or "")
    if not m:
        return "", False
    a, b, c = (int(m.group(i)) for i in (1, 2, 3))
    ambiguous = False
    if a > 31:                       # Y-M-D
        year, month, day = a, b, c
    else:
        year = c + (2000 if c < 100 else 0)
        if a > 12:
            day, month = a, b
        elif b > 12 or day_first is False:
            month, day = a, b
        else:
            day, month = a, b
            ambiguous = a != b and day_first is None
    hour = int(m.group(5) or 0)
    minute = int(m.group(6) or 0)
    second = int(m.group(7) or 0)
    meridiem = (m.group(8) or m.group(4) or "").lower()
    if meridiem in ("pm", "下午") and hour < 12:
        hour += 12
    if meridiem in ("am", "上午") and hour == 12:
        hour = 0
    try:
        stamp = _dt.datetime(year, month, day, hour, minute, second)
    except ValueError:
        return "", False
    return stamp.isoformat(), ambiguous


def parse_length_mm(text: str) -> float | None:
    """A specimen dimension such as '72.5', '72,5 mm' or '2.85 in', in mm."""
    m = re.match(r"^\s*([-+]?\d+(?:[.,]\d+)?)\s*([A-Za-zµμ毫米英寸厘]*)\s*$", text or "")
    if not m:
        return None
    value = float(m.group(1).replace(",", "."))
    unit = normalize_unit(m.group(2)) or "mm"
    factor = LENGTH_UNITS.get(unit)
    if factor is None or not np.isfinite(value) or value <= 0:
        return None
    return value * factor
