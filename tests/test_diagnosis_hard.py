"""Issue 16's hard pairs on runs foamlab never generated: tests/independent_model.py (its own
arithmetic, three cycles at 16 Hz, noise 0.15 N) with a cause hidden by tests/independent_effects.py
(sizes in its physical units: N/mm frame, N, ms). The effects at the issue's sizes the data hold are named,
clean runs give none.

Not here: regime A's 2 000 N/mm frame and 0.45 N friction (and B's 0.45 N friction). On those
runs even the model of the true structure, fitted from the true parameters, gains less than the
Delta BIC 10 a finding needs in most seeds (docs/analysis.md, "What one run holds of the hard
pairs"); benchmarks/bench_diagnosis.py --hard measures every row.
"""

from __future__ import annotations

import independent_effects as ie
import pytest
from diagnosis_support import VERDICT_ONLY

from foamlab.diagnosis import diagnose

CASES = [
    # regime, seed, effect, the verdict required. Seeds: the first two of each case's range, set
    # before looking. Regime A's lag at 50 ms sits at the detection limit (seeds 300-307: 2 of 8
    # under Delta BIC 10 or a held-out gain of 1e-5 N; benchmarks/bench_diagnosis.py --hard), so
    # the test asks for 100 ms, where seeds 300/301 give Delta BIC 240/125 and held-out gains of
    # 4.8/3.7 mN - far from the edge on any machine.
    ("A", 300, {"channel_lag": 100.0}, "channel_lag"),
    # 115af44-18b7afc placed three of its turns the other way (a lag misfits every turn) and
    # named cycle_softening; a turn is now placed alone only when it misfits more than the others
    ("A", 301, {"channel_lag": 100.0}, "channel_lag"),
    ("B", 300, {"channel_lag": 50.0}, "channel_lag"),
    ("B", 301, {"channel_lag": 50.0}, "channel_lag"),
    ("B", 300, {"machine_compliance": 1000.0}, "machine_compliance"),
    ("B", 301, {"machine_compliance": 2000.0}, "machine_compliance"),
    ("A", 300, {}, "none"),
    # a clean run where an early force (negative lag) fitted from several starts was named
    ("B", 302, {}, "none"),
]


def _case_id(case) -> str:
    regime, seed, effect, _ = case
    return f"{regime}-{seed}-{next(iter(effect), 'clean')}"


@pytest.mark.parametrize("regime,seed,effect,expected", CASES,
                         ids=[_case_id(c.values if hasattr(c, "marks") else c) for c in CASES])
def test_hard_pair_on_the_independent_generator_is_named(regime, seed, effect, expected):
    d = diagnose([ie.independent_run(regime, seed, effect)], settings=VERDICT_ONLY)
    assert d.verdict == expected, [(c.name, round(c.delta_bic, 1), c.reason) for c in d.tested[0]] if d.tested else d.verdict
