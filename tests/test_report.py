"""`foamlab report` and `foamlab series` (foamlab.reporting): the PDF a lab archives, read back
with poppler (pdftotext for its text, pdftoppm for its pages), and the specimen series'
statistics against numbers worked out by hand."""

from __future__ import annotations

import csv
import hashlib
import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from foamlab import cli, pipeline
from foamlab.reporting import specimen_series, write_report
from foamlab.reporting.content import schedule_summary
from foamlab.reporting.series import Column, statistic
from foamlab.rundata import Specimen
from foamlab.storage.runfile import write_run_file
from tests.hil_support import short_method
from tests.synthetic import triangle_run

REAL = Path(__file__).parent / "data" / "real" / "Specimen_RawData_6.csv"
SECTIONS = ("Run file", "Specimen", "Method", "Machine profile", "Curves", "Results of the method",
            "Fit of the model", "Forecast of each cycle from the earlier ones", "Diagnosis", "Schedule statistics")

needs_poppler = pytest.mark.skipif(shutil.which("pdftotext") is None or shutil.which("pdftoppm") is None,
                                   reason="poppler-utils (pdftotext, pdftoppm) not installed: scripts/setup.sh")


def pdf_text(pdf: Path) -> str:
    return subprocess.run(["pdftotext", "-layout", str(pdf), "-"], check=True, capture_output=True,
                          text=True, timeout=30).stdout


def render_first_page(pdf: Path, folder: Path) -> np.ndarray:
    """Page 1 through pdftoppm, as a grey image (PGM: no imaging library needed to read it)."""
    prefix = folder / "page"
    subprocess.run(["pdftoppm", "-r", "40", "-gray", "-f", "1", "-l", "1", str(pdf), str(prefix)],
                   check=True, capture_output=True, timeout=30)
    page = next(folder.glob("page*.pgm"))
    data = page.read_bytes()
    _, w, h, _ = data.split(maxsplit=4)[:4]
    pixels = np.frombuffer(data[-int(w) * int(h):], np.uint8)
    return pixels.reshape(int(h), int(w))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err and len(err.splitlines()) == 1, err
    return err


# --------------------------------------------------------------------------- a real run

