"""The validation harness: how accurate is each method, where does it fail, and did a
change make it worse? (docs/validation.md)

``omnivalidate DATASET --out REPORT_DIR`` (:mod:`validation.cli`) scores every
omniflow variant and the OpenCV baselines on any dataset in the omnisim contract.
Modules: :mod:`~validation.sampling` (truth at sub-pixel points),
:mod:`~validation.metrics`, :mod:`~validation.motion` (truth of derived quantities
from the poses), :mod:`~validation.baselines`, :mod:`~validation.runner`,
:mod:`~validation.summary`, :mod:`~validation.report`, :mod:`~validation.thresholds`
and :mod:`~validation.calibrate` (the reviewed thresholds file and how its bounds are
measured), :mod:`~validation.synthdata` (closed-form datasets, no renderer),
:mod:`~validation.oracle` (a perfect method, to test the harness itself).
"""
