"""Streaming omni flow: one stereo frame at a time, each frame fitted once.

A robot sees a sequence. :func:`omniflow.pipeline.estimate` on the pair
(t, t + 1) fits both frames of both units, evaluates their grids, matches on
frame t and solves; on the next pair (t + 1, t + 2) it would fit frame t + 1
again. Everything the flow step takes from a pair is linear in the per-frame
DCT fits (eq. 17-20): the averaged gradient of ``gradients="average"`` is the
mean of the two frames' gradient grids, and f_t is the series of the
difference of their coefficients. :class:`OmniFlowStream` therefore keeps one
:class:`StereoFrame` per time step (the fit of each unit at the widest band
the configuration needs, its noise level, and its grids made on demand, at
most once per band) and builds each pair from the previous frame and the new
one. The stereo matches of a pair are those of its first frame, made once.

The result of :meth:`OmniFlowStream.push` equals ``estimate`` on the same two
frames to floating-point tolerance (the gradient mean is taken on float32
grids instead of on the coefficients; the matches, the pools and f_t are the
same computation). Nothing is kept beyond the previous frame, so memory does
not grow with the length of the sequence.

``temporal="dct3d"`` fits a 3-D series over ``temporal_frames`` frames and has
no per-frame fit to reuse: the stream then keeps the last ``temporal_frames``
frames and returns, for each new one, ``estimate`` on that window for the last
pair (the causal window: a live stream cannot look ahead).
"""

from __future__ import annotations

import collections
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omniflow.config import OmniFlowConfig
from omniflow.fit.series import (
    Frame,
    choose_flow_band,
    fit_band,
    grey_input,
    needs_noise_sigma,
    noise_variance,
    truncate,
    unit_noise_sigma,
)
from omniflow.geometry.rig import Rig, Unit
from omniflow.paper.dct import DCTFit, fit_dct
from omniflow.parallel import map_tasks, submit
from omniflow.pipeline import (
    estimate,
    flow_grids,
    matching_grid,
    predicted_sigmas,
    stereo_matches,
)
from omniflow.registration import Rectifier, has_errors
from omniflow.result import OmniFlowResult, no_points
from omniflow.solve.at_matches import flow_at_matches
from omniflow.solve.monocular import add_monocular

__all__ = ["OmniFlowStream", "StereoFrame"]


class _UnitFrame:
    """One unit at one time step: its DCT fit, noise level and grids per band."""

    def __init__(self, fit: DCTFit, unit: Unit, sigma: float, image: NDArray):
        self.fit, self.unit, self.sigma = fit, unit, sigma
        self.image = image  # the frame as pushed, for the noise of the predicted sigmas
        self._frames: dict[tuple[float, float], Frame] = {}

    def frame(self, band: float, taper: float = 0.0) -> Frame:
        """The fit truncated to ``band`` and rolled off by ``taper`` (omniflow.fit.series.truncate),
        as a lazy-grid frame made once per (band, taper)."""
        fr = self._frames.get((band, taper))
        if fr is None:
            fr = self._frames[band, taper] = Frame(truncate(self.fit, band, taper), self.unit)
        return fr


class StereoFrame:
    """Both units at one time step, fitted once: what a stream keeps between pushes.

    Built by :meth:`OmniFlowStream.push`; holds per unit the DCT fit at the
    widest band the configuration needs (eq. 17), the image noise where the
    configuration uses it, the grids made so far (each at most once per
    band) and the flow band chosen for the pair that starts here.
    """

    def __init__(self, frame1: ArrayLike, frame2: ArrayLike, rig: Rig, config: OmniFlowConfig,
                 index: int):  # fmt: skip
        self.index = index
        need_sigma = needs_noise_sigma(config)

        def fit(what, frame, unit):
            image = grey_input(frame, f"{what} of push {index}", unit, config)
            sigma = unit_noise_sigma(frame, unit, config) if need_sigma else 0.0
            return _UnitFrame(fit_dct(image, band=fit_band(config)), unit, sigma, np.array(frame))

        units = map_tasks(fit, ("frame1", frame1, rig.cam1), ("frame2", frame2, rig.cam2))
        self.units: tuple[_UnitFrame, _UnitFrame] = (units[0], units[1])
        self.flow_band = choose_flow_band(
            [{"a": u.fit} for u in self.units], [u.sigma for u in self.units], config
        )
        self.matching: Future | None = None  # the background matching, if any