@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A run made by `foamlab run` on the built-in simulated machine (three short cycles at x12,
    fitted and diagnosed as `foamlab run` does), then `foamlab report` on its run file with
    the diagnosis forbidden: the one stored beside the run is current and must be used."""
    folder = tmp_path_factory.mktemp("report")
    method = short_method(folder, strain=0.15, speed=100.0, cycles=3)
    data = folder / "data"
    assert cli.main(["run", "--method", str(method), "--speedup", "12", "--out", str(data), "--quiet",
                     "--specimen-label", "R7", "--width", "100", "--depth", "100"]) == 0
    run_file = next(data.glob("*_R7_short.csv"))
    sidecars = {p: p.stat().st_mtime_ns for p in data.glob("*.json")}
    assert len(sidecars) == 2                       # <run>.fit.json, <run>.diagnosis.json

    def no_diagnosis(*args, **kwargs):
        raise AssertionError("diagnosed again although the stored diagnosis is current")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "diagnose", no_diagnosis)
        code = cli.main(["report", str(run_file), "--method", str(method)])
    assert {p: p.stat().st_mtime_ns for p in data.glob("*.json")} == sidecars   # current: left alone
    return run_file, code


@pytest.mark.hil
@pytest.mark.timeout(300)     # may set up the recorded run, as the next test may
@needs_poppler
def test_report_of_a_foamlab_run_has_every_section_and_the_run_files_sha256(recorded, capsys):
    run_file, code = recorded
    assert code == 0
    pdf = run_file.with_name(f"{run_file.stem}.report.pdf")      # beside the run file by default
    assert pdf.is_file()
    text = pdf_text(pdf)
    for section in SECTIONS:
        # a heading starts a line, or a page when the section before it filled one (how much
        # precedes it varies from run to run: the forecast's and the schedule's lines)
        assert re.search(rf"(^|[\n\f]) *{re.escape(section)}\n", text), section
    digest = sha256(run_file)
    pages = text.count("\f")
    assert text.count(digest) == 1 + pages          # the run file section and every page's footer
    flat = " ".join(text.split())                   # phrases may wrap at any width
    for words in ("R7", "sim-modbus-tcp", "Hysteresis loss, cycle 3", "%", "100 mm", "joint", "adjusted R²",
                  "Parameters the data determine", "verdict:", "stored with the run", "missed deadlines"):
        assert words in flat, words
    # the stages' failure lines ("not fitted: ...") - not a settled form's "the other form was not fitted"
    for failed in ("not fitted:", "not diagnosed:"):
        assert failed not in flat, failed


@pytest.mark.hil
@pytest.mark.timeout(300)     # may set up the recorded run (20 s idle, 2-3x with a core busy)
@needs_poppler
def test_report_renders_to_an_a4_page_with_its_figures(recorded, tmp_path):
    run_file, _ = recorded
    page = render_first_page(run_file.with_name(f"{run_file.stem}.report.pdf"), tmp_path)
    h, w = page.shape
    assert abs(h / w - math.sqrt(2)) < 0.01                        # A4
    ink = page < 200                                                # grey at 40 dpi: text, lines, tables
    assert 0.03 < ink.mean() < 0.5                                  # a page with content, not blank
    assert ink[int(0.55 * h):int(0.9 * h)].mean() > 0.03           # the curves sit in the lower half


# --------------------------------------------------------------------------- imported export

@pytest.mark.timeout(120)
@needs_poppler
def test_report_of_an_imported_export_goes_to_out_and_nothing_beside_the_export(tmp_path, capsys):
    before = sorted(REAL.parent.iterdir())
    out = tmp_path / "22L3.pdf"
    assert cli.main(["report", str(REAL), "--out", str(out), "--no-diagnose", "--method", "paper-3cycle"]) == 0
    assert capsys.readouterr().out.strip().splitlines() == ["fitting the model...", f"report: {out.resolve()}"]
    assert sorted(REAL.parent.iterdir()) == before
    text = " ".join(pdf_text(out).split())
    for words in ("22L.3", "Instron Bluehill", sha256(REAL), "paper-3cycle", "damping", "residual", "elastic", "joint",
                  "Parameters the data determine", "not diagnosed", "the specimen height is not recorded"):
        assert words in text, words


@needs_poppler
def test_report_of_an_export_without_out_goes_to_the_current_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["report", str(REAL), "--no-fit"]) == 0
    pdf = tmp_path / "Specimen_RawData_6.report.pdf"
    assert capsys.readouterr().out.strip() == f"report: {pdf}"
    text = pdf_text(pdf)
    assert sha256(REAL) in text and "not fitted" in text and "Schedule statistics" in text
    assert "no test method recorded with the run" in text


@pytest.mark.hil
@pytest.mark.timeout(120)
@needs_poppler
def test_report_diagnoses_a_run_without_a_current_diagnosis_and_stores_nothing_with_no_store(recorded, tmp_path):
    """The run file alone (its sidecars left behind): fitted once, diagnosed with that fit, the
    diagnosis report's figure reused; --no-store writes nothing beside the run file."""
    run_file, _ = recorded
    alone = tmp_path / run_file.name
    shutil.copy(run_file, alone)
    out = tmp_path / "r.pdf"
    assert cli.main(["report", str(alone), "--out", str(out), "--no-store"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alone.name, out.name])
    text = " ".join(pdf_text(out).split())      # a long verdict meaning wraps the phrase
    assert "verdict:" in text and "made now, on the fit above" in text and sha256(alone) in text
    assert "Where the base model misses" in text or "what its extension adds" in text


