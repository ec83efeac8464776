"""Importers: every format and variant against known truth, the real Bluehill file,
malformed inputs (one-line errors, exit code 2), and property-based garbage."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from foamlab import FoamlabError
from foamlab.cli import main
from foamlab.importers import detect_format, load_run
from foamlab.importers._text import decode

DATA = Path(__file__).parent / "data"
REAL = DATA / "real" / "Specimen_RawData_6.csv"
sys.path.insert(0, str(DATA))
import make_fixtures  # noqa: E402


@pytest.fixture(scope="module")
def truth():
    run, _ = make_fixtures.truth_run()
    return run


# --------------------------------------------------------------------------- vendor fixtures

@pytest.mark.parametrize("fx", make_fixtures.FIXTURES, ids=lambda fx: fx.name)
def test_vendor_fixture_imports_to_the_truth(fx, truth):
    run = load_run(DATA / fx.name)
    assert run.metadata["format"] == fx.fmt
    assert run.specimen.label == fx.label
    assert run.started_at == fx.started_at
    assert run.status == "imported"
    assert len(run) == len(truth)
    assert run.sampling_hz == pytest.approx(5.0)
    # converted to s / mm / N, compression positive, displacement 0 at the start
    assert np.allclose(run.time_s, truth.time_s, atol=1e-4)
    x_expected = truth.displacement_mm - truth.displacement_mm[0]
    assert np.allclose(run.displacement_mm, x_expected, atol=3e-4)
    assert np.allclose(run.force_N, truth.force_N, atol=2e-3, rtol=1e-4)
    assert run.metadata["displacement_offset_mm"] == pytest.approx(
        make_fixtures.PRELOAD_OFFSET_MM + truth.displacement_mm[0], abs=3e-4)
    assert ("force_sign" in run.metadata) == (fx.sign < 0)
    assert run.segments().n_cycles == 2


def test_encodings_are_detected():
    assert load_run(DATA / "bluehill_zh_gbk.csv").metadata["encoding"] == "gb18030"
    assert load_run(DATA / "bluehill_de_cp1252.csv").metadata["encoding"] == "cp1252"
    assert load_run(DATA / "testxpert_de_semicolon.txt").metadata["encoding"] == "cp1252"
    assert load_run(DATA / "bluehill_zh_utf8bom_ms_kN.csv").metadata["encoding"] == "utf-8-bom"
    # cp1252 German decodes as GB18030 too, but as mojibake: it must not be taken for Chinese
    text, enc = decode("Prüfzeit;Standardkraft\r\ns;N\r\n".encode("cp1252"))
    assert enc == "cp1252" and text.startswith("Prüfzeit")
    text, enc = decode("时间,负荷\n(秒),(牛)\n".encode("gbk"))
    assert enc == "gb18030" and text.startswith("时间")
    text, enc = decode("Zeit;Kraft\n".encode("utf-16"))
    assert enc == "utf-16" and text.startswith("Zeit")


def test_specimen_dimension_and_units_from_header():
    run = load_run(DATA / "bluehill_us_in_lbf.csv")
    assert run.specimen.height_mm == pytest.approx(2.854 * 25.4)
    assert run.metadata["channels"]["force"] == "Compressive load (lbf)"


def test_testxpert_prefers_standard_travel_over_crosshead():
    run = load_run(DATA / "testxpert_de_semicolon.txt")
    assert run.metadata["channels"]["displacement"] == "Standardweg (mm)"
    assert run.metadata["header"]["Prüfer"] == "Müller"
    assert run.metadata["started_at_assumed_day_first"] == "05.02.2021"


def test_fixtures_are_reproducible(tmp_path):
    for path in make_fixtures.write_all(tmp_path):
        assert path.read_bytes() == (DATA / path.name).read_bytes(), path.name


def test_plain_csv_and_comment_metadata(truth):
    run = load_run(DATA / "plain.csv")
    assert run.metadata["format"] == "plain CSV"
    assert run.specimen.label == "plain-1"
    assert run.metadata["comments"] == ["plain CSV written by hand (tests/data/make_fixtures.py)"]
    assert np.allclose(run.displacement_mm, truth.displacement_mm, atol=1e-5)  # not shifted


# --------------------------------------------------------------------------- the real file

def test_real_bluehill_file_imports_as_three_compression_cycles():
    run = load_run(REAL)
    assert run.metadata["format"] == "Instron Bluehill"
    assert run.specimen.label == "22L.3"
    assert run.started_at == "2018-11-13T17:14:00"
    assert len(run) == 18011
    assert run.sampling_hz == pytest.approx(50.0, rel=1e-6)
    assert run.time_s[-1] == pytest.approx(360.06)
    # stored negative in the file: now compression positive, 0 at the start
    assert run.metadata["displacement_offset_mm"] == pytest.approx(2.04726)
    assert run.displacement_mm[0] == 0.0
    assert run.displacement_mm.max() == pytest.approx(10.0014, abs=1e-3)
    assert run.force_N[0] == pytest.approx(4.319)             # preload start
    assert run.force_N.max() == pytest.approx(52.97507)
    assert run.force_N.min() > -0.5                           # only load-cell noise below 0
    seg = run.segments()
    assert seg.n_cycles == 3
    assert seg.stroke_mm == pytest.approx(10.0, abs=0.05)


# --------------------------------------------------------------------------- malformed input

def _write(tmp_path, content, name="bad.csv"):
    p = tmp_path / name
    p.write_bytes(content if isinstance(content, bytes) else content.encode())
    return p


HEADER = "time_s,displacement_mm,force_N\n"
MALFORMED = {
    "empty": ("", "file is empty"),
    "blank": ("  \n\n", "file is empty"),
    "only comments": ("# nothing\n# here\n", "no header row"),
    "wrong header": ("time,disp,force\n0,0,0\n1,1,1\n", "header row is 'time,disp,force'"),
    "header only": (HEADER, "no data rows"),
    "text in numbers": (HEADER + "0,0,0\n0.1,abc,1\n", "line 3: 'abc' in column 'displacement_mm'"),
    "NaN": (HEADER + "0,0,0\n0.1,0.5,nan\n", "line 3: no valid number in column 'force_N'"),
    "infinite": (HEADER + "0,0,0\n0.1,inf,1\n", "line 3: no valid number in column 'displacement_mm'"),
    "time backwards": (HEADER + "0,0,0\n0.2,1,1\n0.1,2,2\n", "line 4: time goes backwards"),
    "time repeats": (HEADER + "0,0,0\n0.2,1,1\n0.2,2,2\n", "line 4: time repeats"),
    "truncated last line": (HEADER + "0,0,0\n0.1,1,1\n0.2,2", "line 4: truncated last line"),
    "missing field": (HEADER + "0,0,0\n0.1,1\n0.2,2,2\n", "line 3: 2 fields, expected 3"),
    "extra field": (HEADER + "0,0,0\n0.1,1,1,7\n", "line 3: 4 fields, expected 3"),
    "one sample": (HEADER + "0,0,0\n", "only 1 sample"),
    "binary": (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "binary file"),
    "unknown": ("hello world\n", "unknown format"),
    "bluehill no force": ("General : Start Date,1/1/2020\n\nTime,Extension\n(s),(mm)\n0,0\n1,1\n",
                          "no force column"),
    "bluehill bad unit": ("Time,Extension,Load\n(s),(furlong),(N)\n0,0,0\n1,1,1\n",
                          "no displacement column"),
    "testxpert text": ("Prüfzeit;Standardkraft;Standardweg\ns;N;mm\n0,0;0,0;0,0\n0,1;x;0,1\n",
                       "line 4: 'x' in column 'force'"),
}


@pytest.mark.parametrize("case", list(MALFORMED), ids=list(MALFORMED))
def test_malformed_input_gives_one_line_error(tmp_path, case):
    content, expected = MALFORMED[case]
    path = _write(tmp_path, content)
    with pytest.raises(FoamlabError) as info:
        load_run(path)
    message = str(info.value)
    assert expected in message
    assert "\n" not in message and str(path) in message


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(FoamlabError, match="file not found"):
        load_run(tmp_path / "nope.csv")
    with pytest.raises(FoamlabError, match="is a folder"):
        load_run(tmp_path)


@pytest.mark.parametrize("content,expected", [
    (HEADER + "0,0,0\n0.1,abc,1\n", "'abc'"),
    (HEADER + "0,0,1\n0.1,0,1\n0.2,0,1\n0.3,0,1\n", "no motion"),   # 0 cycles
    ("", "file is empty"),
])
def test_cli_show_exit_code_and_single_line(tmp_path, capsys, content, expected):
    path = _write(tmp_path, content)
    assert main(["show", str(path)]) == 2
    err = capsys.readouterr().err
    assert expected in err and err.count("\n") == 1 and "Traceback" not in err


def test_cli_show_real_file_and_plot(tmp_path, capsys):
    out = tmp_path / "plot.png"
    assert main(["show", str(REAL), "--plot", str(out)]) == 0
    text = capsys.readouterr().out
    assert "cycles:        3" in text and "contact lost" in text
    assert out.stat().st_size > 10_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_detect_format_does_not_need_the_whole_file():
    lines = REAL.read_text().splitlines()[:10]
    assert detect_format(lines) == "Instron Bluehill"


# --------------------------------------------------------------------------- property-based

def _check_no_internal_error(path):
    try:
        run = load_run(path)
    except FoamlabError as exc:
        message = str(exc)
        assert "\n" not in message
        assert "internal parser error" not in message, message
        return
    assert len(run) >= 2 and np.all(np.diff(run.time_s) > 0)
    try:
        run.segments()
    except FoamlabError as exc:
        assert "\n" not in str(exc)


# CI runs a fixed, fast sample; FOAMLAB_HYPOTHESIS_EXAMPLES=5000 searches harder (random).
_EXAMPLES = int(os.environ.get("FOAMLAB_HYPOTHESIS_EXAMPLES", "120"))
_SETTINGS = settings(max_examples=_EXAMPLES, deadline=None, derandomize=_EXAMPLES <= 120,
                     suppress_health_check=[HealthCheck.function_scoped_fixture,
                                            HealthCheck.too_slow])


@_SETTINGS
@given(st.binary(max_size=600))
def test_random_bytes_never_escape(tmp_path, raw):
    _check_no_internal_error(_write(tmp_path, raw, "random.csv"))


_cells = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.sampled_from(["", " ", "nan", "abc", "1e999", "-", "1,5", '"2"', "0x10", "1.2.3", "１２"]),
    st.text(max_size=6),
)
_headers = st.sampled_from([
    "time_s,displacement_mm,force_N",
    "time_s,displacement_mm,force_N,rtt_ms",
    "# foamlab run file v1\n# status: finished\ntime_s,displacement_mm,force_N",
    "General : Start Date,1/1/2020\n\nTime,Extension,Load\n(sec),(mm),(N)",
    "时间,拉伸,负荷\n(秒),(毫米),(牛)",
    "Prüfzeit;Standardkraft;Standardweg\ns;N;mm",
    "Test time\tStandard force\tStandard travel\n[s]\t[kN]\t[mm]",
    "Time,Extension,Load\n(sec),(mm),(furlong)",
])


@_SETTINGS
@given(_headers, st.lists(st.lists(_cells, min_size=0, max_size=5), max_size=12),
       st.sampled_from([",", ";", "\t"]), st.booleans(), st.sampled_from(["utf-8", "gb18030", "cp1252"]))
def test_random_csvs_never_escape(tmp_path, header, rows, sep, final_newline, encoding):
    body = "\n".join(sep.join(r) for r in rows)
    text = header + "\n" + body + ("\n" if final_newline else "")
    raw = text.encode(encoding, errors="replace")
    _check_no_internal_error(_write(tmp_path, raw, "random.csv"))


@_SETTINGS
@given(st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)), min_size=2, max_size=60))
def test_random_valid_tables_import_exactly(tmp_path, samples):
    text = HEADER + "".join(f"{0.1 * i!r},{x!r},{f!r}\n" for i, (x, f) in enumerate(samples))
    run = load_run(_write(tmp_path, text, "valid.csv"))
    assert np.array_equal(run.displacement_mm, [x for x, _ in samples])
    assert np.array_equal(run.force_N, [f for _, f in samples])


def test_cli_show_json(capsys):
    import json

    assert main(["show", str(REAL), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["cycles"] == 3 and summary["samples"] == 18011
    assert [tp["index"] for tp in summary["turning_points"]] == [3004, 6005, 9006, 12008, 15009]
    assert [tp["kind"] for tp in summary["turning_points"]] == ["max", "min", "max", "min", "max"]
    assert [c["cycle"] for c in summary["contact_lost"]] == [2, 3, 3]
    assert summary["linear_region"]["r2"] > 0.998
