"""Run files (written as acquired, crash-safe, readable without foamlab) and the catalog."""

from __future__ import annotations

import json
import os
import selectors
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from foamlab import FoamlabError
from foamlab.cli import main
from foamlab.importers import load_run
from foamlab.rundata import RunData, Specimen
from foamlab.storage import runfile
from foamlab.storage.catalog import Catalog, data_dir, sidecar_path
from foamlab.storage.runfile import RunWriter, read_run_file, write_run_file

REPO = Path(__file__).resolve().parent.parent

HEADER = {
    "method": "paper-3cycle",
    "specimen": Specimen("PU-45 A", 72.5, 100.0, 100.0),
    "machine": "sim-modbus-tcp",
    "started_at": "2025-03-01T10:00:00+01:00",
    "sampling_hz": 50,
    "speedup": 20.0,                       # unknown keys are free metadata
    "metadata": {"operator": "Anna: line 1\nline 2", "limits": {"force_N": 450.0}, "ok": True},
}


def _sample(i: int) -> tuple[float, float, float, float]:
    t = i / 50.0
    return t, 0.1 * t + 1e-7 * i, 3.0 * np.sin(t) + 0.001 * i, 1.0 + (i % 7) / 10.0


def test_run_file_round_trip_and_self_description(tmp_path):
    path = tmp_path / "run.csv"
    with RunWriter(path, HEADER) as writer:
        for i in range(200):
            writer.write_sample(*_sample(i))
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    assert lines[0] == "# foamlab run file v1"
    assert "# method: paper-3cycle" in lines
    assert "# specimen_height_mm: 72.5" in lines
    assert any(ln.startswith("# software: foamlab ") for ln in lines)
    assert "# meta.speedup: 20.0" in lines
    assert lines[lines.index("time_s,displacement_mm,force_N,rtt_ms") + 1].startswith("0.0,0.0,0.0,1.0")
    assert lines[-1] == "# status: finished"

    # without foamlab: pandas (and so a spreadsheet) reads the table
    frame = pd.read_csv(path, comment="#")
    assert list(frame.columns) == ["time_s", "displacement_mm", "force_N", "rtt_ms"]
    assert len(frame) == 200
    expected = np.array([_sample(i) for i in range(200)])
    assert np.array_equal(frame.to_numpy(), expected)       # repr(): exact round trip

    run = read_run_file(path)
    assert run.method == "paper-3cycle" and run.machine == "sim-modbus-tcp"
    assert run.specimen == Specimen("PU-45 A", 72.5, 100.0, 100.0)
    assert run.started_at == "2025-03-01T10:00:00+01:00" and run.finished_at
    assert run.status == "finished" and run.abort_reason == ""
    assert run.metadata["operator"] == "Anna: line 1\nline 2"     # JSON keeps it on one line
    assert run.metadata["limits"] == {"force_N": 450.0} and run.metadata["ok"] is True
    assert run.metadata["speedup"] == 20.0 and run.metadata["sampling_hz"] == "50"
    assert run.metadata["extra_columns"] == ["rtt_ms"]
    assert np.array_equal(run.force_N, expected[:, 2])
    assert load_run(path).metadata["format"] == "foamlab run file"


def test_aborted_run_keeps_reason(tmp_path):
    path = tmp_path / "aborted.csv"
    writer = RunWriter(path, HEADER)
    for i in range(10):
        writer.write_sample(*_sample(i)[:3])            # extra column left empty
    writer.finish("aborted", "force limit 450 N exceeded\n(at 12.3 mm)")
    writer.finish("finished")                            # idempotent: first call wins
    run = read_run_file(path)
    assert run.status == "aborted"
    assert run.abort_reason == "force limit 450 N exceeded (at 12.3 mm)"
    assert len(run) == 10
    assert pd.read_csv(path, comment="#")["rtt_ms"].isna().all()


def test_exception_inside_writer_context_marks_aborted(tmp_path):
    path = tmp_path / "boom.csv"
    with pytest.raises(RuntimeError):
        with RunWriter(path, HEADER) as writer:
            writer.write_sample(*_sample(0))
            writer.write_sample(*_sample(1))
            raise RuntimeError("driver lost")
    run = read_run_file(path)
    assert run.status == "aborted" and "driver lost" in run.abort_reason


