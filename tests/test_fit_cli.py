"""`foamlab fit PATH`: table, --json (exactly the DESIGN.md object), --plot, storage, errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from foamlab.cli import main
from foamlab.model import ModelParameters, evaluate, triangular_history

REAL = Path(__file__).parent / "data" / "real" / "Specimen_RawData_6.csv"


@pytest.fixture(scope="module")
def plain_csv(tmp_path_factory) -> Path:
    """A plain CSV of the default specimen on a short paper-like protocol (4 Hz)."""
    p = ModelParameters.default()
    t, x = triangular_history(58.0, 23.6 / 60.0, 3, 4.0)
    f = evaluate(p, t, x).measured_force + np.random.default_rng(1).normal(0, 0.1, len(t))
    path = tmp_path_factory.mktemp("runs") / "synthetic.csv"
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# synthetic run of the default specimen\ntime_s,displacement_mm,force_N\n")
        for row in zip(t, x, f):
            fh.write("%.4f,%.5f,%.4f\n" % row)
    return path


def test_json_is_exactly_the_design_object(plain_csv, capsys, tmp_path):
    run = tmp_path / plain_csv.name
    shutil.copy(plain_csv, run)
    assert main(["fit", str(run), "--json", "--orders", "2,3,7", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr()
    obj = json.loads(out.out)                            # stdout: one JSON object, nothing else
    assert list(obj)[:4] == ["parameters", "statistics", "rmse", "constraints"]
    assert set(obj["statistics"]) == {"damping", "residual", "elastic", "joint"}
    assert all(set(s) == {"sse", "r2", "adj_r2", "rmse"} for s in obj["statistics"].values())
    assert all({"value", "stderr"} <= set(v) for v in obj["parameters"].values())
    assert obj["parameters"]["x_scale_mm"]["stderr"] is None
    assert all(isinstance(v, bool) for v in obj["constraints"].values())
    assert isinstance(obj["rmse"], float) and obj["rmse"] < 0.15
    # kept in the folder named (note on stderr), and usable as a simulator specimen
    side = run.with_name("synthetic.fit.json")
    assert side.exists() and "stored" in out.err
    assert ModelParameters.load(side).order_N == 2


def test_table_plot_and_no_store(plain_csv, capsys, tmp_path):
    run = tmp_path / plain_csv.name
    shutil.copy(plain_csv, run)
    png = tmp_path / "fit.png"
    assert main(["fit", str(run), "--plot", str(png), "--no-store", "--orders", "1,1,7"]) == 0
    out = capsys.readouterr().out
    # a terminal gets the short summary: quality against the noise, determined parameters
    assert "x the load cell's noise" in out and "parameters the data determine" in out
    assert "[[Parameters]]" not in out and len(out.splitlines()) < 40
    assert main(["fit", str(run), "--no-store", "--orders", "1,1,7", "--full"]) == 0
    out = capsys.readouterr().out
    for word in ("[[Statistics]]", "damping", "residual", "elastic", "joint", "[[Parameters]]",
                 "[[Constraints]]", "RMSE"):
        assert word in out
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not run.with_name("synthetic.fit.json").exists()


def test_compare_orders_prints_information_criteria(plain_csv, capsys):
    assert main(["fit", str(plain_csv), "--no-store", "--orders", "1,1,7", "--compare", "0,1,5"]) == 0
    out = capsys.readouterr().out
    assert "[[Orders]]" in out and "BIC" in out and "<- best BIC" in out


def test_real_bluehill_file_from_the_command_line(tmp_path):
    run = tmp_path / REAL.name
    shutil.copy(REAL, run)
    proc = subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(run), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    obj = json.loads(proc.stdout)
    assert obj["statistics"]["joint"]["r2"] > 0.998      # no cancelling terms (test_identification)


@pytest.mark.parametrize("make, expected", [
    (lambda d: d / "missing.csv", "not found"),
    (lambda d: _write(d / "half.csv", halves=1), "no complete cycle"),
    (lambda d: _write(d / "flat.csv", halves=6, flat=True), "force is flat"),
])
def test_bad_runs_exit_2_with_one_line(tmp_path, capsys, make, expected):
    path = make(tmp_path)
    assert main(["fit", str(path), "--no-store"]) == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and "\n" not in err and "Traceback" not in err


def test_a_single_cycle_is_fitted_and_says_what_it_skipped(tmp_path, capsys):
    path = _write(tmp_path / "one.csv", halves=2)
    assert main(["fit", str(path)]) == 0
    out = capsys.readouterr().out
    assert "three steps skipped" in out and "a single cycle" in out
    # an imported file gets nothing beside it unless a folder is named
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.csv"]
    keep = tmp_path / "fits"
    keep.mkdir()
    assert main(["fit", str(path), "--out", str(keep)]) == 0
    assert (keep / "one.fit.json").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["fits", "one.csv"]


def test_bad_orders_exit_2(plain_csv, capsys):
    assert main(["fit", str(plain_csv), "--orders", "3,x,7", "--no-store"]) == 2
    err = capsys.readouterr().err.strip()
    assert "N,M,P" in err and "\n" not in err


def _write(path: Path, halves: int, flat: bool = False) -> Path:
    t, x = triangular_history(10.0, 0.5, 3, 10.0)
    n = int(round(halves * 20.0 * 10.0)) + 1
    rng = np.random.default_rng(0)
    f = rng.normal(0, 0.05, n) + (0.0 if flat else 5.0 * x[:n])
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("time_s,displacement_mm,force_N\n")
        for row in zip(t[:n], x[:n], f):
            fh.write("%.3f,%.5f,%.4f\n" % row)
    return path


def test_fit_of_a_run_file_is_indexed_in_its_folders_catalog(plain_csv, tmp_path, capsys):
    from foamlab.importers import load_run
    from foamlab.storage.catalog import Catalog
    from foamlab.storage.runfile import write_run_file

    run_path = write_run_file(tmp_path / "run-001.csv", load_run(plain_csv))
    Catalog.for_folder(tmp_path).close()                 # the folder has a catalog
    assert main(["fit", str(run_path), "--orders", "1,1,7"]) == 0
    assert "catalog" in capsys.readouterr().out
    with Catalog(tmp_path / "catalog.sqlite") as catalog:
        fits = catalog.fits(run_path)
    assert len(fits) == 1 and fits[0]["json_path"].endswith("run-001.fit.json")
    assert fits[0]["rmse"] == pytest.approx(json.loads((tmp_path / "run-001.fit.json").read_text())["rmse"])
