"""The held-out rule's margin: a gain within its block-to-block spread does not count."""

from __future__ import annotations

import numpy as np

from foamlab.analysis.heldout import HeldoutGain, folds
from foamlab.diagnosis.settings import DEFAULT


def test_a_gain_within_its_spread_is_refused_and_one_beyond_it_passes():
    z = DEFAULT.heldout_margin_z
    assert z > 0                                     # the default asks for more than any gain
    assert not HeldoutGain(0.160, 0.159, 0.002, z).passed      # 0.5 standard errors
    assert HeldoutGain(0.160, 0.150, 0.002, z).passed          # 5 standard errors
    assert not HeldoutGain(0.160, 0.161, 0.002, 0.0).passed    # no gain at all, whatever the margin
    assert HeldoutGain(0.160, 0.159, float("nan"), z).passed   # too few blocks for a spread: any gain


class _Series:
    def __init__(self, n: int, off: np.ndarray | None = None):
        self.n, self.no_contact = n, off

    def __len__(self) -> int:
        return self.n


def test_every_block_is_held_out_once_and_the_contact_edges_never():
    off = np.zeros(600, bool)
    off[100:140] = True                              # the plate off the specimen for 40 samples
    keeps = folds([_Series(600, off)])
    held_out = np.sum([~k[0] for k in keeps], axis=0)
    edges = np.array([98, 99, 100, 101, 138, 139, 140, 141])
    assert set(held_out[np.setdiff1d(np.arange(600), [100, 101, 138, 139])]) == {1}
    assert not held_out[[100, 101, 138, 139]].any()  # off-specimen samples next to contact stay in
    assert held_out[edges[[0, 1, 6, 7]]].all()       # samples in contact beside them are held out
