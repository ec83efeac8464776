"""Diagnosis settings the tests share."""

from __future__ import annotations

from dataclasses import replace

from foamlab.diagnosis.settings import DEFAULT

#: The verdict, the findings and the linearised detection limits, without the limits' check by
#: identification refits (limits.checked: 10-20 refits, two thirds of a clean run's diagnosis). The
#: check runs after the verdict, only where nothing was found, and changes the limits alone: the
#: tests whose subject is the verdict diagnose with this (~250 of the suite's ~2 800 worker-seconds,
#: docs/benchmarks.md). tests/test_detection_limits.py and the end-to-end tests (the window, the
#: pipeline, the report, the command line) diagnose with the check, as a user does.
VERDICT_ONLY = replace(DEFAULT, limit_injections=0)
