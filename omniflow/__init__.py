"""Omni Flow (Spacek): optic flow and stereo of a coaxial conical-mirror rig.

Packages, from the base up (``tests/test_layout.py`` guards the order):

- :mod:`omniflow.conventions` axes, angle sense, pixel centres, units
- :mod:`omniflow.geometry` the rig, eq. (1)-(7), and its calibration
- :mod:`omniflow.paper` the paper's equations as written: DCT fit (17-18), polar
  edges (19-20), radial matching (5.2), the flow equation and eq. (16)
- :mod:`omniflow.fit` each unit's fitted series, the flow band, sampling at points
- :mod:`omniflow.matching` the robust radial matcher
- :mod:`omniflow.solve` the pooled solver and its extensions
- :mod:`omniflow.config`, :mod:`omniflow.result`, :mod:`omniflow.pipeline`
  (``estimate``), :mod:`omniflow.stream` (``OmniFlowStream``): the flow step
- :mod:`omniflow.applications` section 6: time to contact, steering, position fix,
  odometry; regions
- :mod:`omniflow.io` image, JSON and dataset files, pictures
- :mod:`omniflow.cli` the commands (nothing imports them)
"""

__version__ = "0.1.0"
