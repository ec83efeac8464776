"""The held-out rule's margin: a gain within the noise's reach does not count, and the held-out blocks."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.signal import lfilter
from scipy.stats import norm

from foamlab.analysis.heldout import HeldoutGain, folds, heldout_gain
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


def _held(series: list, residual: np.ndarray, in_sample: np.ndarray) -> SimpleNamespace:
    """A fit whose held-out prediction errors (what heldout_rmse stores) and in-sample residuals
    are already known."""
    return SimpleNamespace(heldout_rmse=float(np.sqrt(np.mean(residual ** 2))), heldout_refit="base re-estimated",
                           heldout_residual=residual, model=SimpleNamespace(series=series),
                           solution=SimpleNamespace(used_residuals=[in_sample]))


def _ar_noise(rng: np.random.Generator, n: int, sigma: float = 0.15, phi: float = 0.6) -> np.ndarray:
    """AR(1) noise, correlated over a few samples as a filtered load cell's is."""
    return lfilter([np.sqrt(1 - phi ** 2)], [1, -phi], rng.normal(0, sigma, n))


def test_an_extension_that_only_moves_the_prediction_passes_as_often_as_its_margin_allows():
    # the model extended is right; the extension predicts the held-out samples off by a smooth
    # sliver (0.005 N against 0.15 N of noise correlated over a few samples). Its gain is noise
    # less the sliver squared, so it passes the margin of z standard errors in at most the normal
    # tail beyond z of runs: 13.5 % at the default 1 (1.5 % at 2); a standard error that took the
    # noise as white lets 26 % pass at 1 (12.5 % at 2). Seeds 0-399 fixed before the rate was looked at.
    n, series, t = 900, [_Series(900)], np.arange(900)
    z = DEFAULT.heldout_margin_z
    passed = 0
    for seed in range(400):
        rng = np.random.default_rng(seed)
        noise, in_sample = _ar_noise(rng, n), _ar_noise(rng, n)
        deviation = 0.005 * np.sin(2 * np.pi * t / rng.uniform(40, 300) + rng.uniform(0, 6.3))
        passed += heldout_gain(_held(series, noise, in_sample), _held(series, noise - deviation, in_sample), z).passed
    tail = norm.sf(z)
    assert passed / 400 <= tail + 2 * np.sqrt(tail * (1 - tail) / 400)


def test_a_true_effect_in_a_few_blocks_passes_and_surer_the_larger_it_is():
    # the effect shows in six short stretches (turns) of 900 samples, the model extended misses it
    # and the extension has it: its noise is the gain's, its shape is not, so a larger effect
    # stands further out (4.8 -> 7.4 standard errors; the spread of the gain block to block, which
    # held the shape, saturated: 3.3 -> 3.5; docs/analysis.md, "Held-out blocks")
    n, series = 900, [_Series(900)]
    shape = np.zeros(n)
    for turn in (100, 250, 400, 550, 700, 850):
        shape[turn - 5:turn + 5] = np.hanning(10)
    rng = np.random.default_rng(11)
    noise, in_sample = _ar_noise(rng, n), _ar_noise(rng, n)
    z = [(g.before_rmse - g.after_rmse) / g.gain_se for g in
         (heldout_gain(_held(series, noise + a * shape, in_sample), _held(series, noise, in_sample), 1.0)
          for a in (0.3, 0.6))]
    assert z[0] > 3 and z[1] > z[0] + 2