def test_write_report_takes_the_windows_analysis(tmp_path):
    run, _ = triangle_run(cycles=2, stroke_mm=8.0, speed_mm_min=120.0, rate_hz=20.0)
    run.specimen = Specimen("W1", 20.0, 50.0, 50.0)
    path = write_run_file(tmp_path / "w1.csv", run)
    analysis = pipeline.Analysis(run, path)
    out = write_report(path, tmp_path / "w1.pdf", analysis, fit=False)
    assert out == tmp_path / "w1.pdf" and out.read_bytes().startswith(b"%PDF")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w1.csv", "w1.pdf"]   # no sidecar without a fit


def test_schedule_statistics_from_the_header_else_counted_from_the_time_stamps():
    t = np.delete(np.arange(160) / 16.0, [40, 41, 90])           # 16 Hz, three deadlines skipped
    run = pipeline.RunData(t, np.zeros_like(t), np.zeros_like(t), metadata={"sampling_hz": 16.0})
    s = schedule_summary(run, None)
    assert (s.samples, s.missed, s.missed_source) == (157, 3, "estimated from the time stamps")
    assert s.missed_percent == pytest.approx(100 * 3 / 160)
    jittered = pipeline.RunData(t + np.where(np.arange(157) % 7 == 3, 0.02, 0.0), np.zeros(157), np.zeros(157),
                                metadata={"sampling_hz": 16.0})
    assert schedule_summary(jittered, None).missed == 3           # a sample stamped off its deadline is no miss
    run.metadata["schedule"] = {"missed": 5}                       # what the engine counted, when the file has it
    assert schedule_summary(run, None).missed == 5
    assert schedule_summary(run, None).missed_source == "recorded in the run file"


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("case", ["missing", "folder", "garbage", "not-pdf", "no-folder", "bad-option"])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, case):
    garbage = tmp_path / "garbage.csv"
    garbage.write_bytes(bytes(range(256)) * 8)
    args = {"missing": [str(tmp_path / "nothing.csv")],
            "folder": [str(tmp_path)],
            "garbage": [str(garbage), "--out", str(tmp_path / "g.pdf")],
            "not-pdf": [str(REAL), "--out", str(tmp_path / "r.txt"), "--no-fit"],
            "no-folder": [str(REAL), "--out", str(tmp_path / "no" / "r.pdf"), "--no-fit"],
            "bad-option": [str(REAL), "--pages", "2"]}[case]
    if case == "bad-option":                        # argparse's own complaint, on one line too
        with pytest.raises(SystemExit) as stop:
            cli.main(["report"] + args)
        assert stop.value.code == 2 and "unrecognized arguments: --pages" in one_error_line(capsys)
        return
    assert cli.main(["report"] + args) == 2
    assert one_error_line(capsys).startswith("foamlab report: error: ")
    assert not list(tmp_path.glob("*.pdf"))


# --------------------------------------------------------------------------- specimen series

def test_series_statistics_by_hand():
    st = statistic(Column("CV40", 4, "kPa", "CV40"), [1.0, 2.0, None, 4.0])
    # mean 7/3; deviations -4/3, -1/3, 5/3: squares 16/9 + 1/9 + 25/9 = 42/9, over n - 1 = 2: 7/3
    assert st.n == 3
    assert st.mean == pytest.approx(7 / 3)
    assert st.sd == pytest.approx(math.sqrt(7 / 3))               # 1.5275
    assert st.cv_percent == pytest.approx(100 * math.sqrt(7 / 3) / (7 / 3))   # 65.47 %
    one = statistic(Column("CV40", 4, "kPa", "CV40"), [5.0])
    assert (one.n, one.mean, one.sd, one.cv_percent) == (1, 5.0, None, None)


