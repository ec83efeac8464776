"""The analysis core under identification and diagnosis: one preparation of a run, one fit.

- prepared.py: ``prepare(run) -> PreparedRun`` - segmentation, the model's labels, the
  displacement path and its corner nodes, the noise, the contact set measured, the
  decimated search rows and the ``Series`` every full fit uses; made once per run.
- path.py: the crosshead's path as the model sees it, and the samples it determines.
- basis.py: the model as linear columns (variable projection) with their derivatives.
- design.py: the base model extended by effects, contact set and zero, on one or more runs.
- solve.py: the fitting core (varpro on all samples; ``polish``), used by both.
- noise.py: the noise level (one definition), whiteness tests, prewhitening.
"""