def test_never_overwrites_and_rejects_bad_columns(tmp_path):
    path = tmp_path / "run.csv"
    RunWriter(path, HEADER).finish()
    with pytest.raises(FoamlabError, match="already exists"):
        RunWriter(path, HEADER)
    with pytest.raises(ValueError):
        RunWriter(tmp_path / "other.csv", HEADER, columns=("t", "x", "f"))


def test_fsync_is_rate_limited(tmp_path, monkeypatch):
    calls = []
    real_fsync = os.fsync
    monkeypatch.setattr(runfile.os, "fsync", lambda fd: (calls.append(fd), real_fsync(fd)))
    writer = RunWriter(tmp_path / "run.csv", HEADER, fsync_interval_s=3600)
    for i in range(2000):
        writer.write_sample(*_sample(i))
    assert len(calls) == 1                 # the header only; every line still flushed
    assert len(pd.read_csv(writer.path, comment="#")) == 2000
    writer.finish()
    assert len(calls) == 2                 # and at close


_CHILD = """
import sys
sys.path.insert(0, {repo!r})
from tests.test_storage import HEADER, _sample
from foamlab.storage.runfile import RunWriter
writer = RunWriter({path!r}, HEADER)
i = 0
while True:
    writer.write_sample(*_sample(i))
    print(i, flush=True)               # reported only after write_sample returned
    i += 1
"""