def _series_files(tmp_path: Path, scales=(1.0, 1.1, 1.3)) -> tuple[Path, list[Path]]:
    """Three specimens of one 3-cycle method: one run with its force scaled (so every energy
    scales exactly and the hysteresis loss, a ratio, does not change)."""
    method = tmp_path / "tri.toml"
    method.write_text('name = "tri"\ntitle = "tri"\nsampling_hz = 20.0\n'
                      '[contact]\npreload_N = 0.5\nsearch_speed_mm_min = 20.0\nmax_search_mm = 30.0\n'
                      '[[sequence]]\nrepeat = 3\nsteps = [{ action = "compress", strain = 0.4, speed_mm_min = 120.0 },'
                      ' { action = "return", speed_mm_min = 120.0 }]\n')
    base, _ = triangle_run(cycles=3, stroke_mm=8.0, speed_mm_min=120.0, rate_hz=20.0, seed=3)
    paths = []
    for i, k in enumerate(scales, 1):
        run = pipeline.RunData(base.time_s, base.displacement_mm, base.force_N * k,
                               specimen=Specimen(f"S{i}", 20.0, 50.0, 50.0), method="tri")
        paths.append(write_run_file(tmp_path / f"s{i}.csv", run))
    return method, paths


def test_series_csv_rows_and_statistics_against_hand_numbers(tmp_path, capsys):
    method, paths = _series_files(tmp_path)
    out = tmp_path / "series.csv"
    assert cli.main(["series", *map(str, paths), "--method", str(method), "--out", str(out)]) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed[0].startswith("method tri: 3 specimens") and printed[-1] == f"series: {out.resolve()}"
    assert any(line.startswith("Loading energy, cycle 1") and line.endswith("13.48") for line in printed)
    lines = out.read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith("# foamlab specimen series: method tri")
    rows = list(csv.reader(lines[1:]))
    header = rows[0]
    assert header[:2] == ["specimen", "file"]
    assert "loading_energy_c1 [J]" in header and "hysteresis_loss_c2 [%]" in header \
        and "residual_strain_c3 [mm/mm]" in header
    assert [r[0] for r in rows[1:]] == ["S1", "S2", "S3", "n", "mean", "sd", "cv [%]"]
    col = header.index("loading_energy_c1 [J]")
    e = [float(r[col]) for r in rows[1:4]]
    assert e[1] / e[0] == pytest.approx(1.1, rel=1e-5) and e[2] / e[0] == pytest.approx(1.3, rel=1e-5)
    n, mean, sd, cv = (rows[i][col] for i in range(4, 8))
    # scales 1, 1.1, 1.3: mean 1.13333; deviations -0.13333, -0.03333, 0.16667;
    # squares 0.017778 + 0.001111 + 0.027778 = 0.046667, / 2 -> sd 0.152753; cv 13.478 %
    assert int(n) == 3
    assert float(mean) == pytest.approx(1.133333 * e[0], rel=1e-5)
    assert float(sd) == pytest.approx(0.152753 * e[0], rel=1e-5)
    assert float(cv) == pytest.approx(13.478, abs=1e-3)
    hl = header.index("hysteresis_loss_c2 [%]")
    assert float(rows[7][hl]) == pytest.approx(0.0, abs=1e-6)      # a ratio: the same for all three


@needs_poppler
def test_series_pdf_shows_the_table_with_the_statistics(tmp_path, capsys):
    method, paths = _series_files(tmp_path)
    pdf = tmp_path / "series.pdf"
    assert cli.main(["series", *map(str, paths), "--method", str(method), "--pdf", str(pdf)]) == 0
    text = pdf_text(pdf)
    series = specimen_series(paths, method)
    st = series.statistic("loading_energy", 1)
    for words in ("Specimen series", "S1", "S2", "S3", "mean", "sd", "cv %", "Loading energy, cycle 1",
                  f"{st.mean:.4g}", sha256(paths[2])):
        assert words in text, words


def test_series_of_two_methods_is_refused_in_one_line(tmp_path, capsys):
    _, paths = _series_files(tmp_path, scales=(1.0, 1.2))
    other = tmp_path / "other.csv"
    run, _ = triangle_run(cycles=1, rate_hz=20.0, speed_mm_min=120.0)
    run.method = "iso3386-1"
    write_run_file(other, run)
    assert cli.main(["series", str(paths[0]), str(other)]) == 2
    err = one_error_line(capsys)
    assert "one method" in err and "s1.csv: tri" in err and "other.csv: iso3386-1" in err
