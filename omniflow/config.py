"""The knobs of the stereo omni flow step: :class:`OmniFlowConfig`.

Every choice :func:`omniflow.pipeline.estimate` makes is a field here, checked
when the config is made. Start from a preset (:data:`PRESETS`,
``OmniFlowConfig.preset("dense", pool_k=64)``) and change one or two things; a
combination of knobs that cannot work together is an error naming both.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from omniflow.matching import MATCH_METHODS

__all__ = ["OmniFlowConfig"]

GRADIENTS = ("first", "average")
TEMPORALS = ("difference", "dct3d")
SOLVERS = ("direct", "pooled")
SAMPLINGS = ("cubic", "linear", "exact")
RIM_FILLS = ("reflect", "none")
POOL_MODELS = ("linear", "constant")
EIVS = ("correct", "residual", "none")
BAND_RULES = ("gain", "variance")
SHADING_WHERE = ("everywhere", "moving")
BRIGHTNESS_MODELS = ("linear", "gain")
#: Weightings of the two units' equations in :func:`omniflow.solve.pooled.pooled_solution`.
UNIT_WEIGHTINGS = ("equal", "global", "local")


#: The fields :meth:`OmniFlowConfig.dense` changes from the defaults. Grid pools fit one
#: gain per pool (``brightness_model="gain"``; the linear gain needs the k-d tree's pools).
DENSE = {
    "dense_percentile": 60.0,
    "dense_smooth": 0.95,
    "pool_grid": 0.125,
    "decouple_tol": 60.0,
    "decouple_gain_tol": 60.0,
    "brightness_model": "gain",
}

#: The fields :meth:`OmniFlowConfig.paper` changes from the defaults: the paper's choices.
PAPER = {
    "band": 0.25,
    "flow_band": 0.25,
    "flow_taper": 0.0,
    "eiv": "none",
    "match_method": "paper",
    "gradients": "first",
    "temporal": "difference",
    "solver": "direct",
    "rim_fill": "none",
    "sampling": "exact",
    "iterations": 0,
    "iterate_min_px": 0.0,
    "brightness_gate": None,
    "decouple_gain_tol": None,
}

#: The presets of :meth:`OmniFlowConfig.preset`: each one's fields changed from the
#: defaults. "default": the robust edges-only step (docs/decisions/defaults.md);
#: "dense": more matches and grid pools, about three times the time
#: (docs/decisions/dense-preset.md); "paper": the paper as written
#: (docs/decisions/paper-preset.md).
PRESETS: dict[str, dict] = {"default": {}, "dense": DENSE, "paper": PAPER}

#: The knobs that thin each pool by its neighbours: they need the k-d tree's pools, so
#: they cannot be combined with ``pool_grid`` (the value each has when off).
TREE_ONLY = {
    "pool_unit_weighting": "equal",
    "pool_edge_tol": None,
    "pool_residual_tol": None,
    "pool_flow_tol": None,
    "pool_min_info": None,
}


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
        f_t of eq. 9 and 15); 0.5 by default, rolled off over its outer
        half (``flow_taper``). None: chosen per frame pair from the images
        by ``flow_band_rule`` (omniflow.fit.noise.choose_band, with the noise
        measured by Immerkaer's estimator on each unit's annulus; the
        narrower of the two units' choices). The band trades noise (in f_t,
        and in the gradients, which shrinks the flow: an errors-in-variables
        bias) against texture detail. The automatic choice is not the
        default because Immerkaer's estimate reads fine texture as noise
        (docs/measurements.md, "flow band default").
    flow_taper : float
        Fraction of the flow band over which the flow series rolls off to 0
        (omniflow.paper.dct.band_window, a radial cos^2 window on the DCT
        coefficients); 0 is the sharp truncation of eq. (18) (the paper).
        The sharp truncation rings, and near the image centre, where the
        mirror compresses the texture tangentially, its ringing shrank the
        radial flow by 5-10 %; 0.5 (weight 1 up to half the band) gave radial
        gain 0.99-1.03 on the rendered and closed-form scenes, and 10-35 %
        lower EPE on the rendered ones and 2.7-8x on the closed-form room (on the
        closed-form striped wall, whose texture does not reach the band's
        edge, as before); docs/measurements.md, "radial shrink".
    flow_band_rule : {"gain", "variance"}
        With ``flow_band=None``: the widest band whose fitted gradient keeps
        ``flow_band_gain`` of its power as signal
        (omniflow.fit.noise.predicted_gain), or the widest whose predicted flow
        variance (omniflow.fit.noise.predicted_variance) is within
        ``flow_band_tolerance`` of the least; docs/measurements.md compares
        the two rules.
    flow_band_tolerance : float
        ``flow_band_rule="variance"``: the factor over the least variance allowed.
    flow_band_gain : float
        ``flow_band_rule="gain"``: the least predicted signal share of the
        gradient power the chosen band keeps.
    noise_sigma : float or None
        Standard deviation of the image noise, grey levels (images in
        [0, 1]); None: Immerkaer's estimate on each unit's frame t
        (omniflow.fit.noise.immerkaer_sigma; it also counts fine texture, so it
        errs high). Used by ``flow_band=None`` and ``eiv="correct"``.
    eiv : {"correct", "none"}
        Errors-in-variables correction of the pooled solver: the expected
        contribution of gradient noise (omniflow.fit.noise.gradient_noise_variance
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
        patch_radius / 16 (33 samples per profile).
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
        bring both units to one angular resolution; 0 disables it.
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
        (the default; docs/measurements.md has its effect and cost).
    alias_score : float
        Robust matcher: periodic-alias test (omniflow.matching.robust): drop a
        match whose image-1 profile recurs on its own line (NCC above this,
        after falling below 0 at a smaller lag) within the disparity window's
        width; 1 disables it. Cheaper than self_similarity (only the matches
        that passed the other tests are compared) and on by default.
    alias_image2 : float
        Robust matcher: the alias test (omniflow.matching.periodic) drops a
        match whose profile recurs at lag L only when image 2 holds the alias
        too (NCC with image 2's profile at h_2 +- L above this). On low
        texture a lone step edge recurs in image 1 with no alias in image 2.
        <= -1: any recurrence drops the match (the rule before).
    alias_period : float
        Robust matcher: where image 2's columns a recurrence away are past
        its rim, the match is dropped only when its profile also recurs at a
        second lag with NCC above this (a period, not a lone recurrence).
    flatness : float
        Robust matcher: keep a match only when its NCC peak is sharp enough
        to place to sub-pixel, (1 - NCC_peak) <= flatness x the peak's
        curvature (omniflow.matching.tables.sharp_peak); 0 disables it.
        Most 1-2 px errors on rendered frames have flat peaks.
    dense_percentile : float
        Robust matcher: also match the samples whose |df1/dh_1| is above this
        percentile near each match on its line, at that match's disparity
        (omniflow.matching.dense); 100 disables it (the default: edges only).
        60 gives ~4 % of the valid pixels on the rendered scenes, but with
        the pooled solver's default pool (the ``pool_k`` nearest) the flow is
        less accurate and the step ~3x slower (docs/measurements.md,
        "Matching"); with ``pool_grid`` the pools keep their area and the
        flow is more accurate than without the densification ("Density").
    dense_reach : float
        Robust matcher: how far along the line a match's disparity is tried
        on its neighbours, in patch radii.
    dense_smooth : float
        Robust matcher, densified matches only: drop one whose image-1
        profile has an NCC above this with itself half a profile radius away
        (omniflow.matching.dense.smooth_profiles): a profile smooth over its
        own length correlates with image 2 almost as well off the truth as
        at it. 1 disables it (the default); the dense preset sets 0.95: on
        low_texture's plain walls the densified matches it drops were all
        13-15 px off (docs/measurements.md, "Dense preset on low_texture").
    edge_smooth : float
        Robust matcher: the same test on the search's own matches, before the
        consistency vote (omniflow.matching.radial.match_radial); 1 disables
        it. Default 0.95, with ``edge_smooth_floor``: alone it also drops
        correct matches on independent_movers' ball, whose curved shading is as
        smooth over a profile as a plain wall's ramp.
    edge_smooth_floor : float or None
        Pooled solver, with ``edge_smooth``: keep its smooth matches to the flow
        step and drop only those whose pooled system's conditioning (the
        ``confidence`` column) is below this: a ramp across the pool too (its
        gradients all parallel), which neither NCC nor the flow equations can
        place; the densified matches grown from a smooth match carry its flag
        (they sit at its disparity). None: drop every smooth match in the
        matcher. Default 0.015:
        on the five rendered scenes (3 pairs) the smooth matches 13-15 px off
        (all on low_texture's plain wall, whose radial gain they took from 1.01
        to 0.66) have 0.0022-0.0038, the 28 right ones 0.059-0.54; 0.015 is the
        geometric middle (docs/measurements.md, "low_texture's radial gain").
    short_patch : float
        Robust matcher: a second pass with profiles this fraction of
        patch_radius long, adding matches where the first left none (small
        and inclined objects: the ring of independent_movers); 0 disables it.
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
        Pooled solver: most neighbours, the point itself included
        (docs/measurements.md has 48 against 24).
    pool_grid : float or None
        Pooled solver: pool by filtering on a grid (omniflow.solve.gridpool)
        with cells of this fraction of ``pool_radius``, so each pool holds
        every match within the radius (not the ``pool_k`` nearest) at a cost
        that does not grow with the number of matches; points whose window
        mixes ranges (``pool_range_tol``) keep the k-d tree's pools. Only for
        the one-pass equal-weight solver: an error with any knob of
        :data:`TREE_ONLY` set, or with ``brightness_model="linear"``. The
        decoupling test (``decouple_tol``) pools over the same grid windows.
        None: the k-d tree everywhere.
    pool_range_tol : float or None
        Pooled solver: neighbours whose range differs by more than this
        fraction (another surface) are left out; None keeps them.
    pool_flow_tol : float or None
        Pooled solver: solve twice, and in the second pass leave out the
        neighbours whose first-pass flow differs from the point's by more
        than this, cam1 pixels per frame (a mover keeps its own motion where
        its range does not set it apart from the background); None: one pass.
    pool_edge_tol : float or None
        Pooled solver: leave out the neighbours separated from the point by
        an image edge stronger than this many times the typical edge at the
        matches (the largest gradient magnitude of the flow step's fitted
        cam1 image on the segment between them, against its median at the
        matches; omniflow.solve.pooled.edge_between): an object's outline bounds the
        pool where it is a stronger edge than the texture. None: no test.
        Off by default: on the rendered scenes the range test already keeps
        the movers' pools on the movers, and the edge test only thins the
        pools (docs/measurements.md, "Pooling that respects objects").
    pool_residual_tol : float or None
        Pooled solver: solve twice, and in the second pass leave out the
        neighbours whose own eq. (9) and (15) miss the point's first-pass
        flow by more than this many robust standard deviations of the
        residuals (omniflow.solve.pooled.consistent_neighbours): another motion, or
        another surface. None: one pass (unless ``pool_flow_tol``).
    pool_min_info : float or None
        Pooled solver: adapt each pool's size to the local texture; the pool
        grows over the neighbours, nearest first, until the weaker direction
        of its normal matrix holds this many typical points' information
        (omniflow.solve.pooled.informative_pools), so rich texture pools a few close
        neighbours and poor texture all of them. None: every neighbour.
    pool_model : {"linear", "constant"}
        Pooled solver: local flow model (omniflow.solve.pooled.pooled_solution),
        varying linearly with theta or constant.
    pool_unit_weighting : {"equal", "global", "local"}
        Pooled solver: weight of each unit's equations, eq. (9) against
        eq. (15) (omniflow.solve.pooled.pooled_solution): alike, or by the inverse of
        each unit's residual variance, one figure per unit ("global") or
        measured around each point ("local"). "equal" is the default: with
        the default roll-off "local" halves the mean EPE on closed-form
        frames and gains 0-5 % on the rendered ones, but at a motion boundary
        it pulls the mover further towards the background (closed-form band:
        0.70 of its flow against 0.75) and cancels ``pool_residual_tol``
        (0.64 against 0.82); it halves the radial error where one unit is
        noisier (docs/measurements.md, "radial shrink"). Costs a second solve.
    static_test : float or None
        Pooled solver: report zero flow at the points whose pool shows no
        motion: where the squared residual of eq. (9) and (15) that the
        pool's flow explains is below this many times the pool's remaining
        residual variance per equation (a Wald test of zero flow, the noise
        measured in the pool itself; omniflow.solve.pooled.motion_statistic). With
        independent equations the statistic of a still pool is chi-squared
        with 2 degrees of freedom (mean 2); neighbouring matches share the
        fitted images' noise, which inflates it. It removes the noise of the
        flow where nothing moves (a robot standing still), and shrinks to
        zero true flows too small for the pool to detect. None (the default):
        no test (docs/measurements.md, "cam2 against DIS").
    static_max_px : float or None
        With ``static_test``: call a pool still only where it would have
        detected a flow of this many pixels per frame (cam1): sqrt(static_test)
        times the standard error of its flow along the weakest direction is
        at most this. Bounds the flow the test can set to zero; a pool too
        poor in texture keeps its estimate. None: no bound.
    min_conditioning : float
        Drop points whose confidence is below this (0 keeps all).
    pool_min_conditioning : float
        Pooled solver: the floor of ``min_conditioning`` for the pooled
        system (the larger of the two applies). Default 1e-3: a pool that
        near-singular is not a measurement (one short-profile match with
        too few neighbours gave 225 px of flow on the 512 px approach
        render); it drops 0-3 of ~2500 points per 512 px scene. 0.01 also
        drops good points on anisotropic texture (closed-form striped walls,
        whose pools are legitimately ill-conditioned along the stripes);
        docs/measurements.md, "Matching defaults after the merge".
    decouple_tol : float or None
        Pooled solver: report a point decoupled (result column ``coupled``
        0) where the two units' equations cannot share one radial flow,
        eq. (14) failing (motion along the axis: a rolling or tumbling
        object's texture): the F statistic of a separate radial flow per
        unit over the point's pool above this (omniflow.solve.decoupled). There
        dh1_dt, dh2_dt and dtheta_dt come from eq. (9) and (10) with one
        shared dtheta/dt, and dr_dt from both radial flows. None: every
        point coupled (the paper's model). 20 switches no point of the
        default, approach and crossing renders (the largest F there is
        19) and 41 of the 47 points on the ball of independent_movers;
        docs/measurements.md, "Movers: decoupled radial flow".
    brightness_gate : float or None
        Pooled solver: a brightness gain per pool (omniflow.solve.gain), eq. (9) and
        (15) of every neighbour written f_h a + f_theta b + f_t = beta f (f the
        image at the point, beta one unknown per pool shared by both units),
        taken only by the pools whose F statistic of beta against the plain
        solve exceeds this; the others keep the plain answer. For surfaces
        whose brightness changes as they move (a face driving towards a lamp,
        a body turning under fixed lights), which brightness constancy
        (eq. 8) reads as flow. Applies in the first solve, the refinement and
        the decoupled model. None: off. 20 (the default) fixes
        approach's incoming face (radial flow +3.0 % -> -1.1 %, time to
        contact's median error 4.0 -> 2.3 %) and most of the ball's radial
        flow (53 -> 79 %), at +2 % static mean error on crossing (equal
        median) and none on default and low_texture, for 1-3 ms a pair
        (compiled sums, omniflow.solve.gain_kernels.gain_sums). With grid pools
        (``pool_grid``, the dense preset) the gain fit and its test use the
        grid's windows: there 20 takes approach's time-to-contact error 4.2 ->
        1.7 % and the ball's radial flow 45 -> 87 %, static scenes unchanged.
        A fitted |beta| below omniflow.solve.gain.MIN_CHANGE (0.2 % per frame) is
        never taken (model error, not a change). Off in the paper's
        configuration (eq. 8 as written); docs/measurements.md,
        "brightness_gate: the gated gain term built" and "brightness_gate
        made cheap, and the default".
    brightness_model : {"linear", "gain"}
        With ``brightness_gate``: the brightness change of the coupled pools (eq. 14
        kept; the first solve and the refinement). "gain": one gain per pool,
        beta f_j. "linear" (the default): a gain varying linearly across the pool,
        (beta + beta_u u_j + beta_h dh_j) f_j (u_j, dh_j the tangential and radial
        offsets of neighbour j over the pool radius), taken where the F statistic of
        its three columns against the plain fit exceeds ``brightness_gate``, with at
        least omniflow.solve.gain.MIN_RESIDUAL_DOF residual degrees of freedom and a term of
        at least omniflow.solve.gain.MIN_GAIN_CHANGE; a pool whose one gain passes keeps it unless
        the two slopes' own F against it passes too. For texture turning through
        shading that stays put (independent_movers' spinner: no level, a gradient
        across the pool): its mean-flow error 10.5 / 11.1 % -> 4.1 / 4.3 % (cam1 /
        cam2; tangential gain 0.89 -> 0.96), every other mover and every static
        figure of the five rendered scenes unchanged to the printed digits, for about
        1.5-2.5 ms more solve a pair (its 7 x 7 sums). The k-d tree pools only: with
        grid pools (``pool_grid``, the dense preset) "linear" is an error (they fit
        one gain per pool).
        docs/measurements.md, "The spinner's linear gain".
    decouple_gain_tol : float or None
        Pooled solver, with ``decouple_tol``: after the two-model test and the
        gain, test eq. (14) again with a brightness gain varying linearly across
        the pool, (beta + beta_u u_j + beta_h dh_j) f_j, in both models' fits
        (omniflow.solve.gain.decoupled_linear_gain), and report decoupled, with that
        model's flow (without the gain where it does not matter:
        omniflow.solve.gain.MIN_GAIN_F, MIN_GAIN_CHANGE), the points whose F
        statistic of the axial share U exceeds
        this (half of it on pools at a range edge, omniflow.solve.decoupled.EDGE_GATE),
        where at least 4 residual degrees of freedom estimate the variance
        (omniflow.solve.gain.MIN_RESIDUAL_DOF) and the coupled fit's residual is at
        least twice the decoupled one's (omniflow.solve.gain.MIN_RESIDUAL_RATIO: F
        grows with the pool's rows for the same relative misfit). For a body turning
        about a tilted axis under fixed lights (independent_movers' ring and
        ball): its texture moves along the axis and its shading changes across a
        pool, which inflates both fits of the plain test so that it misses them.
        20 (the default) takes the ball's mean-flow error from 21 to 2.5 % and
        the ring's from 64 to 32 % (cam1; independent_movers' cam1 radial gain
        0.83 -> 0.95) and switches no static point of approach, crossing,
        default, independent_movers or low_texture (every static figure
        unchanged), for about 3 ms of solve a pair (the 6 x 6 sums). None: off,
        and off in the paper's configuration (eq. 14 as written); with
        ``decouple_tol`` None (no test of eq. 14 at all) it does nothing. The
        dense preset sets 60, as its ``decouple_tol`` (its larger pools make F
        larger for the same misfit; 20 and 60 answer the same there, the
        residual ratio deciding). docs/measurements.md, "decouple_gain_tol: eq.
        (14) tested with a linear gain, built" and "decouple_gain_tol gated, and
        the default". Its fits use the k-d tree pools also with ``pool_grid``,
        searched there only at the points a test on the grid's windows says may
        pass (omniflow.solve.decoupled.screen; "The linear-gain test screened on the
        grid").
    flow_shading : float or None
        Fit the flow step's series to each frame divided by its Gaussian
        local mean of this many pixels (omniflow.solve.shading), so that shading
        that stays put while a curved body turns (a rolling ball, a spinning
        pillar) does not shorten its flow; the matcher keeps the frames as
        given. None: the frames as given. Costs a second fit of both units.
        :func:`omniflow.pipeline.estimate` only (OmniFlowStream ignores it).
    flow_shading_where : {"everywhere", "moving"}
        With ``flow_shading``: the flattened frames' flow at every point
        ("everywhere"), or only at the points of independently moving objects
        ("moving": odometry's outliers on the plain flow, in groups of at least
        ``omniflow.solve.shading.MOVING_MIN_POINTS`` linked within r_m / 10 px;
        omniflow.solve.shading.moving_points), the plain flow elsewhere. On static
        surfaces under static lights the shading moves with the surface and
        flattening only removes signal; on a body turning under those lights it
        stays put (docs/measurements.md, "Ball, ring and spinner"). Costs a
        second solve as well.
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
        gradients="average"), and eq. (9) and (15), linearised about each
        point's own flow, are solved again (same solver) for the total flow.
        0 is the paper's single first-order step of eq. (8); the paper does
        not iterate. The default, 1 with
        ``iterate_min_px`` 1.0, refines only where a surface moves at least
        a pixel, where the first-order step overstates the motion (the
        crossing box by 8-9 %); every point refined (``iterate_min_px`` 0)
        hurts where noise, not the linearisation, is the error
        (docs/measurements.md, "Large motion: refine where it moves" and
        "The refinement solved for the total flow").
    iterate_min_px : float
        With ``iterations`` > 0: refine only the points whose first-step
        flow moves them at least this many pixels in cam1 or cam2 and that
        have 8 such points within the pool radius (a moving surface, not a
        stray wrong match), each linearised about its own first flow and
        solved for the total flow with the pools of the first solve, the
        series evaluated exactly (:mod:`omniflow.solve.refine`); with the pooled
        solver only (the direct solution's fast points are mostly its
        ill-conditioned failures, from which the step diverges). The first-order step
        overstates a large motion (by about (k d)^2 / 12 for a texture
        wavenumber k and displacement d); the refinement removes that where
        it matters and leaves the small flows, where it adds only noise,
        alone. 0: every point refined, read off pixel grids.
    monocular_gap : float or None
        Also solve cam1's eq. (9) alone, pooled over its neighbours like the
        stereo solve, at significant cam1 points farther than this (px) from
        every stereo match (:mod:`omniflow.solve.monocular`): flow without range
        where the matcher has no answer, e.g. an object outside cam2's view
        (the crossing pillar). Returned as :attr:`OmniFlowResult.monocular`
        (the ``omniflow`` CLI writes monocular.csv). None (default): off.
        The tangential flow is the reliable component; the radial is weakly
        determined by cam1 alone (docs/measurements.md, "cam1-only flow").
    rim_fill : {"reflect", "none"}
        Before the DCT fit, replace the pixels beyond the mirror's rim by the
        image reflected radially about the rim ("reflect"), or keep them
        ("none", the paper). The step at the rim otherwise rings through the
        truncated series (Gibbs) some 20 px into the image.
    """

    band: float = 0.5
    match_band: float | None = None
    flow_band: float | None = 0.5
    flow_taper: float = 0.5
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
    tangential_blur: float = 0.02
    consistency: float = 1.0
    consistency_support: int = 2
    self_similarity: float = 1.0
    alias_score: float = 0.9
    alias_image2: float = 0.9
    alias_period: float = 0.8
    flatness: float = 0.5
    dense_percentile: float = 100.0
    dense_reach: float = 1.0
    dense_smooth: float = 1.0
    edge_smooth: float = 0.95
    edge_smooth_floor: float | None = 0.015
    short_patch: float = 0.5
    gradients: str = "average"
    temporal: str = "difference"
    temporal_frames: int = 3
    solver: str = "pooled"
    pool_radius: float | None = None
    pool_k: int = 48
    pool_grid: float | None = None
    pool_range_tol: float | None = 0.1
    pool_model: str = "linear"
    pool_flow_tol: float | None = None
    pool_unit_weighting: str = "equal"
    pool_edge_tol: float | None = None
    pool_residual_tol: float | None = None
    pool_min_info: float | None = None
    static_test: float | None = None
    static_max_px: float | None = None
    min_conditioning: float = 0.0
    pool_min_conditioning: float = 1e-3
    decouple_tol: float | None = 20.0
    brightness_gate: float | None = 20.0
    brightness_model: str = "linear"
    decouple_gain_tol: float | None = 20.0
    flow_shading: float | None = None
    flow_shading_where: str = "everywhere"
    sampling: str = "cubic"
    iterations: int = 1
    iterate_min_px: float = 1.0
    monocular_gap: float | None = None
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
            "pool_unit_weighting": (self.pool_unit_weighting, UNIT_WEIGHTINGS),
            "eiv": (self.eiv, EIVS),
            "flow_band_rule": (self.flow_band_rule, BAND_RULES),
            "flow_shading_where": (self.flow_shading_where, SHADING_WHERE),
            "brightness_model": (self.brightness_model, BRIGHTNESS_MODELS),
        }
        for name, (val, allowed) in checks.items():
            if val not in allowed:
                raise ValueError(f"OmniFlowConfig.{name} = {val!r}: expected one of {allowed}")
        if not 0.0 <= self.flow_taper <= 1.0:
            raise ValueError(
                f"OmniFlowConfig.flow_taper = {self.flow_taper!r}: expected a fraction in [0, 1]"
            )
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
        for name in ("pool_edge_tol", "pool_residual_tol", "pool_min_info", "pool_grid",
                     "static_test", "static_max_px", "brightness_gate",
                     "decouple_gain_tol"):  # fmt: skip
            val = getattr(self, name)
            if val is not None and not val > 0:
                raise ValueError(f"OmniFlowConfig.{name} = {val!r}: expected > 0 or None")
        if self.noise_sigma is not None and not self.noise_sigma >= 0:
            raise ValueError(
                f"OmniFlowConfig.noise_sigma = {self.noise_sigma!r}: expected >= 0 or None"
            )
        if not (0 <= self.short_patch < 1):
            raise ValueError(f"OmniFlowConfig.short_patch = {self.short_patch!r}: expected [0, 1)")
        if not (0 <= self.dense_percentile <= 100 and self.dense_reach > 0 and self.flatness >= 0):
            raise ValueError(
                f"OmniFlowConfig.dense_percentile = {self.dense_percentile!r}, dense_reach = "
                f"{self.dense_reach!r}, flatness = {self.flatness!r}: expected [0, 100], > 0, >= 0"
            )
        if not (-1.0 <= self.edge_smooth <= 1.0):
            raise ValueError(
                f"OmniFlowConfig.edge_smooth = {self.edge_smooth!r}: expected an NCC in [-1, 1]"
            )
        if self.edge_smooth_floor is not None and not (0.0 <= self.edge_smooth_floor <= 1.0):
            raise ValueError(
                f"OmniFlowConfig.edge_smooth_floor = {self.edge_smooth_floor!r}: expected a "
                "conditioning in [0, 1] or None"
            )
        if not (-1.0 <= self.dense_smooth <= 1.0):
            raise ValueError(
                f"OmniFlowConfig.dense_smooth = {self.dense_smooth!r}: expected an NCC in [-1, 1]"
            )
        if self.temporal_frames < 3:
            raise ValueError("OmniFlowConfig.temporal_frames must be >= 3")
        if not (self.iterate_min_px >= 0.0):
            raise ValueError(
                f"OmniFlowConfig.iterate_min_px = {self.iterate_min_px!r}: expected >= 0 (pixels)"
            )
        if self.monocular_gap is not None and not (self.monocular_gap >= 0.0):
            raise ValueError(
                f"OmniFlowConfig.monocular_gap = {self.monocular_gap!r}: expected >= 0 (pixels) "
                "or None"
            )
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
        self._check_combinations()

    def _check_combinations(self) -> None:
        """Raise naming both knobs where one would silently cancel the other."""
        if self.pool_grid is None:
            return
        for name, off in TREE_ONLY.items():
            if getattr(self, name) != off:
                raise ValueError(
                    f"OmniFlowConfig.pool_grid = {self.pool_grid!r} with {name} = "
                    f"{getattr(self, name)!r}: {name} needs the k-d tree's pools; set "
                    f"pool_grid=None or {name}={off!r}"
                )
        if self.brightness_gate is not None and self.brightness_model != "gain":
            raise ValueError(
                f"OmniFlowConfig.pool_grid = {self.pool_grid!r} with brightness_model = "
                f"{self.brightness_model!r}: grid pools fit one gain per pool; set "
                "brightness_model='gain' or pool_grid=None"
            )

    @classmethod
    def preset(cls, name: str, **overrides) -> OmniFlowConfig:
        """The named preset of :data:`PRESETS` ("default", "dense", "paper") with
        ``overrides`` changed."""
        if name not in PRESETS:
            raise ValueError(f"preset {name!r}: expected one of {tuple(PRESETS)}")
        return cls(**{**PRESETS[name], **overrides})

    @classmethod
    def paper(cls, **overrides) -> OmniFlowConfig:
        """The paper's choices, as written.

        Gradient-similarity matching (section 5.2), P = X/4 for the matching
        and the flow step alike, the image as it is (no rim fill), the series
        and its analytic derivatives evaluated exactly at the points (eq.
        18-20), first-frame gradients, the frame difference of the fitted
        images for f_t and the direct solution of eq. (16) at each point, once
        (no Gauss-Newton step); no noise correction, no brightness gain
        (eq. 8 as written) and no test of eq. (14) with a gain. tests/omniflow/test_flow.py
        checks that this reproduces eq. (16), (19) and (20) computed
        independently to rounding.

        Why it fails under noise: eq. (9) and (15) at one point are nearly
        dependent, because both units see nearly the same patch at the same
        scale (f2_h ~ f1_h, f2_theta ~ f1_theta), so D of eq. (16) is
        ~ f_h f_theta (1 - h_2/h_1) and the radial flow rests on the small
        difference f2_t - f1_t divided by it. Noise in the temporal
        derivatives and in the gradients is divided by that small D: the
        2x2 solve is ill-conditioned, and its error grows as its conditioning
        falls (tests/omniflow/test_flow.py measures this on noisy closed-form frames).
        """
        return cls.preset("paper", **overrides)

    @classmethod
    def dense(cls, **overrides) -> OmniFlowConfig:
        """The densified configuration: more matches beyond the edges, grid pools.

        Matches beyond the edges (``dense_percentile`` 60) whose profiles are
        not smooth over their own length (``dense_smooth`` 0.95), the pooled
        solver's sums on a grid (``pool_grid`` 0.125), the decoupling test at
        ``decouple_tol`` 60 (at 20 the larger pools switch static points) and
        its linear-gain test at ``decouple_gain_tol`` 60, with the default's
        Gauss-Newton step where a surface moves at least a pixel, and the
        default's brightness gain (on the grid's windows). About ten times the
        default's points (4 % of the valid pixels of the rendered scenes against
        0.4 %) and a smaller error on every rendered scene, at about three times
        DIS medium's time per pair (2.8-3.8x measured at stop 21, with its
        linear-gain test's k-d tree search and sums made only where a test on
        the grid's windows says the tree's may pass, omniflow.solve.decoupled.screen:
        11 % of the points; 4 of the 487 switched points on 15 rendered pairs
        lost, no figure changed; docs/measurements.md, "The dense preset",
        "The linear-gain test screened on the grid" and "Speed: the dense
        preset's pool fits on both threads"). Not the default
        because of that time: the default answers within about DIS medium's time
        (issue 10).
        """
        return cls.preset("dense", **overrides)

    @property
    def grid_pools(self) -> bool:
        """Whether the pools are grid filters (``pool_grid``, omniflow.solve.gridpool); the
        knobs that thin each pool by its neighbours (:data:`TREE_ONLY`) cannot be set with
        it."""
        return self.pool_grid is not None

    def replace(self, **changes) -> OmniFlowConfig:
        """A copy with some fields changed."""
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}
