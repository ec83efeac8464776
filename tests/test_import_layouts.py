"""Every export layout of issue 17 (tests/data/layouts/, written by make_layouts.py):
read, converted and segmented into its cycles; the quirks noted; binary testXpert
files refused in one line; a fuzz test over the vendor readers."""

from __future__ import annotations

import gzip
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from foamlab import FoamlabError
from foamlab.cli import main
from foamlab.importers import load_run
from foamlab.importers._text import decode

DATA = Path(__file__).parent / "data"
LAYOUTS = DATA / "layouts"
sys.path.insert(0, str(DATA))
import make_layouts  # noqa: E402


@pytest.mark.parametrize("name", list(make_layouts.LAYOUTS))
def test_layout_is_read_and_segmented(name):
    expect = make_layouts.LAYOUTS[name][1]
    run = load_run(LAYOUTS / name)
    assert run.metadata["format"] == expect.fmt
    assert run.specimen.label == expect.label
    assert run.metadata.get("operator", "") == expect.operator
    if expect.encoding:
        assert run.metadata["encoding"] == expect.encoding
    notes = " | ".join(run.metadata.get("import_notes", []))
    for text in expect.notes:
        assert text in notes
    assert np.all(np.diff(run.time_s) > 0) and run.time_s[0] == 0.0
    # compression positive in foamlab's units whatever the file stored
    assert run.force_N.max() > 5.0 and run.force_N.max() > -run.force_N.min()
    assert run.displacement_mm.max() == pytest.approx(
        5.0 if expect.cycles == 3 else 2.0, abs=0.05)
    if expect.force_max_N:
        assert run.force_N.max() > expect.force_max_N
    assert run.segments().n_cycles == expect.cycles


def test_layout_fixtures_are_reproducible(tmp_path):
    for path in make_layouts.write_all(tmp_path):
        assert path.read_bytes() == (LAYOUTS / path.name).read_bytes(), path.name


def test_wavematrix_grouped_time_is_read_exactly():
    run = load_run(LAYOUTS / "wavematrix_bom.steps.tracking.csv")
    assert run.metadata["time_offset_s"] == pytest.approx(985.0)
    assert run.time_s[-1] == pytest.approx(40.0)          # 985 .. 1025 s, past "1,000.00000"
    assert run.sampling_hz == pytest.approx(10.0)
    assert run.metadata["channels"]["force"] == "Load (kN)"


def test_mts_blocks_with_other_columns_are_joined_by_name():
    run = load_run(LAYOUTS / "mts_enu_blocks.dat")
    assert len(run) == 61 and run.sampling_hz == pytest.approx(10.0)
    assert run.started_at == "2016-03-29T13:55:00"       # M/D/Y: the format line says so
    assert run.metadata["channels"] == {"time": "Running Time (Sec)",
                                        "displacement": "Displacement (mm)",
                                        "force": "Force (kN)"}


def test_mts_excel_day_time_and_left_out_peak_block():
    run = load_run(LAYOUTS / "mts_deu_exceltime.dat")
    assert run.started_at == "2023-06-30T07:30:00"       # the first block's clock, D.M.Y
    assert run.metadata["channels"]["time"] == "Datum (d)"
    assert run.time_s[-1] == pytest.approx(6.0, abs=0.1)
    assert run.sampling_hz == pytest.approx(20.0, rel=0.03)  # the day number's 86 ms rounding undone
    assert "t = 999..5" in run.metadata["import_notes"][0]


def test_repeated_timestamps_are_spread_in_order():
    run = load_run(LAYOUTS / "bluehill_repeated_time.csv")
    assert len(run) == 122                                # nothing dropped
    # rounded to 0.1 s at 20 Hz: the repeats are re-spaced to the 20 Hz they were
    assert np.diff(run.time_s) == pytest.approx(0.05, abs=0.02)


def test_show_prints_the_import_notes(capsys):
    assert main(["show", str(LAYOUTS / "bluehill_repeated_time.csv")]) == 0
    out = capsys.readouterr().out
    assert "import note:   time repeats at" in out
    assert main(["show", str(LAYOUTS / "mts_enu_blocks.dat"), "--json"]) == 0
    import json
    summary = json.loads(capsys.readouterr().out)
    assert summary["operator"] == "J. Smith" and summary["cycles"] == 3
    assert summary["import_notes"] == ["7 data blocks joined in file order"]


@pytest.mark.parametrize("text,encoding", [
    ("Etykieta próbki;Pianka żółta\nSiła;Czas\n", "cp1250"),
    ("Prędkość;wartość\n", "cp1250"),
    ("Probenbezeichnung;Würfel Ä\nVolumen;mm³\n", "cp1252"),
    ("Contrainte à rupture;Éprouvette\n", "cp1252"),
    ("Año;señal\n", "cp1252"),
])
def test_cp1250_and_cp1252_told_apart(text, encoding):
    assert decode(text.encode(encoding)) == (text, encoding)