class OmniFlowStream:
    """Omni flow of a live sequence: push one stereo frame, get the flow since the last.

    Parameters
    ----------
    rig : Rig
        The coaxial pair; every frame must have its units' sizes.
    config : OmniFlowConfig, optional
        Defaults to ``OmniFlowConfig()``. Any configuration works;
        ``temporal="dct3d"`` runs :func:`~omniflow.pipeline.estimate` on a
        window of the last ``temporal_frames`` frames (no per-frame reuse).
    background : bool
        Match each new frame in a background thread as soon as it is pushed
        (its matches are needed only by the next push), while the caller
        goes on: :meth:`push` then costs the fit, the sampling and the solve,
        and the matching of a frame overlaps the wait for the next one and
        that frame's fit. The results are the same; an error in the matching
        is raised by the next push. Call :meth:`close` (or use the stream as a
        context manager) to end the thread.

    Examples
    --------
    >>> stream = OmniFlowStream(rig)                      # doctest: +SKIP
    >>> for cam1, cam2 in camera_frames():                # doctest: +SKIP
    ...     result = stream.push(cam1, cam2)              # None for the first frame
    """

    def __init__(self, rig: Rig, config: OmniFlowConfig | None = None, *, background: bool = False):
        # a rig with errors: each frame rectified to the ideal rig, results mapped back
        self._rect = Rectifier(rig) if has_errors(rig) else None
        self.rig = rig if self._rect is None else self._rect.ideal
        self.config = OmniFlowConfig() if config is None else config
        if (
            self.config.brightness.flow_shading is not None
        ):  # a second fit per frame, not kept here yet
            raise ValueError("flow_shading: not supported by OmniFlowStream; use estimate()")
        self._prev: StereoFrame | None = None
        window = self.config.fit.temporal_frames if self.config.fit.temporal == "dct3d" else 0
        self._window: collections.deque = collections.deque(maxlen=max(window, 1))
        self.frames_pushed = 0
        dct3d = self.config.fit.temporal == "dct3d"
        self._pool = ThreadPoolExecutor(1, "omniflow-match") if background and not dct3d else None

    def reset(self) -> None:
        """Forget the previous frame(s): the next push starts a new sequence."""
        if self._prev is not None and self._prev.matching is not None:
            self._prev.matching.cancel()
        self._prev = None
        self._window.clear()

    def close(self) -> None:
        """End the background thread (if any); the stream can still be used without it."""
        self.reset()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> OmniFlowStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def push(self, frame1: ArrayLike, frame2: ArrayLike) -> OmniFlowResult | None:
        """Add the next stereo frame; the flow from the previous frame to this one.

        Parameters
        ----------
        frame1, frame2 : ndarray, shape (H, W)
            Grey frames of cam1 and cam2 at the new time step.

        Returns
        -------
        OmniFlowResult or None
            None for the first frame after construction or :meth:`reset` (and,
            with ``temporal="dct3d"``, until ``temporal_frames`` frames are in).
            ``timings["fit"]`` is the new frame's fit; ``grids`` includes the
            gradient mean of the pair and the other grids the flow step
            samples (made here, the units in two threads, not while
            sampling); the other stages as in :func:`~omniflow.pipeline.estimate`.
        """
        if self._rect is not None:
            frame1, frame2 = self._rect.image(frame1, "cam1"), self._rect.image(frame2, "cam2")
            return self._rect.result(self._push(frame1, frame2))
        return self._push(frame1, frame2)

    def _push(self, frame1: ArrayLike, frame2: ArrayLike) -> OmniFlowResult | None:
        index = self.frames_pushed
        if self.config.fit.temporal == "dct3d":
            return self._push_window(frame1, frame2, index)
        t_start = time.perf_counter()
        cur = StereoFrame(frame1, frame2, self.rig, self.config, index)
        t_fit = time.perf_counter() - t_start
        self.frames_pushed += 1
        prev, self._prev = self._prev, cur
        if prev is None:
            result = None
        else:
            result = self._pair(prev, cur, t_start, t_fit)
        if self._pool is not None:  # cur's matches, for the next push, while the caller goes on
            cur.matching = self._pool.submit(_frame_matches, cur, self.rig, self.config)
        return result

    def _push_window(self, frame1, frame2, index: int) -> OmniFlowResult | None:
        for what, frame, unit in (("frame1", frame1, self.rig.cam1),
                                  ("frame2", frame2, self.rig.cam2)):  # fmt: skip
            grey_input(frame, f"{what} of push {index}", unit, self.config)  # shape check only
        self._window.append((np.array(frame1, copy=True), np.array(frame2, copy=True)))
        self.frames_pushed += 1
        if len(self._window) < self._window.maxlen:
            return None
        f1 = [a for a, _ in self._window]
        f2 = [b for _, b in self._window]
        return estimate(f1, f2, self.rig, self.config, t=len(f1) - 2)

    # -- one pair -----------------------------------------------------------------

    def _pair(self, prev: StereoFrame, cur: StereoFrame, t_start: float,
              t_fit: float) -> OmniFlowResult:  # fmt: skip
        config = self.config
        timings: dict[str, float] = {"fit": t_fit}
        flow_band = prev.flow_band
        t_m = time.perf_counter()
        if prev.matching is None:  # a frame starts one pair only: matched once, here
            # the pair's flow grids on the other thread while this one matches; every
            # Frame either reads is made here first, so the threads share no lazy dict entry
            for u in (*prev.units, *cur.units):
                u.frame(config.band)
                u.frame(flow_band, config.fit.flow_taper)
            flow = [submit(_unit_flow, a, b, config, flow_band)
                    for a, b in zip(prev.units, cur.units, strict=True)]  # fmt: skip
            try:
                matches, t_grids, t_match = _frame_matches(prev, self.rig, config)
            except BaseException:
                for task in flow:
                    task.cancel()
                raise
            timings["match"] = t_match
        else:  # matched in the background since prev was pushed: the wait is what counts
            matches, t_grids, t_match = prev.matching.result()
            prev.matching = None
            timings["match"] = time.perf_counter() - t_m
            timings["match_background"] = t_grids + t_match
            t_grids = 0.0
            # prev's frames are touched here only after its matching is done
            flow = [submit(_unit_flow, a, b, config, flow_band)
                    for a, b in zip(prev.units, cur.units, strict=True)]  # fmt: skip
        t_g = time.perf_counter()
        cams = [task.result() for task in flow]
        diagnostics = {"flow_band": flow_band, "noise_sigma1": prev.units[0].sigma,
                       "noise_sigma2": prev.units[1].sigma}  # fmt: skip
        timings["grids"] = t_grids + time.perf_counter() - t_g
        n_sig = matches.n_significant
        if len(matches.theta) == 0:
            return add_monocular(no_points(timings, t_start, config, n_sig), cams[0], self.rig.cam1)
        t_s = time.perf_counter()
        result = flow_at_matches(matches, self.rig, cams[0], cams[1], config)
        timings["sample"] = result.pop("_t_sample")
        timings["solve"] = time.perf_counter() - t_s - timings["sample"]
        timings["total"] = time.perf_counter() - t_start
        out = OmniFlowResult(columns=result, timings=timings, config=config,
                             n_significant=n_sig, diagnostics=diagnostics)  # fmt: skip
        frames = tuple((a.image, b.image) for a, b in zip(prev.units, cur.units, strict=True))
        out.defer_sigma(predicted_sigmas(result, frames, 0, self.rig, tuple(cams), config))
        return add_monocular(out, cams[0], self.rig.cam1)


