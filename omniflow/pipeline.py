"""The stereo omni flow step: fit, match, solve (paper section 5).

:func:`estimate` takes the frames of both units, fits the DCT (eq. 17) to the
two frames of each unit, evaluates the fitted images and their polar
gradients (eq. 18-20) on the pixel grid by fast transforms, matches along the
radial lines (section 5.2, :mod:`omniflow.matching`), samples the gradients
and temporal derivatives at the matched points and solves for the flow
(section 5.3, :mod:`omniflow.flow`). Every choice is a field of
:class:`OmniFlowConfig`; :meth:`OmniFlowConfig.paper` gives the paper's.

Output per point (:class:`OmniFlowResult`, columns in :data:`COLUMNS`): cam1
position (x, y, theta, h1), its match h2 and cam2 position (x2, y2), range
and height (r, h; eq. 5), the polar flow (dh1_dt, dtheta_dt;
dh2_dt = (h2/h1) dh1_dt, eq. 14), dr_dt = -(d + r) dh1_dt / h1, the pixel
flow of both units (dx, dy; dx2, dy2), the determinant D of eq. (16), a
confidence in [0, 1] and the derivatives that entered eq. (9) and (15). The
pixel flow is the displacement of the point's image over one frame,
(x_c + (h + dh) cos(theta + dtheta), ...) - (x, y), so it compares directly
with a ground-truth displacement; velocities are per frame interval.

Accuracy of the variants (closed-form scenes, 256 x 256, 0.1-0.27 px of
motion; median endpoint error; the tests print the full tables):

================================================  ============  ==============
configuration                                     true matches  end to end
================================================  ============  ==============
paper: band 1/4, paper matching, first-frame      0.045-0.32    0.29-0.94
gradients, frame difference, direct (eq. 16)                    (58-91 % wrong
                                                                matches)
band 1/2, averaged gradients, direct              0.009-0.145
band 1/4, averaged gradients, pooled              0.014-0.066
default: band 1/2, robust matching, averaged      0.0005-0.011  0.004-0.009
gradients, frame difference, pooled (linear,                    (0 % wrong)
48 neighbours within r_m / 8)
same with the 3-D DCT over 3 frames               0.0035-0.015
OpenCV DIS medium, same frames and points         0.014-0.097   0.033-0.097
================================================  ============  ==============

(tests/omniflow/test_flow.py for the true-match table, tests/omniflow/test_pipeline.py end to
end, tests/omniflow/test_matching.py for the matchers.) Eq. (14) assumes no motion
along the axis; a wall moving up shows the error omniflow.flow predicts
(tests/omniflow/test_flow.py::test_vertical_motion_bias_matches_prediction).

Speed: the stage timings are in :attr:`OmniFlowResult.timings`;
benchmarks/bench_omniflow.py compares the whole step with OpenCV DIS.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from omniflow.applications import radial_velocity
from omniflow.dct import DCTFit, _cos3, fit_dct, fit_dct3
from omniflow.edges import polar_from_cartesian
from omniflow.flow import conditioning as direct_conditioning
from omniflow.flow import direct_solution, neighbourhoods, pooled_solution
from omniflow.matching import (
    MATCH_METHODS,
    Matches,
    PolarGrids,
    match_radial,
    polar_gradient_fast,
    sample_xy,
)
from omniflow.noise import BAND_CANDIDATES, choose_band, gradient_noise_variance, immerkaer_sigma
from omniflow.rig import Rig, Unit

__all__ = [
    "COLUMNS",
    "NoMatchesWarning",
    "OmniFlowConfig",
    "OmniFlowResult",
    "estimate",
    "fill_outside_rim",
    "flow_at_matches",
]

#: Output columns and their units, in CSV order.
COLUMNS: dict[str, str] = {
    "x": "px, cam1 column coordinate (pixel centre j + 0.5)",
    "y": "px, cam1 row coordinate",
    "theta": "rad, azimuth (theta_1 = theta_2)",
    "h1": "px, cam1 image radius",
    "h2": "px, matched cam2 image radius",
    "r": "m, range from the axis (eq. 5)",
    "h": "m, height above cam2's tip (eq. 4)",
    "dh1_dt": "px/frame, cam1 radial flow",
    "dtheta_dt": "rad/frame, angular flow",
    "dr_dt": "m/frame, radial velocity -(d + r) dh1_dt / h1",
    "dx": "px/frame, cam1 flow along x",
    "dy": "px/frame, cam1 flow along y",
    "x2": "px, cam2 column coordinate",
    "y2": "px, cam2 row coordinate",
    "dh2_dt": "px/frame, cam2 radial flow (h2/h1) dh1_dt (eq. 14)",
    "dx2": "px/frame, cam2 flow along x",
    "dy2": "px/frame, cam2 flow along y",
    "score": "1, stereo match score (NCC or gradient similarity)",
    "confidence": "1, lambda_min/lambda_max of the flow system's normal matrix",
    "D": "grey^2/(px rad), determinant of eq. (16)",
    "f1_h": "grey/px, df1/dh_1 used in eq. (9)",
    "f1_theta": "grey/rad, df1/dtheta used in eq. (9)",
    "f1_t": "grey/frame, df1/dt used in eq. (9)",
    "f2_h": "grey/px, df2/dh_2 used in eq. (15)",
    "f2_theta": "grey/rad, df2/dtheta used in eq. (15)",
    "f2_t": "grey/frame, df2/dt used in eq. (15)",
}

GRADIENTS = ("first", "average")
TEMPORALS = ("difference", "dct3d")
SOLVERS = ("direct", "pooled")
SAMPLINGS = ("cubic", "linear", "exact")
RIM_FILLS = ("reflect", "none")
POOL_MODELS = ("linear", "constant")
EIVS = ("correct", "residual", "none")
BAND_RULES = ("gain", "variance")


@dataclass(frozen=True)
class OmniFlowConfig:
    """Every knob of the stereo omni flow step.

    The defaults are the robust choices measured best on closed-form scenes
    (tests/omniflow/test_flow.py, tests/omniflow/test_pipeline.py); :meth:`paper` gives the
    paper's own choices.

    Attributes
    ----------
    band : float
        DCT band of the image matched on: P = band * W, Q = band * H
        coefficients (eq. 17). Paper: 0.25 (for matching and flow alike).
    match_band : float or None
        Narrower band for the matched image (frame t's series truncated);
        None: band.
    flow_band : float or None
        DCT band of the series the flow step differentiates (gradients and
        f_t of eq. 9 and 15); 0.5 by default, the matching band. None: chosen
        per frame pair from the images
        by ``flow_band_rule`` (omniflow.noise.choose_band, with the noise
        measured by Immerkaer's estimator on each unit's annulus; the
        narrower of the two units' choices). The band trades noise (in f_t,
        and in the gradients, which shrinks the flow: an errors-in-variables
        bias) against texture detail; docs/measurements.md, "omniflow
        accuracy", has the figures. The automatic choice is not the default:
        Immerkaer's estimate reads fine texture as noise, and on the 128 px
        closed-form validation scene it read 0.034 (the frames are noise-free
        but for 8-bit rounding), chose 1/8 and multiplied the mean EPE by 40
        (0.079 -> 3.3 px); on the converged default renders it chooses 1/2,
        the default, anyway (docs/measurements.md, "flow band default").
    flow_band_rule : {"gain", "variance"}
        With ``flow_band=None``: the widest band whose fitted gradient keeps
        ``flow_band_gain`` of its power as signal
        (omniflow.noise.predicted_gain), or the widest whose predicted flow
        variance (omniflow.noise.predicted_variance) is within
        ``flow_band_tolerance`` of the least. "variance" measured better on
        rendered frames (1 % noise: it picks 1/4 on the default scene, cam2
        EPE 0.55x DIS instead of 0.77x) but picks too narrow a band for
        texture whose detail runs along one direction only (closed-form
        striped wall: 0.075 px instead of 0.0025); docs/measurements.md.
    flow_band_tolerance : float
        ``flow_band_rule="variance"``: the factor over the least variance allowed.
    flow_band_gain : float
        ``flow_band_rule="gain"``: the least predicted signal share of the
        gradient power the chosen band keeps.
    noise_sigma : float or None
        Standard deviation of the image noise, grey levels (images in
        [0, 1]); None: Immerkaer's estimate on each unit's frame t
        (omniflow.noise.immerkaer_sigma; it also counts fine texture, so it
        errs high). Used by ``flow_band=None`` and ``eiv="correct"``.
    eiv : {"correct", "none"}
        Errors-in-variables correction of the pooled solver: the expected
        contribution of gradient noise (omniflow.noise.gradient_noise_variance
        at the flow band, halved for averaged gradients) is subtracted from
        the normal matrix (bias-compensated least squares), where that leaves
        it positive definite; "none" solves the plain least squares. The
        direct solver (eq. 16) is never corrected.
    match_method : {"robust", "paper"}
        Radial matching rule (omniflow.matching.match_radial): NCC of radial
        profiles with left-right and uniqueness checks, or the paper's most
        similar gradient vector.
    threshold_percentile : float
        Significant points of image 1: |df1/dh_1| above this percentile over
        the annulus searched (paper: "passes some threshold").
    min_gradient : float
        Significant points also need |df1/dh_1| above this, grey levels per
        pixel (images in [0, 1]); a textureless image has none.
    r_min : float or None
        Nearest range searched, metres (far end of the disparity window);
        None: the nearest range both units see (Rig.min_common_range).
    r_max : float
        Farthest range searched, metres: the paper's minimum disparity.
    n_theta : int
        Radial lines searched, evenly spaced in theta.
    h_step : float
        Sample spacing along the radial lines, pixels.
    h_min : float
        Smallest image radius searched in cam1, pixels.
    rim_margin : float
        Radii within this of the rim are not searched, pixels.
    patch_radius : float or None
        Robust matcher: half-length of the radial profile compared, pixels;
        None: r_m / 8.
    patch_lines : int
        Robust matcher: neighbouring radial lines on each side in the patch.
    profile_step : float or None
        Robust matcher: spacing of the profile's samples, pixels; None:
        patch_radius / 8.
    min_score : float
        Robust matcher: smallest normalised cross-correlation accepted.
    uniqueness : float
        Robust matcher: accept when (1 - NCC_best) <= uniqueness *
        (1 - NCC_second); 1 disables the test.
    left_right : bool
        Robust matcher: require the left-right consistency check.
    candidate_fraction : float
        Robust matcher: edges count as candidates down to this fraction of the
        significance threshold.
    tangential_blur : float
        Robust matcher: Gaussian blur across the radial lines, radians, to
        bring both units to one angular resolution; 0 disables it. 0.03
        (was 0.06) cut outliers on rendered 512 px frames of the default
        scene from 11.4 % to 4.9 % (tests/omniflow/test_matching.py).
    consistency : float
        Robust matcher: disparity consistency vote, pixels: keep a match only
        if enough neighbours (+-0.05 rad, +-r_m/16) have a disparity within
        this much of its own; 0 disables the vote.
    consistency_support : int
        Robust matcher: how many agreeing neighbours the vote needs (and at
        least half of them).
    self_similarity : float
        Robust matcher: periodic-alias test (omniflow.matching.match_radial):
        accept a match only when (1 - NCC_best) <= self_similarity
        (1 - NCC_self), NCC_self the best NCC of the point's profile with
        another edge of its own line within the window's width; 1 disables
        (the default: 0.5 cut the wrong matches on periodic closed-form walls
        15-30 times but changed nothing on the rendered default scene and
        costs ~45 % of the matching time; docs/measurements.md).
    gradients : {"first", "average"}
        Spatial gradient of frame t (paper) or the mean of frames t and t + 1.
    temporal : {"difference", "dct3d"}
        f_t as the frame difference of the fitted images (paper, section 5.3)
        or from a 3-D DCT over temporal_frames frames (the paper's suggested
        refinement), evaluated at t + 1/2.
    temporal_frames : int
        Frames in the 3-D DCT window (>= 3), centred on t + 1/2 where possible.
    solver : {"direct", "pooled"}
        Eq. (16) per point (paper) or eq. (9) and (15) of neighbouring
        matches pooled in least squares.
    pool_radius : float or None
        Pooled solver: neighbourhood radius, pixels; None: r_m / 8 (16 px at
        256 x 256, 32 px at 512 x 512).
    pool_k : int
        Pooled solver: most neighbours, the point itself included. With
        r_m / 8, 48 neighbours measured better than r_m / 16 and 24 on
        closed-form frames (median EPE with the true matches 0.0050 ->
        0.0030 px striped, 0.0142 -> 0.0112 room) and on rendered ones
        (default scene, 16 spp, true matches: 0.224 -> 0.183 px cam1,
        0.398 -> 0.321 px cam2 at 512 px; 0.321 -> 0.187, 0.533 -> 0.327 at
        128 px 4 spp): the render noise averages out over more equations.
    pool_range_tol : float or None
        Pooled solver: neighbours whose range differs by more than this
        fraction (another surface) are left out; None keeps them.
    pool_flow_tol : float or None
        Pooled solver: solve twice, and in the second pass leave out the
        neighbours whose first-pass flow differs from the point's by more
        than this, cam1 pixels per frame (a mover keeps its own motion where
        its range does not set it apart from the background); None: one pass.
    pool_model : {"linear", "constant"}
        Pooled solver: local flow model (omniflow.flow.pooled_solution),
        varying linearly with theta or constant.
    min_conditioning : float
        Drop points whose confidence is below this (0 keeps all).
    sampling : {"cubic", "linear", "exact"}
        How gradients and the fitted images are read at the matched points:
        cv2.remap of the pixel grids, or the series evaluated exactly.
    iterations : int
        Gauss-Newton (Lucas-Kanade) refinements of the solution: frame
        t + 1's fitted image is read at the displaced points (h_1 + dh_1,
        theta + dtheta) in cam1 and (h_2 + (h_2/h_1) dh_1, theta + dtheta)
        in cam2 (eq. 14; on a grid at twice the resolution, Lanczos
        interpolation), the gradients are frame t + 1's at the displaced
        point (averaged with frame t's at the point for
        gradients="average"), and eq. (9) and (15) are solved again (same
        solver) for the increment. 0 is the paper's single first-order step
        of eq. (8); the paper does not iterate. Measured: helps on exact
        closed-form frames with ~0.7 px of motion (0.028 -> 0.013 px median
        EPE, tests/omniflow/test_flow.py), hurts on rendered frames (default scene,
        true matches, 512 px 16 spp, 24 neighbours: 0.224 -> 0.283 px cam1;
        scenes/turn_in_place, default pooling: 0.125 -> 0.187 px) where the
        error is render noise, not the linearisation; it
        helps again where the motion is several pixels (scenes/large_motion,
        512 px: 2.77 -> 1.50 px cam1 with 3 iterations, still far off). Off
        by default.
    rim_fill : {"reflect", "none"}
        Before the DCT fit, replace the pixels beyond the mirror's rim by the
        image reflected radially about the rim ("reflect"), or keep them
        ("none", the paper). The step at the rim otherwise rings through the
        truncated series (Gibbs) some 20 px into the image.
    """

    band: float = 0.5
    match_band: float | None = None
    flow_band: float | None = 0.5
    flow_band_rule: str = "gain"
    flow_band_tolerance: float = 1.35
    flow_band_gain: float = 0.99
    noise_sigma: float | None = None
    eiv: str = "residual"
    match_method: str = "robust"
    threshold_percentile: float = 80.0
    min_gradient: float = 1e-4
    r_min: float | None = None
    r_max: float = 10.0
    n_theta: int = 360
    h_step: float = 1.0
    h_min: float = 16.0
    rim_margin: float = 4.0
    patch_radius: float | None = None
    patch_lines: int = 0
    profile_step: float | None = None
    min_score: float = 0.95
    uniqueness: float = 0.5
    left_right: bool = True
    candidate_fraction: float = 0.5
    tangential_blur: float = 0.03
    consistency: float = 1.0
    consistency_support: int = 2
    self_similarity: float = 1.0
    gradients: str = "average"
    temporal: str = "difference"
    temporal_frames: int = 3
    solver: str = "pooled"
    pool_radius: float | None = None
    pool_k: int = 48
    pool_range_tol: float | None = 0.1
    pool_model: str = "linear"
    pool_flow_tol: float | None = None
    min_conditioning: float = 0.0
    sampling: str = "cubic"
    iterations: int = 0
    rim_fill: str = "reflect"

    def __post_init__(self) -> None:
        checks = {
            "match_method": (self.match_method, MATCH_METHODS),
            "gradients": (self.gradients, GRADIENTS),
            "temporal": (self.temporal, TEMPORALS),
            "solver": (self.solver, SOLVERS),
            "sampling": (self.sampling, SAMPLINGS),
            "rim_fill": (self.rim_fill, RIM_FILLS),
            "pool_model": (self.pool_model, POOL_MODELS),
            "eiv": (self.eiv, EIVS),
            "flow_band_rule": (self.flow_band_rule, BAND_RULES),
        }
        for name, (val, allowed) in checks.items():
            if val not in allowed:
                raise ValueError(f"OmniFlowConfig.{name} = {val!r}: expected one of {allowed}")
        for name in ("band", "flow_band", "match_band"):
            val = getattr(self, name)
            if val is not None and not (0 < val <= 1):
                raise ValueError(f"OmniFlowConfig.{name} = {val!r}: expected a fraction in (0, 1]")
        if not self.flow_band_tolerance >= 1:
            raise ValueError(
                f"OmniFlowConfig.flow_band_tolerance = {self.flow_band_tolerance!r}: expected >= 1"
            )
        if not (0 < self.flow_band_gain < 1):
            raise ValueError(
                f"OmniFlowConfig.flow_band_gain = {self.flow_band_gain!r}: "
                "expected a fraction in (0, 1)"
            )
        if self.noise_sigma is not None and not self.noise_sigma >= 0:
            raise ValueError(
                f"OmniFlowConfig.noise_sigma = {self.noise_sigma!r}: expected >= 0 or None"
            )
        if self.temporal_frames < 3:
            raise ValueError("OmniFlowConfig.temporal_frames must be >= 3")
        if not (isinstance(self.iterations, int) and self.iterations >= 0):
            raise ValueError(
                f"OmniFlowConfig.iterations = {self.iterations!r}: expected an integer >= 0"
            )
        if self.consistency < 0 or self.consistency_support < 1:
            raise ValueError(
                f"OmniFlowConfig.consistency = {self.consistency!r}, consistency_support = "
                f"{self.consistency_support!r}: expected >= 0 and >= 1"
            )
        if self.pool_k < 1 or (self.pool_radius is not None and self.pool_radius <= 0):
            raise ValueError("OmniFlowConfig.pool_k must be >= 1 and pool_radius > 0")

    @classmethod
    def paper(cls, **overrides) -> OmniFlowConfig:
        """The paper's choices, as written.

        Gradient-similarity matching (section 5.2), P = X/4 for the matching
        and the flow step alike, the image as it is (no rim fill), the series
        and its analytic derivatives evaluated exactly at the points (eq.
        18-20), first-frame gradients, the frame difference of the fitted
        images for f_t and the direct solution of eq. (16) at each point;
        no noise correction. tests/omniflow/test_flow.py checks that this reproduces
        eq. (16), (19) and (20) computed independently to rounding.

        Why it fails under noise: eq. (9) and (15) at one point are nearly
        dependent, because both units see nearly the same patch at the same
        scale (f2_h ~ f1_h, f2_theta ~ f1_theta), so D of eq. (16) is
        ~ f_h f_theta (1 - h_2/h_1) and the radial flow rests on the small
        difference f2_t - f1_t divided by it. Noise in the temporal
        derivatives and in the gradients is divided by that small D: the
        2x2 solve is ill-conditioned, and its error grows as its conditioning
        falls (tests/omniflow/test_flow.py measures this on noisy closed-form frames).
        """
        base = dict(
            band=0.25,
            flow_band=0.25,
            eiv="none",
            match_method="paper",
            gradients="first",
            temporal="difference",
            solver="direct",
            rim_fill="none",
            sampling="exact",
        )
        base.update(overrides)
        return cls(**base)

    def replace(self, **changes) -> OmniFlowConfig:
        """A copy with some fields changed."""
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class OmniFlowResult:
    """Per-point results of :func:`estimate`.

    Attributes
    ----------
    columns : dict[str, ndarray]
        Equal-length 1-D arrays, keys and units in :data:`COLUMNS`.
    timings : dict[str, float]
        Seconds per stage: ``fit``, ``grids``, ``match``, ``sample``,
        ``solve``, ``total``.
    config : OmniFlowConfig
    n_significant : int
        Significant points of image 1 that the matcher tried.
    diagnostics : dict[str, float]
        ``flow_band`` (the flow step's DCT band, chosen or given),
        ``noise_sigma1``, ``noise_sigma2`` (the image noise used per unit,
        grey levels; 0 when not needed).
    """

    columns: dict[str, NDArray]
    timings: dict[str, float] = field(default_factory=dict)
    config: OmniFlowConfig | None = None
    n_significant: int = 0
    diagnostics: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(next(iter(self.columns.values())).size) if self.columns else 0

    def __getitem__(self, key: str) -> NDArray:
        return self.columns[key]

    def to_csv(self, path: str | Path) -> Path:
        """Write the columns to CSV atomically, with a '#' header line of units."""
        from omniflow.imageio import atomic_output

        names = list(self.columns)
        data = (
            np.column_stack([np.asarray(self.columns[k], dtype=float) for k in names])
            if names
            else np.zeros((0, 0))
        )
        units = "; ".join(f"{k}: {COLUMNS.get(k, '')}" for k in names)
        path = Path(path)
        with atomic_output(path) as tmp, open(tmp, "w") as fh:
            fh.write(f"# omniflow per-point results; {units}\n")
            fh.write(",".join(names) + "\n")
            np.savetxt(fh, data, delimiter=",", fmt="%.9g")
        return path


# ---------------------------------------------------------------------------


def _grey(frame, what: str, unit: Unit, config: OmniFlowConfig) -> NDArray:
    arr = np.asarray(frame)
    if arr.ndim != 2:
        raise ValueError(f"{what}: expected a grey image (H, W), got shape {arr.shape}")
    if arr.shape != (unit.height, unit.width):
        raise ValueError(
            f"{what} has shape {arr.shape}; the rig's {unit.name} is "
            f"{unit.height}x{unit.width} (rows x columns)"
        )
    arr = np.asarray(arr, dtype=np.float32)
    if config.rim_fill == "reflect":
        arr = fill_outside_rim(arr, unit)
    return arr


@lru_cache(maxsize=8)
def _rim_maps(unit: Unit, margin: float) -> tuple[NDArray, NDArray]:
    x, y = unit.pixel_centres()
    h_i, theta = unit.polar_of_pixel(x, y)
    edge = unit.r_m - margin
    src = np.where(h_i > edge, np.maximum(2.0 * edge - h_i, 0.0), h_i)
    xs, ys = unit.pixel_of_polar(src, theta)
    return (xs - 0.5).astype(np.float32), (ys - 0.5).astype(np.float32)


def fill_outside_rim(image: NDArray, unit: Unit, *, margin: float = 1.0) -> NDArray:
    """The image with every pixel beyond r_m - margin replaced by its radial mirror image.

    A pixel at image radius h_i > e = r_m - margin takes the (bilinear) value
    at radius 2 e - h_i on the same radial line, so the image continues
    smoothly across the rim instead of stepping to the background; the DCT
    fit of eq. (17) then does not ring near the rim. Pixels inside are
    unchanged. Returns float32 (H, W).
    """
    import cv2

    mx, my = _rim_maps(unit, float(margin))
    return cv2.remap(
        np.ascontiguousarray(image, dtype=np.float32),
        mx,
        my,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )


class _Frame:
    """One unit at one time: its fit, and grids made on demand."""

    def __init__(self, fit: DCTFit, unit: Unit):
        self.fit, self.unit = fit, unit
        self._f = self._grad = self._grad_xy = self._fine = None

    @property
    def f(self) -> NDArray:
        """The fitted image on the pixel grid, eq. (18)."""
        if self._f is None:
            self._f = np.asarray(self.fit.grid(), dtype=np.float32)
        return self._f

    @property
    def fine(self) -> NDArray:
        """The fitted image at twice the resolution: sample j at x = (j + 1/2) / 2."""
        if self._fine is None:
            c = self.fit.coeffs.astype(np.float32, copy=False)
            self._fine = _cos3(_cos3(c, 2 * self.fit.width, axis=1), 2 * self.fit.height, axis=0)
        return self._fine

    @property
    def grad(self) -> tuple[NDArray, NDArray]:
        """(f_h, f_theta) grids, eq. (19)-(20)."""
        if self._grad is None:
            self._grad = polar_gradient_fast(self.fit, self.unit)
        return self._grad

    @property
    def grad_xy(self) -> tuple[NDArray, NDArray]:
        """(f_x, f_y) grids."""
        if self._grad_xy is None:
            self._grad_xy = tuple(np.asarray(g, dtype=np.float32) for g in self.fit.grid_gradient())
        return self._grad_xy


def _sample_polar_grad(
    frame: _Frame, x: NDArray, y: NDArray, sampling: str
) -> tuple[NDArray, NDArray]:
    """(f_h, f_theta) at points: f_x, f_y sampled (or evaluated exactly), then eq. (19)-(20)."""
    if sampling == "exact":
        f_x, f_y = frame.fit.gradient(x, y)
    else:
        gx, gy = frame.grad_xy
        f_x = sample_xy(gx, x, y, interpolation=sampling).astype(np.float64)
        f_y = sample_xy(gy, x, y, interpolation=sampling).astype(np.float64)
    f_h, f_th = polar_from_cartesian(f_x, f_y, x - frame.unit.x_c, y - frame.unit.y_c)
    return f_h, f_th


def _sample_f(frame: _Frame, x: NDArray, y: NDArray, sampling: str) -> NDArray:
    if sampling == "exact":
        return frame.fit.evaluate(x, y)
    return sample_xy(frame.f, x, y, interpolation=sampling).astype(np.float64)


_FINE_INTERP = 4  # lanczos


def _sample_fine(frame: _Frame, x: NDArray, y: NDArray, sampling: str) -> NDArray:
    """The fitted image at points: Lanczos-4 interpolation of the grid (or exact)."""
    if sampling == "exact":
        return frame.fit.evaluate(x, y)
    import cv2

    mx = (2.0 * np.asarray(x, dtype=np.float64) - 0.5).astype(np.float32).reshape(1, -1)
    my = (2.0 * np.asarray(y, dtype=np.float64) - 0.5).astype(np.float32).reshape(1, -1)
    out = np.empty(mx.size, np.float64)
    for lo in range(0, mx.size, 32000):  # cv2.remap maps are at most 32767 wide
        sl = slice(lo, lo + 32000)
        out[sl] = cv2.remap(
            frame.fine, mx[:, sl], my[:, sl], _FINE_INTERP, borderMode=cv2.BORDER_CONSTANT
        )[0]
    return out.reshape(np.shape(x))


def _fits(
    frames: Sequence, t: int, unit: Unit, config: OmniFlowConfig, what: str, band: float
) -> dict[str, DCTFit]:
    """The series one unit needs, fitted at ``band`` (truncated later by :func:`_frames`).

    ``a``: the image at frame t (matched on); ``b``: the image at frame
    t + 1 (read at the displaced points by ``iterations``); ``g``: the series whose
    gradient enters eq. (8) (frame t, or the mean of frames t and t + 1, or
    the 3-D series at t + 1/2); ``t``: the series of f_t (the difference of
    the fits of frames t + 1 and t, or the 3-D series' time derivative at
    t + 1/2). Linear in the coefficients, so averaging or differencing the
    coefficients equals doing it to the grids.
    """
    n = len(frames)
    if config.temporal == "dct3d":
        T = config.temporal_frames
        if n < T:
            raise ValueError(f"{what}: temporal='dct3d' needs {T} frames, got {n}")
        t0 = int(np.clip(t + 1 - T // 2, 0, n - T))
        stack = np.stack(
            [_grey(frames[k], f"{what}[{k}]", unit, config) for k in range(t0, t0 + T)]
        )
        f3 = fit_dct3(stack, band=band)
        tw = t - t0  # frame t in the window's time
        a = _as32(f3.at_time(tw))
        return {
            "a": a,
            "b": _as32(f3.at_time(tw + 1)),
            "g": a if config.gradients == "first" else _as32(f3.at_time(tw + 0.5)),
            "t": _as32(f3.time_derivative_at(tw + 0.5)),
        }
    fa, fb = (
        fit_dct(_grey(frames[k], f"{what}[{k}]", unit, config), band=band) for k in (t, t + 1)
    )
    g = fa if config.gradients == "first" else replace(fa, coeffs=0.5 * (fa.coeffs + fb.coeffs))
    return {"a": fa, "b": fb, "g": g, "t": replace(fa, coeffs=fb.coeffs - fa.coeffs)}


def _truncate(fit: DCTFit, band: float) -> DCTFit:
    """The series with only the coefficients of ``band`` kept (eq. 18 truncated further)."""
    q = max(1, round(band * fit.height))
    p = max(1, round(band * fit.width))
    if q >= fit.Q and p >= fit.P:
        return fit
    return replace(fit, coeffs=fit.coeffs[:q, :p])


def _frames(fits: dict[str, DCTFit], unit: Unit, config: OmniFlowConfig, flow_band: float) -> dict:
    """Lazy-grid :class:`_Frame` s: ``a`` at the matching band, the others at ``flow_band``."""
    out = {"a": _Frame(_truncate(fits["a"], config.band), unit)}
    for key in ("b", "g", "t"):
        out[key] = _Frame(_truncate(fits[key], flow_band), unit)
    return out


@lru_cache(maxsize=8)
def _annulus(unit: Unit, h_min: float, margin: float) -> NDArray:
    """Pixels of the unit's annulus h_min + 1 <= h_i <= r_m - margin - 1 (read-only).

    One pixel inside the searched annulus, so the 3x3 noise kernel sees only its pixels.
    """
    x, y = unit.pixel_centres()
    h_i, _ = unit.polar_of_pixel(x, y)
    m = (h_i >= h_min + 1.5) & (h_i <= unit.r_m - margin - 1.5)
    m.setflags(write=False)
    return m


def _noise_sigma(frame, unit: Unit, config: OmniFlowConfig) -> float:
    """The image noise of one unit's frame: ``config.noise_sigma`` or Immerkaer's estimate."""
    if config.noise_sigma is not None:
        return float(config.noise_sigma)
    mask = _annulus(unit, float(config.h_min), float(config.rim_margin))
    s = immerkaer_sigma(np.asarray(frame, dtype=np.float32), mask, erode=False)
    return 0.0 if not np.isfinite(s) else s


def _flow_band(fits: Sequence[dict], sigmas: Sequence[float], config: OmniFlowConfig) -> float:
    """The flow step's band: ``config.flow_band``, or the narrower of the units' choices."""
    if config.flow_band is not None:
        return float(config.flow_band)
    averaged = 1 if config.gradients == "first" else 2
    return min(
        choose_band(
            f["a"],
            s,
            rule=config.flow_band_rule,
            min_gain=config.flow_band_gain,
            tolerance=config.flow_band_tolerance,
            frames=averaged,
        )
        for f, s in zip(fits, sigmas, strict=True)
    )


def _gradient_noise(sigma: float, fit: DCTFit, config: OmniFlowConfig) -> float:
    """Variance of the gradient series' f_h (and f_theta / h_i) from pixel noise ``sigma``."""
    v = gradient_noise_variance(sigma, fit.P, fit.Q, fit.width, fit.height)
    # the mean of two frames' fits with independent noise has half the variance
    return v if config.gradients == "first" else 0.5 * v


def _match_frame(frame: _Frame, config: OmniFlowConfig) -> _Frame:
    """The image matched on: frame t's series truncated to ``match_band``."""
    if config.match_band is None or config.match_band >= config.band:
        return frame
    return _Frame(_truncate(frame.fit, config.match_band), frame.unit)


def _as32(fit: DCTFit) -> DCTFit:
    return replace(fit, dtype=np.dtype(np.float32))


def _check_inputs(frames1, frames2, rig: Rig, t: int) -> None:
    if len(frames1) != len(frames2):
        raise ValueError(f"frames1 has {len(frames1)} frames but frames2 {len(frames2)}")
    if not (0 <= t and t + 1 < len(frames1)):
        raise ValueError(f"t = {t}: need frames t and t + 1 of {len(frames1)}")
    for name, frames, unit in (("frames1", frames1, rig.cam1), ("frames2", frames2, rig.cam2)):
        shape = np.shape(frames[t])
        if shape != (unit.height, unit.width):
            raise ValueError(
                f"{name}[{t}] has shape {shape}; the rig's {unit.name} is "
                f"{unit.height}x{unit.width} (rows x columns)"
            )


class NoMatchesWarning(UserWarning):
    """:func:`estimate` found no stereo match, so its result has no points.

    Zero matches is an answer, not an error: a dark or lens-capped frame, a
    constant image, or a rig whose units share no range in the searched window
    leave nothing to measure. The result then has every column, each of length 0.
    """


def _no_points(timings: dict, t_start: float, config, n_sig: int) -> OmniFlowResult:
    """The empty result (every column of :data:`COLUMNS`, length 0) with a warning."""
    warnings.warn(
        f"no stereo matches ({n_sig} significant points in cam1 tried): the result is empty "
        "(is the image dark, constant, or outside the units' common view?)",
        NoMatchesWarning,
        stacklevel=3,
    )
    timings.update(sample=0.0, solve=0.0, total=time.perf_counter() - t_start)
    columns = {name: np.zeros(0) for name in COLUMNS}
    return OmniFlowResult(columns=columns, timings=timings, config=config, n_significant=n_sig)


def estimate(
    frames1: Sequence[NDArray],
    frames2: Sequence[NDArray],
    rig: Rig,
    config: OmniFlowConfig | None = None,
    *,
    t: int = 0,
    matches: Matches | None = None,
) -> OmniFlowResult:
    """Stereo omni flow from frame t to t + 1 of both units.

    Parameters
    ----------
    frames1, frames2 : sequence of ndarray, each shape (H, W)
        Grey float frames of cam1 and cam2 (at least t + 2; at least
        ``config.temporal_frames`` for ``temporal="dct3d"``).
    rig : Rig
    config : OmniFlowConfig, optional
        Defaults to ``OmniFlowConfig()``.
    t : int
        The flow is from frame t to frame t + 1.
    matches : Matches, optional
        Use these stereo matches instead of matching (e.g. the true ones).

    Returns
    -------
    OmniFlowResult
        With no stereo match (a dark or constant image, no common view) every
        column has length 0 and a :class:`NoMatchesWarning` is issued.
    """
    config = OmniFlowConfig() if config is None else config
    _check_inputs(frames1, frames2, rig, t)
    timings: dict[str, float] = {}
    t_start = time.perf_counter()

    need_sigma = config.flow_band is None or (config.eiv == "correct" and config.solver == "pooled")
    sigmas = (
        (_noise_sigma(frames1[t], rig.cam1, config), _noise_sigma(frames2[t], rig.cam2, config))
        if need_sigma
        else (0.0, 0.0)
    )
    fit_band = max(config.band, config.flow_band or max(BAND_CANDIDATES))
    fits = (
        _fits(frames1, t, rig.cam1, config, "frames1", fit_band),
        _fits(frames2, t, rig.cam2, config, "frames2", fit_band),
    )
    flow_band = _flow_band(fits, sigmas, config)
    cam1 = _frames(fits[0], rig.cam1, config, flow_band)
    cam2 = _frames(fits[1], rig.cam2, config, flow_band)
    for cam, s in zip((cam1, cam2), sigmas, strict=True):
        if config.eiv == "correct":
            cam["noise_var"] = _gradient_noise(s, cam["g"].fit, config)
        elif config.eiv == "residual":  # per unit of the fitted value's noise variance
            fit = cam["g"].fit
            cam["noise_var"] = _gradient_noise(1.0, fit, config) / (
                fit.P * fit.Q / (fit.width * fit.height)
            )
        else:
            cam["noise_var"] = 0.0
    diagnostics = {"flow_band": flow_band, "noise_sigma1": sigmas[0], "noise_sigma2": sigmas[1]}
    t_fit = time.perf_counter()
    timings["fit"] = t_fit - t_start

    n_sig = 0
    if matches is None:
        if config.match_method == "paper":  # the polar edge finder's f_h, f_theta
            grids = tuple(
                PolarGrids(f=c["a"].f, f_h=c["a"].grad[0], f_theta=c["a"].grad[1])
                for c in (cam1, cam2)
            )
        else:  # the robust matcher differentiates its polar table of f
            grids = tuple(
                PolarGrids(f=_match_frame(c["a"], config).f, f_h=None) for c in (cam1, cam2)
            )
        timings["grids"] = time.perf_counter() - t_fit
        t_m = time.perf_counter()
        matches = match_radial(
            None,
            None,
            rig,
            method=config.match_method,
            threshold_percentile=config.threshold_percentile,
            min_gradient=config.min_gradient,
            r_min=config.r_min,
            r_max=config.r_max,
            n_theta=config.n_theta,
            h_step=config.h_step,
            h_min=config.h_min,
            rim_margin=config.rim_margin,
            patch_radius=config.patch_radius,
            patch_lines=config.patch_lines,
            profile_step=config.profile_step,
            min_score=config.min_score,
            uniqueness=config.uniqueness,
            left_right=config.left_right,
            candidate_fraction=config.candidate_fraction,
            tangential_blur=config.tangential_blur,
            consistency=config.consistency,
            consistency_support=config.consistency_support,
            self_similarity=config.self_similarity,
            grids=grids,
        )
        n_sig = matches.n_significant
        timings["match"] = time.perf_counter() - t_m
    else:
        timings["grids"] = 0.0
        timings["match"] = 0.0
    if len(matches.theta) == 0:
        return _no_points(timings, t_start, config, n_sig)

    t_s = time.perf_counter()
    result = flow_at_matches(matches, rig, cam1, cam2, config)
    timings["sample"] = result.pop("_t_sample")
    timings["solve"] = time.perf_counter() - t_s - timings["sample"]
    timings["total"] = time.perf_counter() - t_start
    return OmniFlowResult(
        columns=result,
        timings=timings,
        config=config,
        n_significant=n_sig,
        diagnostics=diagnostics,
    )


def flow_at_matches(
    matches: Matches, rig: Rig, cam1: tuple, cam2: tuple, config: OmniFlowConfig
) -> dict[str, NDArray]:
    """Sample gradients and temporal derivatives at the matches and solve.

    ``cam1`` and ``cam2`` are the per-unit series as built by :func:`estimate`
    (keys ``a``, ``g``, ``t``; see ``_fits``).
    Returns the result columns (plus a private ``_t_sample`` timing).
    """
    t0 = time.perf_counter()
    theta, h1, h2 = matches.theta, matches.h1, matches.h2
    x1, y1 = rig.cam1.pixel_of_polar(h1, theta)
    x2, y2 = rig.cam2.pixel_of_polar(h2, theta)
    derivs = []
    for fr, x, y in ((cam1, x1, y1), (cam2, x2, y2)):
        f_h, f_th = _sample_polar_grad(fr["g"], x, y, config.sampling)
        f_t = _sample_f(fr["t"], x, y, config.sampling)  # section 5.3
        derivs.append((f_h, f_th, f_t))
    (f1_h, f1_th, f1_t), (f2_h, f2_th, f2_t) = derivs
    t1 = time.perf_counter()
    r, h = rig.triangulate(h1, h2)
    noise = (cam1.get("noise_var", 0.0), cam2.get("noise_var", 0.0))
    solve = _solver(rig, config, x1, y1, theta, h1, h2, r, noise)
    a, b, conf = solve(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t)
    D = f1_h * f2_th - (h2 / h1) * f2_h * f1_th  # eq. (16)
    k = h2 / h1  # eq. (14)
    for _ in range(config.iterations):
        # Gauss-Newton on eq. (8)'s linearisation: the residual of brightness
        # constancy at the displaced points, solved again for the increment.
        ok = np.isfinite(a) & np.isfinite(b)
        da0, db0 = np.where(ok, a, 0.0), np.where(ok, b, 0.0)
        inc = []
        for fr, x, y, h_i, dh in ((cam1, x1, y1, h1, da0), (cam2, x2, y2, h2, k * da0)):
            unit = fr["a"].unit
            xd, yd = unit.pixel_of_polar(h_i + dh, theta + db0)
            g_h, g_th = _sample_polar_grad(fr["b"], xd, yd, config.sampling)
            if config.gradients == "average":
                a_h, a_th = _sample_polar_grad(fr["a"], x, y, config.sampling)
                g_h, g_th = 0.5 * (g_h + a_h), 0.5 * (g_th + a_th)
            # the residual needs the image itself read off-pixel: cubic
            # interpolation of a series with periods down to 1 / band px is
            # biased by a few per cent, Lanczos (8 taps) much less
            res = _sample_fine(fr["b"], xd, yd, config.sampling) - _sample_fine(
                fr["a"], x, y, config.sampling
            )
            inc.append((g_h, g_th, res))
        (g1_h, g1_th, r1), (g2_h, g2_th, r2) = inc
        da, db, conf_i = solve(g1_h, g1_th, r1, g2_h, g2_th, r2)
        step = np.isfinite(da) & np.isfinite(db)
        a = np.where(step, a + da, a)
        b = np.where(step, b + db, b)
        conf = np.where(step, conf_i, conf)
    keep = np.isfinite(a) & np.isfinite(b)
    if not np.all(keep):
        (theta, h1, h2, x1, y1, x2, y2, r, h, a, b, D, conf) = (
            v[keep] for v in (theta, h1, h2, x1, y1, x2, y2, r, h, a, b, D, conf)
        )
        (f1_h, f1_th, f1_t, f2_h, f2_th, f2_t) = (
            v[keep] for v in (f1_h, f1_th, f1_t, f2_h, f2_th, f2_t)
        )
        score = matches.score[keep]
    else:
        score = matches.score
    dr_dt = radial_velocity(r, h1, a, d=rig.d)  # -(d + r) dh_1/dt / h_1
    k = h2 / h1
    dx, dy = _displacement(rig.cam1, h1, theta, a, b)
    dx2, dy2 = _displacement(rig.cam2, h2, theta, k * a, b)
    return {
        "x": x1,
        "y": y1,
        "theta": theta,
        "h1": h1,
        "h2": h2,
        "r": r,
        "h": h,
        "dh1_dt": a,
        "dtheta_dt": b,
        "dr_dt": dr_dt,
        "dx": dx,
        "dy": dy,
        "x2": x2,
        "y2": y2,
        "dh2_dt": k * a,
        "dx2": dx2,
        "dy2": dy2,
        "score": np.asarray(score, dtype=float),
        "confidence": conf,
        "D": D,
        "f1_h": f1_h,
        "f1_theta": f1_th,
        "f1_t": f1_t,
        "f2_h": f2_h,
        "f2_theta": f2_th,
        "f2_t": f2_t,
        "_t_sample": t1 - t0,
    }


def _solver(
    rig: Rig,
    config: OmniFlowConfig,
    x1: NDArray,
    y1: NDArray,
    theta: NDArray,
    h1: NDArray,
    h2: NDArray,
    r: NDArray,
    noise: tuple[float, float] = (0.0, 0.0),
):
    """The configured solver of eq. (9) and (15) at these matches, as a function
    of the six derivatives returning (dh1_dt, dtheta_dt, confidence).

    ``noise``: the variance of each unit's gradient components, subtracted by
    the pooled solver (``eiv="correct"``)."""
    if config.solver == "direct":

        def solve(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t):
            a, b, _ = direct_solution(
                f1_h,
                f1_th,
                f1_t,
                f2_h,
                f2_th,
                f2_t,
                h1,
                h2,
                min_conditioning=config.min_conditioning,
            )
            return a, b, direct_conditioning(f1_h, f1_th, f2_h, f2_th, h1, h2)

        return solve
    pool_radius = rig.cam1.r_m / 8.0 if config.pool_radius is None else config.pool_radius
    idx, w = neighbourhoods(
        x1, y1, k=config.pool_k, radius=pool_radius, r=r, range_tol=config.pool_range_tol
    )

    kw = dict(theta=theta, model=config.pool_model, scale=pool_radius,
              min_conditioning=config.min_conditioning)  # fmt: skip

    def solve_w(derivs, weights):
        return pooled_solution(
            *derivs, h1, h2, idx, weights, **kw, noise1=noise[0], noise2=noise[1],
            residual_noise=config.eiv == "residual",
        )  # fmt: skip

    def solve(f1_h, f1_th, f1_t, f2_h, f2_th, f2_t):
        derivs = (f1_h, f1_th, f1_t, f2_h, f2_th, f2_t)
        a, b, conf = solve_w(derivs, w)
        if config.pool_flow_tol is None:
            return a, b, conf
        return solve_w(derivs, _same_motion(w, idx, a, b, h1, config.pool_flow_tol))

    return solve


def _same_motion(
    w: NDArray, idx: NDArray, a: NDArray, b: NDArray, h1: NDArray, tol: float
) -> NDArray:
    """Pool weights with the neighbours whose first-pass flow differs by more than ``tol`` removed.

    Flows are compared in cam1 pixels per frame at the point's own radius:
    (a_j h_1,i / h_1,j, h_1,i b_j) against (a_i, h_1,i b_i) (the radial flow
    scales with h_1 on one surface, as in the pooled model). A point without a
    first-pass flow keeps its neighbours; a neighbour without one is dropped.
    """
    n = a.size
    ext = lambda v: np.append(v, np.nan)  # noqa: E731  (index n: no neighbour)
    hi = h1[:, None]
    da = ext(a / h1)[idx] * hi - a[:, None]
    dc = (ext(b)[idx] - b[:, None]) * hi
    with np.errstate(invalid="ignore"):
        same = np.hypot(da, dc) <= tol
    same[:, 0] = True
    same |= ~(np.isfinite(a) & np.isfinite(b))[:, None]
    same &= idx < n
    return np.where(same, w, 0.0)


def _displacement(
    unit: Unit, h_i: NDArray, theta: NDArray, dh: NDArray, dtheta: NDArray
) -> tuple[NDArray, NDArray]:
    """Pixel displacement of the polar point (h_i, theta) moved by (dh, dtheta)."""
    x0, y0 = unit.pixel_of_polar(h_i, theta)
    x1, y1 = unit.pixel_of_polar(h_i + dh, theta + dtheta)
    return x1 - x0, y1 - y0
