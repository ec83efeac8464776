"""What the window says about a run that ended: one line, its colour, and the data-quality
flags that go with it (plain words, with what they mean for the results)."""

from __future__ import annotations

from dataclasses import dataclass

from foamlab.gui.forms import ERROR_STYLE
from foamlab.pipeline import schedule_gaps

WARNING_STYLE = "color: #9A5B00; font-weight: bold;"
OK_STYLE = ""


@dataclass(frozen=True)
class Flag:
    """A data-quality problem: a short name, and what it means for the results."""

    name: str
    meaning: str


def missed_flag(n_samples: int, missed: int) -> Flag | None:
    _, name = schedule_gaps(n_samples, missed)     # pipeline.AfterRun's flag
    if not name:
        return None
    return Flag(name,
                "the machine did not answer in time: the curves have gaps, and the fit and the method's "
                "results may not describe the specimen; test it again.")


def end_message(status: str, reason: str, n_samples: int, missed: int, where: str) -> tuple[str, str]:
    """The run's last word and its style: red when aborted, amber when finished with gaps."""
    if status != "finished":
        return (f"Run aborted: {reason or 'no reason given'}. {n_samples} samples kept. Data: {where}",
                ERROR_STYLE)
    flag = missed_flag(n_samples, missed)
    if flag is not None:
        return f"Run finished with gaps: {flag.name}; {flag.meaning} Data: {where}", WARNING_STYLE
    return f"Run finished: {n_samples} samples ({missed} missed). Data: {where}", OK_STYLE
