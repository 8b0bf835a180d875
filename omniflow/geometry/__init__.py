"""The rig: one conical-mirror unit and the coaxial pair, eq. (1)-(7), and its calibration.

- :mod:`omniflow.geometry.rig` :class:`Unit`, :class:`Rig`, triangulation (eq. 5)
- :mod:`omniflow.geometry.calibration` the mirror's rim in an image and v (eq. 2)
"""