@pytest.mark.timeout(60)
def test_killed_writer_loses_nothing_written(tmp_path):
    path = tmp_path / "killed.csv"
    child = subprocess.Popen([sys.executable, "-c", _CHILD.format(repo=str(REPO), path=str(path))],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    last = -1
    try:
        sel = selectors.DefaultSelector()
        sel.register(child.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + 30
        while last < 3000:
            if time.monotonic() > deadline or not sel.select(timeout=max(0.0, deadline - time.monotonic())):
                pytest.fail(f"writer child reported nothing in time: {child.stderr.read()[:500]}")
            line = child.stdout.readline()
            if not line:
                pytest.fail(f"writer child died: {child.stderr.read()[:500]}")
            last = int(line)
        child.send_signal(signal.SIGKILL)
    finally:
        if child.poll() is None:
            child.kill()
        child.wait(timeout=10)
    assert child.returncode == -signal.SIGKILL

    run = load_run(path)
    assert run.status == "aborted" and "interrupted" in run.abort_reason
    assert len(run) >= last + 1            # every sample reported as written is there
    expected = np.array([_sample(i) for i in range(len(run))])
    assert np.array_equal(run.time_s, expected[:, 0])
    assert np.array_equal(run.displacement_mm, expected[:, 1])
    assert np.array_equal(run.force_N, expected[:, 2])
    assert len(pd.read_csv(path, comment="#")) >= last + 1


def test_partial_last_line_of_an_unfinished_run_is_dropped(tmp_path):
    path = tmp_path / "partial.csv"
    writer = RunWriter(path, HEADER)
    for i in range(5):
        writer.write_sample(*_sample(i))
    writer._file.write("0.1,0.0")       # the sample in flight when the process died
    writer._file.flush()
    run = read_run_file(path)
    assert len(run) == 5
    assert run.metadata["dropped_partial_line"] == len(path.read_text().splitlines())
    # a finished file with a truncated line is malformed, not a crash
    bad = tmp_path / "bad.csv"
    complete = path.read_text().splitlines()[:-1]
    bad.write_text("\n".join(complete + ["# status: finished", "0.2,0.1"]))
    with pytest.raises(FoamlabError, match="truncated last line"):
        read_run_file(bad)


def test_write_run_file_round_trip(tmp_path):
    t = np.linspace(0, 10, 501)
    run = RunData(t, np.abs(np.sin(t)) * 3, np.abs(np.sin(t)) * 20, Specimen("S", 50.0),
                  method="m", machine="sim", started_at="2025-01-01T00:00:00+00:00",
                  metadata={"seed": 3})
    path = write_run_file(tmp_path / "sim.csv", run)
    back = load_run(path)
    assert np.array_equal(back.time_s, run.time_s) and np.array_equal(back.force_N, run.force_N)
    assert back.specimen.height_mm == 50.0 and back.metadata["seed"] == 3
    assert back.status == "finished"


def test_read_run_file_refuses_other_files(tmp_path):
    p = tmp_path / "plain.csv"
    p.write_text("time_s,displacement_mm,force_N\n0,0,0\n1,1,1\n")
    with pytest.raises(FoamlabError, match="not a foamlab run file"):
        read_run_file(p)


# --------------------------------------------------------------------------- catalog

def _make_run(folder: Path, name: str, started: str, n: int = 20) -> Path:
    header = dict(HEADER, started_at=started, specimen=Specimen(name))
    with RunWriter(folder / f"{name}.csv", header) as writer:
        for i in range(n):
            writer.write_sample(*_sample(i))
    return folder / f"{name}.csv"


def test_catalog_rebuild_and_sync(tmp_path):
    data = tmp_path / "data"
    (data / "2025").mkdir(parents=True)
    a = _make_run(data, "A", "2025-03-01T10:00:00+01:00", n=30)
    b = _make_run(data / "2025", "B", "2025-03-02T10:00:00+01:00", n=40)
    sidecar_path(a, "fit").write_text(json.dumps({"rmse": 0.42, "parameters": {}}))
    sidecar_path(a, "diagnosis").write_text(json.dumps({"verdict": "cycle_softening"}))
    (data / "export.csv").write_text("time_s,displacement_mm,force_N\n0,0,0\n1,1,1\n")  # not a run
    (data / "broken.csv").write_text("# foamlab run file v1\ntime_s,displacement_mm,force_N\n0,x,0\n")

    with Catalog(data / "catalog.sqlite") as catalog:
        report = catalog.rebuild(data)
        assert (report.runs, report.fits, report.diagnoses) == (2, 1, 1)
        assert [Path(p).name for p, _ in report.skipped] == ["broken.csv"]
        runs = catalog.runs()
        assert [r.specimen for r in runs] == ["B", "A"]           # newest first
        assert runs[1].rmse == 0.42 and runs[1].verdict == "cycle_softening"
        assert runs[0].n_samples == 40 and runs[0].status == "finished"
        assert runs[0].method == "paper-3cycle" and runs[0].machine == "sim-modbus-tcp"
        assert catalog.fits(a)[0]["json_path"] == str(sidecar_path(a, "fit").resolve())
        assert catalog._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"

        # files are the truth: a deleted run and a new one are seen by sync
        b.unlink()
        c = _make_run(data, "C", "2025-03-03T10:00:00+01:00")
        report = catalog.sync(data)
        assert report.removed == 1 and report.runs == 1
        assert [r.specimen for r in catalog.runs()] == ["C", "A"]
        assert catalog.sync(data).runs == 0                     # unchanged files are not re-read
        catalog.add_fit(c, tmp_path / "elsewhere.json", rmse=1.5, created="2025-03-04T00:00:00")
        assert catalog.runs()[0].rmse == 1.5

    # another process (here: connection) sees the same index
    rows = sqlite3.connect(data / "catalog.sqlite").execute("SELECT count(*) FROM runs").fetchone()
    assert rows[0] == 2


def test_catalog_for_folder_and_default_location(tmp_path, monkeypatch):
    monkeypatch.setenv("FOAMLAB_DATA", str(tmp_path / "lab"))
    assert data_dir() == tmp_path / "lab"
    monkeypatch.delenv("FOAMLAB_DATA")
    assert data_dir() == Path.home() / "foamlab-data"
    _make_run(tmp_path, "X", "2025-01-01T00:00:00")
    with Catalog.for_folder(tmp_path) as catalog:
        assert [r.specimen_label for r in catalog.runs()] == ["X"]
    assert (tmp_path / "catalog.sqlite").exists()


def test_catalog_cli(tmp_path, capsys, monkeypatch):
    _make_run(tmp_path, "R1", "2025-01-01T00:00:00")
    assert main(["catalog", "rebuild", "--data", str(tmp_path)]) == 0
    assert "1 runs, 0 fits, 0 diagnoses" in capsys.readouterr().out
    monkeypatch.setenv("FOAMLAB_DATA", str(tmp_path))
    assert main(["catalog"]) == 0
    out = capsys.readouterr().out
    assert "R1" in out and "paper-3cycle" in out
    assert main(["catalog", "list", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["specimen"] == "R1"
    assert main(["catalog", "list", "--data", str(tmp_path / "missing")]) == 2
    assert "no such data folder" in capsys.readouterr().err


def test_corrupt_catalog_is_a_clear_error(tmp_path):
    bad = tmp_path / "catalog.sqlite"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(FoamlabError, match="catalog rebuild"):
        Catalog(bad)
