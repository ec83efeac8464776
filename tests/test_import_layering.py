"""The import layering of the design notes, kept by import-linter.

"Dependencies point one way: drivers knows nothing of foamlab; simulator uses
foamlab's model; foamlab uses drivers through a small machine interface" - and no
import cycles anywhere. The contracts are in pyproject.toml ([tool.importlinter]);
`lint-imports --no-cache` checks them by hand. A broken contract fails this test
with import-linter's report and, for cycles, every cycle spelled out import by import.
"""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Both run in a child whose cwd (the checkout) comes first on sys.path, so the code
# analysed is this checkout's whatever foamlab the environment has installed.
_LINT = """
import sys
from importlinter.cli import lint_imports
sys.exit(lint_imports(config_filename="pyproject.toml", no_cache=True, no_logo=True))
"""

# import-linter names the imports that would break each cycle; this lists the cycles:
# every pair of sibling modules/packages that import each other, directly or not.
_CYCLES = """
import itertools
import grimp

g = grimp.build_graph("foamlab", "drivers", "simulator", cache_dir=None)

def spelled(chain):
    hops = []
    for importer, imported in zip(chain, chain[1:]):
        lines = sorted({d["line_number"] for d in g.get_import_details(importer=importer, imported=imported)})
        hops.append(f"{importer} -> {imported} (line {', '.join(map(str, lines))})")
    return "; ".join(hops)

for package in sorted(m for m in g.modules if g.find_children(m)):
    for a, b in itertools.combinations(sorted(g.find_children(package)), 2):
        there = g.find_shortest_chain(a, b, as_packages=True)
        back = there and g.find_shortest_chain(b, a, as_packages=True)
        if back:
            print(f"{a} <-> {b}:\\n    {spelled(there)}\\n    {spelled(back)}")
"""


def _child(code: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, COLUMNS="200", PYTHONPATH="")
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=240)


def test_import_contracts_are_kept():
    lint = _child(_LINT)
    if lint.returncode != 0:
        cycles = _child(_CYCLES)
        listing = cycles.stdout.strip() or "(none between siblings)" + cycles.stderr[-2000:]
        raise AssertionError(f"import-linter: contracts broken\n{lint.stdout}{lint.stderr}\n"
                             f"import cycles:\n{listing}")
    assert "0 broken" in lint.stdout, lint.stdout
