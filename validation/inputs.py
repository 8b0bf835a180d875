"""The images every method sees: one function makes them from the dataset's radiance.

Two sources, chosen once per run:

* **a camera model** (:mod:`omnisim.camera`): the dataset's own ``camera`` section
  of ``dataset.json`` (the camera the renderer recorded, whose images are the
  ``camN.png`` files), with ``--camera KEY=VALUE`` overrides, applied to the
  EXR's linear radiance at read time. One render, many cameras: the noise is
  fixed by (camera seed, frame, camera), so every method sees the same noisy
  frames and a sweep re-forms only the images.
* **no camera** (a dataset without a ``camera`` section and no overrides): the
  Rec. 709 luminance of the linear RGB, scaled once per dataset so that the
  99.5th percentile of frame 0's valid pixels maps to 255, rounded to 8 bits.

OpenCV takes 8-bit images, so the baselines get ``rint(255 * grey)``;
omniflow gets the float grey image (for an 8-bit camera or no camera, the same
8-bit values / 255).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.io.dataset import camera_grey, grey_of
from omnisim.camera import CameraError, CameraModel

__all__ = ["CAMERAS", "Inputs", "camera_model"]

CAMERAS = ("cam1", "cam2")


class InputError(ValueError):
    """The dataset or the request cannot be scored (the message says why)."""


def camera_model(
    meta: dict[str, Any], overrides: Sequence[str] = (), *, where: str = "dataset.json"
) -> Any:
    """The camera the methods' images come from, or None for the plain 8-bit luminance.

    ``meta`` is dataset.json; its ``camera`` section (if any) is the base, and
    ``overrides`` (``"read_noise=5"``, ...) change it. A dataset without a camera
    section gets the camera model's defaults, except that :class:`Inputs` sets the
    exposure as the plain path scales (the 99.5th percentile of frame 0's valid
    pixels fills the well) unless ``exposure`` is given. Raises
    :class:`InputError` (one line naming the key and the expected range) on a bad
    parameter, or a ``camera`` section that is not a table (``where`` names the file).
    """
    section = meta.get("camera")
    if section is not None and not isinstance(section, dict):
        # Not "no camera": scoring the plain luminance instead would hide the mistake.
        raise InputError(
            f"{where}: camera = {json.dumps(section)[:60]}: expected a table of "
            "camera parameters (or no camera section)"
        )
    if section is None and not overrides:
        return None
    try:
        base = CameraModel.from_mapping(section or {}, where="dataset.json camera")
        return base.with_overrides(list(overrides)) if overrides else base
    except CameraError as exc:
        raise InputError(str(exc).splitlines()[0]) from exc


class Inputs:
    """Grey frames of both cameras, made once per (frame, camera) and cached.

    Parameters
    ----------
    ds : omniflow.io.dataset.Dataset
    camera : omnisim.camera.CameraModel or None
        See the module docstring; :func:`camera_model` picks it.
    """

    def __init__(self, ds: Any, camera: Any = None, *, auto_exposure: bool = False):
        self.ds = ds
        self.camera = camera
        self.cache: dict[tuple[int, str], tuple[NDArray, NDArray]] = {}
        self.scale: float | None = None
        if camera is not None and auto_exposure:
            # No recorded camera: expose like the plain path, the 99.5th percentile of
            # frame 0's valid luminance at a full well.
            self._set_scale()
            self.camera = camera.with_overrides({"exposure": float(self.scale) / 255.0})

    def describe(self) -> str:
        """One sentence for the report: where the images come from."""
        if self.camera is None:
            return (
                "Rec. 709 luminance of the EXR radiance, scaled so that the 99.5th percentile "
                f"of frame 0's valid pixels is 255 (x {self.scale or 0:.4g}), rounded to 8 bits"
            )
        params = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in self.camera.to_dict().items())  # fmt: skip
        return f"camera model (omnisim.camera) applied to the EXR radiance: {params}"

    def _set_scale(self) -> None:
        vals = []
        for cam in CAMERAS:
            ch = self.ds.read_frame(0, cam)
            g = grey_of(ch)
            ok = (ch["gt.valid"] > 0.5) & np.isfinite(g)
            vals.append(g[ok] if ok.any() else g[np.isfinite(g)])
        v = np.concatenate(vals)
        top = float(np.percentile(v, 99.5)) if v.size else 0.0
        self.scale = 255.0 / top if top > 0 else 1.0

    def _make(self, k: int, cam: str, chans: dict[str, NDArray] | None) -> tuple[NDArray, NDArray]:
        chans = chans if chans is not None else self.ds.read_frame(k, cam)
        rgb = np.stack([chans["R"], chans["G"], chans["B"]], axis=-1)
        if not np.isfinite(rgb).all():
            bad = int(np.count_nonzero(~np.isfinite(rgb)))
            raise InputError(
                f"{self.ds.frame_path(k, cam) if hasattr(self.ds, 'frame_path') else cam}: "
                f"frame {k} {cam}: {bad} non-finite radiance values (NaN or inf); expected "
                "finite R, G, B"
            )
        if self.camera is None:
            if self.scale is None:
                self._set_scale()
            g = grey_of(chans)
            u8 = np.clip(np.rint(g * self.scale), 0, 255).astype(np.uint8)
            return u8, u8.astype(np.float32) / 255.0
        unit = self.ds.rig.cam1 if cam == "cam1" else self.ds.rig.cam2
        dn = self.camera.apply(rgb, frame=k, cam=cam, centre=(unit.x_c, unit.y_c), r_m=unit.r_m)
        grey = camera_grey(dn, self.camera.bits)  # what omniflow --dataset reads from camN.png
        u8 = np.clip(np.rint(grey * 255.0), 0, 255).astype(np.uint8)
        return u8, grey

    def frame(
        self, k: int, cam: str, chans: dict[str, NDArray] | None = None
    ) -> tuple[NDArray, NDArray]:
        """``(uint8 image for OpenCV, float32 grey image in [0, 1] for omniflow)``."""
        key = (k, cam)
        if key not in self.cache:
            self.cache[key] = self._make(k, cam, chans)
        return self.cache[key]

    def u8(self, k: int, cam: str, chans: dict[str, NDArray] | None = None) -> NDArray:
        return self.frame(k, cam, chans)[0]

    def grey(self, k: int, cam: str, chans: dict[str, NDArray] | None = None) -> NDArray:
        return self.frame(k, cam, chans)[1]

    def drop_before(self, k: int) -> None:
        for key in [key for key in self.cache if key[0] < k]:
            del self.cache[key]
