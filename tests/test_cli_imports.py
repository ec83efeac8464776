"""`foamlab --help` stays fast: building the parser imports no numerical or GUI library.

Each command imports what it needs when it runs (foamlab/cli.py); this checks the structure,
the timings are benchmarks/bench_cli_startup.py's.
"""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

HEAVY = ("scipy", "statsmodels", "pandas", "matplotlib", "PySide6", "pyqtgraph", "dask", "reportlab",
         "pymodbus", "numpy", "rich")

_CHILD = "import foamlab.cli as c; c.build_parser(); import sys; print(sorted(sys.modules))"


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return set(eval(out.stdout))  # noqa: S307 (a list of strings printed by the child)


def test_building_the_parser_imports_no_heavy_library():
    loaded = {name.split(".")[0] for name in _modules_after(_CHILD)}
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_the_child_sees_a_heavy_import():
    # the check above can fail: the same child notices a library a command module would import
    loaded = {name.split(".")[0] for name in _modules_after(_CHILD.replace("c.build_parser();",
                                                                           "c.build_parser(); import numpy;"))}
    assert "numpy" in loaded


def test_every_command_is_registered():
    from foamlab import cli

    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert sorted(sub.choices) == sorted(cli.COMMAND_MODULES)


def test_diagnose_help_names_the_whole_catalogue():
    # the help text lists the causes without importing the diagnosis: it must list them all
    from foamlab.commands.diagnose import EXAMPLES
    from foamlab.diagnosis.causes import CAUSES

    verdict = EXAMPLES.split("verdict:", 1)[1].split("'none'", 1)[0]
    assert set(re.findall(r"[a-z]+(?:_[a-z]+)+", verdict)) == set(CAUSES)


def test_a_bad_option_is_one_line(capsys):
    from foamlab import cli

    for argv in (["--no-such"], ["diagnose", "--no-such", "x"], ["show"]):
        try:
            cli.main(argv)
        except SystemExit as exc:
            assert exc.code == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "error:" in err, err
