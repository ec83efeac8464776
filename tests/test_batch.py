"""`foamlab batch` / foamlab.batch.process: an archive fitted and diagnosed on Dask distributed.

One LocalCluster of 2 worker processes serves the module. Runs are short (3 cycles at
200 mm/min sampled at 2 Hz: 210 samples, ~1 s of fit and diagnosis each).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import pandas as pd
import pytest

from foamlab import cli
from foamlab.batch import BatchRow, find_runs, process, write_summary
from foamlab.batch import engine
from foamlab.batch.store import Destination
from foamlab.batch.summary import odd_ones_out
from foamlab.diagnosis import CAUSES
from foamlab.diagnosis.synthetic import hidden_effect_run
from foamlab.storage.catalog import Catalog
from foamlab.storage.runfile import write_run_file

REPO = Path(__file__).resolve().parent.parent
N_RUNS = 10                              # an archive of ten runs in two folders (was 20: 40 s of the suite)
SPEED = 200.0                            # mm/min: 3 cycles in 105 s, 210 samples at 2 Hz
BROKEN = {"broken_header.csv": "hello,world\n1,2\n",
          "broken_value.csv": "time_s,displacement_mm,force_N\n0,0,0\n0.5,0.1,x\n",
          "empty.txt": ""}


def _effects(i: int) -> dict | None:
    """Series S1 (odd i) mostly softens from cycle to cycle, series S0 (even i) does not, but for one."""
    return {"cycle_softening": 0.05} if (i % 2 == 1 and i % 6 != 5) or i == 8 else None


def _verdict(rows, i: int) -> str:
    return next(r.verdict for r in rows if Path(r.file).stem == f"run{i:02d}")


def _run(i: int):
    run = hidden_effect_run(_effects(i), speed_mm_min=SPEED, sampling_hz=2.0, seed=i)
    run.specimen.label, run.started_at = f"S{i % 2}-{i:02d}", f"2026-01-{i + 1:02d}T10:00:00+00:00"
    return run


def _write_plain_csv(path: Path, run) -> Path:
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(f"# specimen_label: {run.specimen.label}\n# started_at: {run.started_at}\n"
                 "time_s,displacement_mm,force_N\n")
        for t, x, f in zip(run.time_s.tolist(), run.displacement_mm.tolist(), run.force_N.tolist()):
            fh.write(f"{t!r},{x!r},{f!r}\n")
    return path


@pytest.fixture(scope="module")
def cluster():
    from distributed import Client, LocalCluster

    # Worker processes import foamlab from this checkout too (cwd is not on their sys.path).
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      env={"PYTHONPATH": path}, silence_logs=40) as c, Client(c) as client:
        client.wait_for_workers(2, timeout=120)
        yield client


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("archive")
    for i in range(N_RUNS):
        folder = root / f"series{i % 2}"      # folders are walked
        folder.mkdir(exist_ok=True)
        _write_plain_csv(folder / f"run{i:02d}.csv", _run(i))
    for name, text in BROKEN.items():
        (root / name).write_text(text, encoding="utf-8")
    return root


@pytest.fixture(scope="module")
def first(archive, cluster, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "results.csv"
    before = sorted(p.relative_to(archive) for p in archive.rglob("*"))
    table = process([archive], cluster, out=out)
    assert sorted(p.relative_to(archive) for p in archive.rglob("*")) == before   # nothing beside vendor files
    return table, out


@pytest.mark.timeout(300)     # the module's cluster and batch (30-117 s) are set up in it
def test_ten_runs_and_three_broken_files_are_ten_results_and_three_error_rows(first, archive):
    table, out = first
    assert len(table) == N_RUNS + len(BROKEN)
    rows = [BatchRow.from_record(r) for r in table.to_dict("records")]
    good = [r for r in rows if not r.error]
    bad = [r for r in rows if r.error]
    assert len(good) == N_RUNS and all(r.verdict in (*CAUSES, "none", "unexplained") for r in good)
    assert {Path(r.file).name for r in bad} == set(BROKEN)
    assert all(r.error_kind == "read" and "\n" not in r.error and Path(r.file).name in r.error for r in bad)
    for r in good:
        assert r.format == "plain CSV" and r.cycles == 3 and r.samples == len(_run(0)) and r.orders == "3,3,7"
        assert r.form in ("causal", "paper")
        assert r.rmse > 0 and r.noise > 0 and r.elapsed_s > 0 and r.parameters["k1"] != 0
        assert r.sha256 == engine.sha256_of(Path(r.file))
        assert r.effect == ("" if r.verdict == "none" else r.verdict)
        if r.verdict in CAUSES:
            assert r.gain > 1 and r.rmse_before > r.rmse_after
    # softening is named, and only on softened runs. How many of the 5 it names is not asked here:
    # on these 210-sample runs the held-out check decides two of them by the CPU (>= 4 of 5 in earlier CI on AVX2,
    # 3 of 5 on AVX-512, where it refuses Delta BIC 264 and 41; issue 27 item 4, docs/analysis.md)
    named = {i for i in range(N_RUNS) if _verdict(good, i) == "cycle_softening"}
    assert named and all(_effects(i) for i in named), named
    # the output file holds the table; the journal is gone once it is written
    again = pd.read_csv(out)
    assert list(again["sha256"]) == list(table["sha256"]) and not out.with_name(out.name + ".journal.jsonl").exists()
    # every run read is in the batch's catalog, its fit and diagnosis JSON beside the output
    with Catalog(out.parent / "catalog.sqlite") as catalog:
        indexed = {Path(r.path).name: r for r in catalog.runs()}
    assert set(indexed) == {Path(r.file).name for r in good}
    assert all(indexed[Path(r.file).name].verdict == r.verdict for r in good)
    assert len(list((out.parent / "results.files").glob("*.diagnosis.json"))) == N_RUNS


@pytest.mark.timeout(60)
def test_verdicts_equal_those_of_foamlab_diagnose(first, capsys):
    table, _ = first
    soft = table[table["verdict"] == "cycle_softening"]["file"].tolist()[:1]
    plain = table[table["verdict"] == "none"]["file"].tolist()[:1]
    for f in soft + plain:
        assert cli.main(["diagnose", f, "--json", "--no-store"]) == 0
        verdict = json.loads(capsys.readouterr().out)["verdict"]
        assert verdict == table.loc[table["file"] == f, "verdict"].item(), f


@pytest.mark.timeout(60)
def test_a_rerun_skips_current_results_and_redoes_a_changed_file(first, archive, cluster):
    table, out = first
    new = []
    again = process([archive], cluster, out=out, on_row=lambda row, done, total: new.append(row.file))
    assert new == []                          # every result is current: nothing submitted
    assert list(again["sha256"]) == list(table["sha256"]) and list(again["verdict"].fillna("")) == \
        list(table["verdict"].fillna(""))
    changed = archive / "series0" / "run00.csv"
    other = _run(0)
    other.force_N += 0.01
    _write_plain_csv(changed, other)
    third = process([archive], cluster, out=out, on_row=lambda row, done, total: new.append(row.file))
    assert new == [str(changed)]
    assert third.loc[third["file"] == str(changed), "sha256"].item() == engine.sha256_of(changed)


def test_the_journal_of_an_interrupted_batch_is_its_results(first, tmp_path):
    """A batch that died left only its journal: the next one takes every result from it (no
    cluster is even started: nothing is left to do) and writes the table."""
    table, _ = first
    done = table[table["file"].str.contains("series1")]
    for f in done["file"]:
        shutil.copy(f, tmp_path / Path(f).name)
    out = tmp_path / "out" / "again.csv"
    out.parent.mkdir()
    journal = out.with_name(out.name + ".journal.jsonl")
    lines = [json.dumps(BatchRow.from_record(r).to_record()) for r in done.to_dict("records")]
    journal.write_text("\n".join(lines) + "\n" + lines[0][:40], encoding="utf-8")   # + a torn last line
    again = process([tmp_path], None, out=out, scheduler="tcp://127.0.0.1:9")        # would fail to connect
    assert list(again["verdict"]) == list(done["verdict"]) and list(again["sha256"]) == list(done["sha256"])
    assert set(again["file"]) == {str(tmp_path / Path(f).name) for f in done["file"]}
    assert out.is_file() and not journal.exists()


@pytest.mark.timeout(60)
def test_cli_on_a_running_cluster_writes_the_table_the_summary_and_sidecars_beside_run_files(
        archive, cluster, tmp_path, capsys):
    lab = tmp_path / "lab"
    lab.mkdir()
    shutil.copy(archive / "broken_value.csv", tmp_path / "vendor.csv")
    run_file = write_run_file(lab / "own.csv", _run(6))
    out = tmp_path / "res.parquet"
    code = cli.main(["batch", str(tmp_path / "vendor.csv"), str(lab), "--scheduler", cluster.scheduler_info()["address"],
                     "--out", str(out)])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "2 runs: 1 result, 1 error row" in printed.out and "batch" not in printed.err   # no bar on a pipe
    table = pd.read_parquet(out)
    assert sorted(table["format"]) == ["", "foamlab run file"] and sorted(table["error_kind"]) == ["", "read"]
    # a foamlab run file: the pipeline's sidecars beside it, indexed in its folder's catalog
    assert run_file.with_name("own.fit.json").is_file() and run_file.with_name("own.diagnosis.json").is_file()
    with Catalog(lab / "catalog.sqlite") as catalog:
        assert [r.verdict for r in catalog.runs()] == table.loc[table["format"] == "foamlab run file",
                                                                "verdict"].tolist()
    page = (tmp_path / "res.summary.html").read_text(encoding="utf-8")
    assert page.count("<img") >= 3 and "Runs unlike their series" in page


@pytest.mark.timeout(120)
def test_a_worker_killed_mid_batch_loses_nothing_and_its_runs_are_retried(archive, cluster, tmp_path):
    runs = sorted((archive / "series0").glob("*.csv"))[1:6]
    for f in runs:
        shutil.copy(f, tmp_path / f.name)
    out = tmp_path / "out" / "killed.parquet"
    pids = cluster.run(os.getpid)
    seen: list[BatchRow] = []
    killed: dict[str, list] = {}

    def kill_a_busy_worker(row, done, total):
        seen.append(row)
        if len(seen) >= 2 and not killed:     # two results are in: kill a worker that is running a run
            busy = {w: keys for w, keys in cluster.processing().items() if keys}
            if not busy:
                return
            worker, keys = next(iter(busy.items()))
            killed.update(journal=_journal(out), keys=list(keys), worker=worker)
            os.kill(pids[worker], signal.SIGKILL)

    table = process([tmp_path], cluster, out=out, on_row=kill_a_busy_worker)
    assert killed, "no worker was busy after the second result"
    assert len(killed["journal"]) >= 2                      # the results before the kill were on disk
    assert len(table) == len(runs) and (table["error"] == "").all(), table["error"].tolist()
    assert set(table["file"]) == {str(tmp_path / f.name) for f in runs}
    for record in killed["journal"]:                        # ... and are the batch's results
        assert table.loc[table["sha256"] == record["sha256"], "verdict"].item() == record["verdict"]
    assert pids[killed["worker"]] not in cluster.run(os.getpid).values()   # (its nanny starts another)


def _journal(out: Path) -> list[dict]:
    path = out.with_name(out.name + ".journal.jsonl")
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def test_the_summary_names_the_runs_unlike_their_series(first, tmp_path):
    table, _ = first
    page = write_summary(table, tmp_path / "s.html").read_text(encoding="utf-8")
    odd = odd_ones_out(table)
    done = table[table["verdict"] != ""]
    usual = {}                                              # series -> the verdict of more than half its runs
    for series in ("S0", "S1"):
        counts = done[done["specimen"].str.startswith(series)]["verdict"].value_counts()
        usual[series] = counts.index[0] if counts.iloc[0] > counts.sum() / 2 else None
    expected = {f for f, v, s in zip(done["file"], done["verdict"], done["specimen"])
                if usual[s[:2]] is not None and v != usual[s[:2]]}
    assert usual["S0"] == "none" and set(odd["file"]) == expected and expected   # run08 softens in S0
    assert all(Path(f).name in page for f in expected)
    for verdict, n in table.loc[table["verdict"] != "", "verdict"].value_counts().items():
        assert f"<td>{verdict}</td><td>{n}</td>" in page
    assert page.count("<img") == 3


def test_folders_are_walked_each_file_once_leaving_out_what_the_batch_writes(archive, tmp_path):
    files = find_runs([archive, archive / "series0" / "run02.csv"])
    assert len(files) == N_RUNS + len(BROKEN) and len(set(files)) == len(files)
    for name in ("run.csv", "res.csv", "res.files/run-0123.csv", ".hidden/run.csv", "notes.md"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text("time_s,displacement_mm,force_N\n")
    dest = Destination.choose(tmp_path / "res.csv")
    assert find_runs([tmp_path], dest.written()) == [tmp_path / "run.csv"]


@pytest.mark.parametrize("argv,message", [
    (["batch", "/no/such/archive"], "no such file or folder"),
    (["batch", "{archive}", "--out", "{tmp}/res.txt"], ".csv or a .parquet"),
    (["batch", "{archive}", "--workers", "0"], "need at least 1"),
    (["batch", "{archive}", "--workers", "2", "--scheduler", "tcp://127.0.0.1:9"], "own workers"),
    (["batch", "{archive}", "--scheduler", "tcp://127.0.0.1:9", "--out", "{tmp}/r.csv"], "cannot connect"),
    (["batch"], "required"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, archive, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(engine, "CONNECT_TIMEOUT_S", 2.0)
    argv = [a.replace("{archive}", str(archive)).replace("{tmp}", str(tmp_path)) for a in argv]
    try:
        code = cli.main(argv)
    except SystemExit as exc:                 # argparse's own errors (one line too: foamlab.cli)
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
