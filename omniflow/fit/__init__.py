"""The per-unit DCT series the flow step reads: fitting both frames, the band, sampling.

- :mod:`omniflow.fit.series` each unit's fitted frames (eq. 17-20), the rim fill
- :mod:`omniflow.fit.noise` image noise and the flow band chosen from it
- :mod:`omniflow.fit.sampling` reading the fitted series at the matched points
"""
