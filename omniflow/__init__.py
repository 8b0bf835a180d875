"""Omni Flow (Spacek): optic flow and stereo of a coaxial conical-mirror rig.

Modules, in the order of the paper:

- :mod:`omniflow.conventions` axes, angle sense, pixel centres, units
- :mod:`omniflow.rig` one unit and the coaxial pair, eq. (1)-(7)
- :mod:`omniflow.calibration` the rim circle and v, eq. (2)
- :mod:`omniflow.dct` the DCT fit, eq. (17)-(18), and its 3-D form
- :mod:`omniflow.edges` the polar edge finder, eq. (19)-(20)
- :mod:`omniflow.matching` radial stereo matching, section 5.2
- :mod:`omniflow.flow` omni flow, eq. (8), (9), (15), (16)
- :mod:`omniflow.pipeline` the whole step: ``estimate(frames1, frames2, rig, config)``
- :mod:`omniflow.applications` section 6: time to contact, steering, position fix, odometry
- :mod:`omniflow.synthetic` closed-form scenes with exact ground truth
- :mod:`omniflow.imageio`, :mod:`omniflow.draw`, :mod:`omniflow.cli` files, pictures, the command
"""

__version__ = "0.1.0"
