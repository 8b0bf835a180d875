"""Motion blur: the shutter open for a fraction of the frame interval, by sub-frames.

Mitsuba 3.8 has no animated transforms, so a frame whose camera has ``shutter`` > 0
(``[camera]``, the fraction of the frame interval the shutter is open) is rendered as
the mean of ``render.time_samples`` sub-frame renders. The shutter is centred on the
frame's instant: sub-frame j of n is rendered at frame + shutter ((j + 0.5) / n - 0.5)
(frame units), each with 1 / n of the samples per pixel (rounded up, to a square for a
stratified sampler) and its own
sampler seed, so the blurred image costs about what an instant one does. The ground
truth stays that of the frame's instant (the middle of the exposure).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["average_subframes", "subframe_offsets", "subframe_spp"]


def subframe_offsets(shutter: float, time_samples: int) -> NDArray[np.float64]:
    """Offsets (frames) of the sub-frames from the frame's instant, (time_samples,).

    ``shutter`` 0 gives the single offset 0 (an instant), whatever ``time_samples``.
    """
    if shutter == 0.0:
        return np.zeros(1)
    n = int(time_samples)
    return float(shutter) * ((np.arange(n) + 0.5) / n - 0.5)


def subframe_spp(spp: int, n_subframes: int) -> int:
    """Samples per pixel of each sub-frame: ``ceil(spp / n)``, at least 1.

    When ``spp`` is a perfect square (the sensor then uses a stratified sampler,
    ``omnisim.sensor.sampler_dict``) the result is rounded up to the next square.
    """
    sub = max(1, -(-int(spp) // int(n_subframes)))
    if round(int(spp) ** 0.5) ** 2 == int(spp):
        root = int(np.ceil(np.sqrt(sub) - 1e-9))
        sub = root * root
    return sub


def average_subframes(
    render: Callable[[float, int], NDArray[np.float32]], offsets: NDArray[np.float64]
) -> NDArray[np.float32]:
    """Mean of ``render(offset, j)`` over the sub-frames (j: the sub-frame's index)."""
    acc = None
    for j, off in enumerate(offsets):
        img = np.asarray(render(float(off), j), dtype=np.float64)
        acc = img if acc is None else acc + img
    return (acc / len(offsets)).astype(np.float32)