@pytest.mark.parametrize("name", ["series.zs2", "Probe.ZSE"])
def test_testxpert_binary_is_refused_in_one_line(tmp_path, capsys, name):
    path = tmp_path / name
    path.write_bytes(gzip.compress(b"\x00\x01testXpert binary\x00" * 20))
    assert main(["show", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "testXpert native file" in err and "Export" in err


def test_renamed_zs2_is_refused_by_its_bytes(tmp_path):
    path = tmp_path / "export.csv"
    path.write_bytes(gzip.compress(b"\x00binary" * 10))
    with pytest.raises(FoamlabError, match="compressed binary file.*testXpert"):
        load_run(path)


BROKEN = {
    "wavematrix text in a number": (
        ('"Total Time (s)","Total Cycles","Position(Linear:Position) (mm)","Load(Linear:Load) (kN)",\n'
         '0.0,0,0.0,0.0,\n0.1,0,abc,0.1,\n'), "line 3: 'abc' in column 'displacement'"),
    "mts time backwards": (
        ("MTS793|MPT|ENU|1|2|.|/|:|1|0|0|A\n\nData Header\tTime:\t1\tSec\n"
         "Running Time\tAxial Displacement\tAxial Force\nSec\tmm\tkN\n0.0\t0\t0\n0.2\t1\t1\n0.1\t2\t2\n"),
        "line 8: time goes backwards"),
    "mts no force": (
        ("MTS793|MPT|ENU|1|2|.|/|:|1|0|0|A\n\nData Header\tTime:\t1\tSec\n"
         "Running Time\tAxial Displacement\nSec\tmm\n0.0\t0\n0.2\t1\n"), "no force column"),
    "unclosed quote": (
        'Time measurement (s),Extension (mm),Primary load measurement (N)\n0,0,0\n0.1,"1,1\n0.2,2,2\n',
        "line 3: a quote"),
    "bluehill 3 missing field": (
        "Time measurement (s),Extension (mm),Primary load measurement (N)\n0,0,0\n0.1,1\n0.2,2,2\n",
        "line 3: 2 fields, expected 3"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_layouts_get_one_line_naming_the_line(tmp_path, case):
    content, expected = BROKEN[case]
    path = tmp_path / "broken.dat"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(FoamlabError) as info:
        load_run(path)
    assert expected in str(info.value) and "\n" not in str(info.value)


# --------------------------------------------------------------------------- fuzz

# CI runs a fixed, fast sample; FOAMLAB_HYPOTHESIS_EXAMPLES=5000 searches harder (random).
_EXAMPLES = int(__import__("os").environ.get("FOAMLAB_HYPOTHESIS_EXAMPLES", "120"))
_FUZZ = settings(max_examples=_EXAMPLES, deadline=None, derandomize=_EXAMPLES <= 120,
                 suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_FIXTURE_BYTES = {name: (LAYOUTS / name).read_bytes() for name in make_layouts.LAYOUTS}


def _outcome(path: Path) -> None:
    """A RunData with increasing time, or a one-line FoamlabError: nothing else."""
    try:
        run = load_run(path)
    except FoamlabError as exc:
        assert "\n" not in str(exc) and "internal parser error" not in str(exc), str(exc)
        return
    assert len(run) >= 2 and np.all(np.diff(run.time_s) > 0)
    assert np.all(np.isfinite(run.displacement_mm)) and np.all(np.isfinite(run.force_N))


@_FUZZ
@given(st.sampled_from(sorted(_FIXTURE_BYTES)), st.floats(0.0, 1.0),
       st.lists(st.tuples(st.floats(0.0, 1.0), st.binary(min_size=1, max_size=3)), max_size=4))
def test_fuzz_truncated_and_mutated_exports(tmp_path, name, cut, mutations):
    raw = bytearray(_FIXTURE_BYTES[name])
    for where, junk in mutations:
        i = int(where * (len(raw) - 1))
        raw[i:i + len(junk)] = junk
    raw = bytes(raw[:max(1, int(cut * len(raw)))])
    path = tmp_path / name
    path.write_bytes(raw)
    _outcome(path)


_HEADS = [
    ("MTS793|MPT|ENU|1|2|.|/|:|1|0|0|A\n\nData Header\tTime:\t1\tSec\n"
     "Running Time\tAxial Displacement\tAxial Force\nSec\tmm\tkN"),
    "MTS793|MPT|DEU|1|2|,|.|:|49|1|1|A\n\nDatenerfassung\tZeit:\t1\ts\nDatum\tCh 1 Weg\tCh 1 Kraft\nd\tmm\tkN",
    "MTS793|MPT|ENU|1|0|.|/|:|1|0|0|A\n\nData Header  Time:  1  Sec\nRunning Time  Axial Force  Axial Displacement\nSec  kN  mm",
    '\ufeff"Total Time (s)","Total Cycles","Position(Linear:Position) (mm)","Load(Linear:Load) (kN)",',
    "Gesamtzeit (s);Gesamtzyklen;Position des Aktuators (mm);Kraft (N);",
    "Time measurement (s),Extension (mm),Primary load measurement (N)",
    "Texteingaben : Probenbeschriftung;Würfel\n\nZeit;Weg;Kraft\n(s);(mm);(N)",
    "aktuelle Probe;Schaum\nPrüfzeit;Standardkraft;Standardweg\ns;N;mm",
]
_NUMBERS = st.one_of(
    st.floats(-5e3, 5e3).map(lambda v: f"{v:.4f}"),
    st.floats(-5e6, 5e6).map(lambda v: f"{v:,.3f}"),                      # 1,234.567
    st.floats(-5e6, 5e6).map(lambda v: f"{v:,.2f}".replace(",", "\u00a0").replace(".", ",")),
    st.floats(-5e6, 5e6).map(lambda v: f'"{v:,.5f}"'),
    st.sampled_from(["", "0", "0", "1,5", "1.000,5", "1\u202f000,0", "nan", "-", "x", '"', "1e400"]),
)


@_FUZZ
@given(st.sampled_from(_HEADS), st.lists(st.lists(_NUMBERS, min_size=0, max_size=4), max_size=10),
       st.sampled_from([",", ";", "\t", "  "]), st.sampled_from(["\n", "\r\n", "\r"]),
       st.sampled_from(["utf-8", "utf-8-sig", "cp1250", "cp1252", "gbk", "utf-16"]))
def test_fuzz_vendor_layouts(tmp_path, head, rows, sep, newline, encoding):
    text = newline.join([head] + [sep.join(r) for r in rows]) + newline
    path = tmp_path / "fuzz.csv"
    path.write_bytes(text.encode(encoding, errors="replace"))
    _outcome(path)


def test_mts_displacement_zeroed_at_the_start_is_joined(tmp_path):
    # MTS zeroes the displacement when the test starts (38 mm -> 0 between two samples)
    t = np.arange(0.0, 130.0, 0.5)
    phase = ((t - 10.0) / 20.0) % 2.0
    x = np.where(t < 10.0, 0.0, -0.34 * np.where(phase < 1, phase, 2 - phase))
    shown = np.where(t < 10.0, 38.03, x)
    rows = [f"{ti:.2f}\t{si:.5f}\t{xi / 0.34 * 110 - 4:.4f}" for ti, si, xi in zip(t, shown, x)]
    text = ("MTS793|MPT|ENU|1|2|.|/|:|1|0|0|A\n\nData Acquisition\tTime:\t130\tSec\n"
            "Running Time\tCh 1 Displacement\tCh 1 Force\nSec\tmm\tkN\n" + "\n".join(rows) + "\n")
    path = tmp_path / "specimen.dat"
    path.write_text(text)
    run = load_run(path)
    assert "the channel was zeroed" in run.metadata["import_notes"][0]
    assert run.displacement_mm.max() == pytest.approx(0.34, abs=1e-3)
    assert run.segments().n_cycles == 3


def test_mts_blocks_without_titles_or_blank_lines(tmp_path):
    rows = [f"{0.1 * i:.1f}\t{-abs(((i / 10) % 2) - 1) * 5:.4f}\t{-abs(((i / 10) % 2) - 1):.4f}"
            for i in range(61)]
    parts = ["MTS793|MPT|ENU|1|2|.|/|:|1|0|0|A", ""]
    for k in range(0, 61, 20):
        parts += ["Running Time\tAxial Displacement\tAxial Force", "s\tmm\tkN"] + rows[k:k + 20]
    path = tmp_path / "specimen.dat"
    path.write_text("\n".join(parts) + "\n")
    run = load_run(path)
    assert len(run) == 61 and run.segments().n_cycles == 3


@pytest.mark.parametrize("delimiter", ["1", "0"])
def test_mts_comma_and_space_delimited_exports(tmp_path, delimiter):
    # the format line's delimiter: 1 = comma ("Lotus", strings quoted), 0 = spaces ("plain")
    t = np.arange(0.0, 30.05, 0.1)
    x = 5.0 - np.abs(((t / 5.0) % 2.0) - 1.0) * 5.0
    if delimiter == "1":
        head = ('"Data Header","","Time:","1","Sec","3/29/2016 1:54:32 PM"\n'
                '"Running Time","Axial Displacement","Axial Force"\n"Sec","mm","kN"\n')
        rows = [f"{ti:.2f},{-xi:.4f},{-xi * 0.002:.6f}" for ti, xi in zip(t, x)]
    else:
        head = ("Data Header          Time:   1  Sec   3/29/2016 1:54:32 PM\n"
                "Running Time    Axial Displacement    Axial Force\nSec mm kN\n")
        rows = [f"  {ti:8.2f}  {-xi:9.4f}  {-xi * 0.002:10.6f}" for ti, xi in zip(t, x)]
    path = tmp_path / "specimen.dat"
    path.write_text(f"MTS793|MPT|ENU|1|{delimiter}|.|/|:|1|0|0|A\n\n" + head + "\n".join(rows) + "\n")
    run = load_run(path)
    assert run.force_N.max() == pytest.approx(10.0)      # kN read as kN
    assert run.started_at == "2016-03-29T13:54:32"
    assert run.segments().n_cycles == 3
