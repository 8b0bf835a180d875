"""Radial stereo matching of a coaxial pair (paper section 5.2).

The public API; one job per module:

- :mod:`omniflow.matching.radial`: :func:`match_radial` (the search: window,
  thresholds, either rule, the vote) and :class:`Matches`;
- :mod:`omniflow.matching.tables`: the fitted images on pixel grids and on
  polar tables (one row per radial line), and sampling them;
- :mod:`omniflow.matching.robust`: NCC of radial profiles with uniqueness and
  left-right checks;
- :mod:`omniflow.paper.matching`: the paper's most similar gradient vector;
- :mod:`omniflow.matching.vote`: the disparity consistency vote.
"""

from omniflow.matching.radial import MATCH_METHODS, Matches, match_radial
from omniflow.matching.tables import (
    PolarGrids,
    polar_gradient_fast,
    polar_grids,
    polar_sample,
    sample_xy,
)

__all__ = [
    "MATCH_METHODS",
    "Matches",
    "PolarGrids",
    "match_radial",
    "polar_gradient_fast",
    "polar_grids",
    "polar_sample",
    "sample_xy",
]