def _frame_matches(frame: StereoFrame, rig: Rig, config: OmniFlowConfig):
    """(stereo matches of one frame, seconds for its grids, seconds for the matching)."""
    t0 = time.perf_counter()
    grids = tuple(map_tasks(lambda u: matching_grid(u.frame(config.band), config),
                            *((u,) for u in frame.units)))  # fmt: skip
    t1 = time.perf_counter()
    matches = stereo_matches(grids, rig, config)
    return matches, t1 - t0, time.perf_counter() - t1


def _unit_flow(a: _UnitFrame, b: _UnitFrame, config: OmniFlowConfig, flow_band: float) -> dict:
    """:func:`_unit_pair` with the grids the flow step samples made (pipeline.flow_grids)."""
    return flow_grids(_unit_pair(a, b, config, flow_band), config)


def _unit_pair(a: _UnitFrame, b: _UnitFrame, config: OmniFlowConfig, flow_band: float) -> dict:
    """One unit's series for the pair (a, b), keys as :func:`omniflow.pipeline.estimate`'s.

    ``a``: frame t at the matching band; ``af``, ``b``: frames t and t + 1 at the flow
    band, rolled off by ``config.fit.flow_taper``;
    ``g``: the gradient series (frame t's, or the mean of both frames: its
    gradient grids are the mean of theirs, each made once per frame); ``t``:
    the series of f_t, the coefficients' difference (eq. 17 is linear).
    """
    fa, fb = a.frame(flow_band, config.fit.flow_taper), b.frame(flow_band, config.fit.flow_taper)
    if config.fit.gradients == "first":
        g = fa
    else:
        g = Frame(replace(fa.fit, coeffs=0.5 * (fa.fit.coeffs + fb.fit.coeffs)), a.unit)
        if config.fit.sampling != "exact":  # the exact path evaluates g's series itself
            g._grad_xy = tuple(
                np.multiply(np.add(p, q), np.float32(0.5))
                for p, q in zip(fa.grad_xy, fb.grad_xy, strict=True)
            )
    ft = Frame(replace(fa.fit, coeffs=fb.fit.coeffs - fa.fit.coeffs), a.unit)
    cam = {"a": a.frame(config.band), "af": fa, "b": fb, "g": g, "t": ft}
    cam["noise_var"] = noise_variance(g.fit, config)
    return cam


def stream_frames(rig: Rig, pairs, config: OmniFlowConfig | None = None):
    """Yield (index, result) for each stereo frame of ``pairs`` after the first.

    ``pairs`` is an iterable of (frame1, frame2); ``index`` is the new frame's
    position in it (the flow runs from index - 1 to index).
    """
    stream = OmniFlowStream(rig, config)
    for k, (f1, f2) in enumerate(pairs):
        result = stream.push(f1, f2)
        if result is not None:
            yield k, result
