"""The diagnosis's thresholds in one frozen object, passed explicitly (DEFAULT unless given).

Each value's reason and the measurement behind it: docs/settings.md. `foamlab diagnose
--full` prints the values a diagnosis used.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from foamlab.analysis.solve import SEARCH_SAMPLES


def _setting(default, meaning: str, **kw):
    return field(default=default, metadata={"meaning": meaning}, **kw)


@dataclass(frozen=True)
class DiagnosisSettings:
    """Acceptance rules (evidence.py), the residual map (residuals.py), the search's budget (core.py)."""

    # -- acceptance rules
    delta_bic_min: float = _setting(10.0, "a candidate improves the prewhitened BIC by more than this")
    effect_z_min: float = _setting(3.0, "its effect lies this many standard errors from zero")
    explained_share_min: float = _setting(0.5, "share of the structure above the noise a named cause explains")
    partial_share_min: float = _setting(0.1, "share a first-round cause explains to be reported as partial")
    heldout_margin_z: float = _setting(1.0, "its held-out gain exceeds this many standard errors of the noise "
                                            "in the gain (0: any gain)")
    pinned_fraction: float = _setting(0.01, "pinned: an effect within this share of its range of a non-zero limit")
    # -- where the residuals have structure
    score_threshold: float = _setting(4.0, "structure: a residual region this many standard errors off zero")
    x_bins: int = _setting(10, "displacement bins per half-cycle in the residual map")
    time_bins: int = _setting(30, "time bins per run in the residual map")
    # -- when to stop
    max_findings: int = _setting(3, "causes found on top of each other at most")
    near_noise: float = _setting(0.1, "white residuals within this of the noise variance end the search")
    at_noise: float = _setting(0.005, "any residuals within this of the noise variance end the search")
    # -- the search's budget
    heldout_candidates: int = _setting(3, "candidates (by Delta BIC) given the held-out check per round")
    joint_candidates: int = _setting(2, "candidates refitted with the base's alpha/beta free")
    full_candidates: int = _setting(2, "of those, carried to full resolution")
    pair_candidates: int = _setting(2, "pairs of causes fitted jointly where the findings do not explain the "
                                       "structure (the screen's best; 0: none)")
    decisive_chi2: float = _setting(100.0, "likelihood-ratio gain above which a candidate is not refitted "
                                           "from the fair comparison's base")
    multistart_samples: int = _setting(int(1.6 * SEARCH_SAMPLES), "samples per run a cause the base imitates "
                                                                  "is fitted on from several starts")
    deep_only_on_structure: bool = _setting(True, "restarts from identification and several starts (the search's "
                                                  "costly fits) only where the current model leaves structure or "
                                                  "a candidate clears delta_bic_min without them")
    multistart_reach: float = _setting(0.3, "several starts when its joint fit is within this fraction of "
                                            "the round's best Delta BIC")
    limit_injections: int = _setting(4, "identification refits that check the detection limit of a cause the base "
                                         "can take into its own terms, per sign it can take (0: the linearised "
                                         "limit alone)")
    # -- the machine
    workers: int = _setting(0, "processes the search's independent fits run on (0: every core this process may "
                               "use; the same results at any number)")

    def lines(self) -> list[str]:
        """`name = value  (meaning)`, one line each, in declaration order."""
        width = max(len(f.name) for f in fields(self))
        return [f"{f.name:<{width}} = {_shown(getattr(self, f.name)):<8} {f.metadata['meaning']}" for f in fields(self)]


def _shown(value) -> str:
    """A setting's value as `--full` prints it (a switch as true/false, a number as %g)."""
    return str(value).lower() if isinstance(value, bool) else f"{value:g}"


#: The values every diagnosis uses unless given others.
DEFAULT = DiagnosisSettings()
