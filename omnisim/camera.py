"""The camera model: the image a real camera would record of the rendered radiance.

The renderer gives clean linear RGB radiance (kept in the EXR with the exact ground
truth). :class:`CameraModel` forms, after rendering, the digital image a camera with
known, recorded parameters would take of it. Each of R, G and B is treated as a
monochrome sensor with the same parameters (no Bayer mosaic). Per pixel and channel,
in this order:

1. **Vignetting** (optical): the irradiance is multiplied by the cos^4 law
   ``V(r) = (1 + a rho^2)^-2`` with ``rho = r / r_m`` the radius from the unit's image
   centre ``(x_c, y_c)`` in units of its rim radius ``r_m``, and ``a`` chosen so that
   ``V(r_m) = 1 - vignetting`` (``a = (1 - vignetting)^-1/2 - 1``; this is cos^4 of
   the field angle of a lens whose field angle at the rim is ``atan(sqrt(a))``).
2. **Defocus** (optical): a Gaussian blur of standard deviation ``defocus`` pixels
   (``cv2.GaussianBlur``, border reflected).
3. **Exposure**: the mean collected charge is ``mu = exposure * full_well * L``
   electrons for radiance ``L`` (W m^-2 sr^-1, linear). So ``exposure`` is the fraction
   of the full well that a radiance of 1 fills; it is one fixed number per dataset,
   so frames stay independent. The default 2.0 puts the mean radiance of the shipped
   scenes (0.12-0.26 in the mirror) at 25-51 % of full well (docs/decisions/camera_model.md).
4. **Photon shot noise**: the charge is Poisson distributed with mean ``mu``: drawn
   exactly (``numpy.random.Generator.poisson``) where ``mu`` < 1000 e-, and from a
   Gaussian of the same mean and variance above (its skewness 1/sqrt(mu) is then
   below 0.03; the Gaussian is four times faster); then clipped at ``full_well``
   (saturation).
5. **Read noise**: Gaussian, ``read_noise`` electrons rms, added to the charge.
6. **Gain and ADC**: the normalised signal is ``v = gain * charge / full_well``,
   clipped to [0, 1] (``gain`` is the unitless analog gain: 1 maps a full well to the
   largest digital number; above 1 the ADC saturates before the well does).
7. **Response**: ``"linear"`` keeps ``v``; ``"srgb"`` applies the sRGB transfer curve
   (IEC 61966-2-1) to ``v``.
8. **Quantisation** to ``bits`` bits: digital number ``DN = round(v (2^bits - 1))``.

The noise is a function of ``(seed, frame, cam)`` only (a NumPy PCG64 generator seeded
from them), so it is reproducible, differs from frame to frame and between the two
cameras, and does not depend on the order frames are rendered in.

The default is a good machine-vision camera: 8 bits, linear response, full well
20000 e-, read noise 5 e- rms, gain 1. At mid grey (``v = 0.5``, 10000 e-) the noise
is ``sqrt(10000 + 5^2) = 100.1`` e-, 1.0 % of the signal, 1.28 DN of 255 (1.31 DN
with the quantisation step's 1/sqrt(12) added).

This module needs only numpy (and OpenCV for the defocus blur); it does not import
Mitsuba, so readers of datasets can apply a camera to a stored radiance
(:func:`camera_image`): one render, many cameras. It is an image-formation model
usable on any linear image; it needs no Mitsuba, so validation scores camera images
without the ``sim`` extra.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omniflow.geometry.rig import Rig, RigError, rig_from_dict
from omniflow.io.dataset import CAMERA_BITS, Dataset, DatasetError
from omniflow.io.imageio import to_grey

__all__ = [
    "BITS",
    "RESPONSES",
    "CameraError",
    "CameraModel",
    "camera_from_meta",
    "camera_image",
    "dataset_camera",
    "parse_camera_overrides",
    "read_camera_dn",
    "read_camera_image",
    "srgb_encode",
]

#: Allowed bit depths of the digital numbers.
BITS = CAMERA_BITS  # the dataset format's (omniflow.io.dataset)
#: Allowed response curves.
RESPONSES = ("linear", "srgb")
#: Largest full well accepted (electrons); also keeps Poisson means far inside int64.
MAX_FULL_WELL = 1e12
#: Mean charge (electrons) below which shot noise is drawn exactly from a Poisson
#: distribution; at and above it from a Gaussian of the same mean and variance.
POISSON_EXACT_BELOW = 1000.0
#: Largest defocus sigma accepted (pixels).
MAX_DEFOCUS = 100.0


class CameraError(ValueError):
    """A camera parameter is unknown or out of range.

    The message is one line: ``"<where>: camera.<key> = <value>: expected <range>"``.
    ``where``, ``key``, ``value`` and ``expected`` are kept as attributes.
    """

    def __init__(self, where: str, key: str, value: Any, expected: str):
        self.where, self.key, self.value, self.expected = where, key, value, expected
        super().__init__(f"{where}: camera.{key} = {value!r}: expected {expected}")


@dataclass(frozen=True)
class CameraModel:
    """A camera's parameters (see the module docstring for the image formation).

    Attributes
    ----------
    exposure : float
        Fraction of the full well filled by a linear radiance of 1 W m^-2 sr^-1
        (``> 0``; default 2.0).
    full_well : float
        Full-well capacity in electrons (``(0, 1e12]``; default 20000).
    read_noise : float
        Read noise in electrons rms (``>= 0``; default 5).
    gain : float
        Unitless analog gain between the well and the ADC (``> 0``; default 1: a full
        well maps to the largest digital number).
    bits : int
        Bit depth of the digital numbers: 8, 10, 12 or 16 (default 8).
    response : str
        ``"linear"`` (default) or ``"srgb"``: the curve applied to the normalised
        signal before quantisation.
    vignetting : float
        Fraction of the light lost at the rim radius ``r_m`` (cos^4 law; ``[0, 1)``;
        default 0, none).
    defocus : float
        Standard deviation of the Gaussian defocus blur in pixels (``[0, 100]``;
        default 0, sharp).
    seed : int
        Seed of the noise (``>= 0``; default 0); independent of the render seed.
    shutter : float
        Fraction of the frame interval the shutter is open, centred on the frame's
        instant (``[0, 1]``; default 0, an instant). Not ``exposure``: it is the
        renderer's motion blur (:mod:`omnisim.exposure`), not a gain.
    """

    exposure: float = 2.0
    full_well: float = 20000.0
    read_noise: float = 5.0
    gain: float = 1.0
    bits: int = 8
    response: str = "linear"
    vignetting: float = 0.0
    defocus: float = 0.0
    seed: int = 0
    shutter: float = 0.0

    # -- construction ------------------------------------------------------------

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any], *, where: str = "camera") -> CameraModel:
        """A model from a mapping of parameters (a scene's ``[camera]`` table, dataset.json).

        Missing keys take the defaults. Raises :class:`CameraError` on an unknown key or
        a value of the wrong type or out of range.
        """
        if not isinstance(d, Mapping):
            raise CameraError(where, "", d, "a table of camera parameters")
        allowed = [f.name for f in fields(cls)]
        for key in d:
            if key not in allowed:
                raise CameraError(
                    where, str(key), d[key], "a known key (one of: " + ", ".join(allowed) + ")"
                )
        base = cls()
        kw: dict[str, Any] = {}
        for key, lo, hi, lo_open, hi_open, unit in _NUMBERS:
            if key in d:
                kw[key] = _number(where, key, d[key], lo, hi, lo_open, hi_open, unit)
        if "bits" in d:
            v = d["bits"]
            if isinstance(v, float) and v.is_integer():
                v = int(v)
            if isinstance(v, bool) or not isinstance(v, int) or v not in BITS:
                raise CameraError(where, "bits", v, "one of " + ", ".join(map(str, BITS)))
            kw["bits"] = int(v)
        if "response" in d:
            v = d["response"]
            if not isinstance(v, str) or v.lower() not in RESPONSES:
                raise CameraError(where, "response", v, "one of " + ", ".join(map(repr, RESPONSES)))
            kw["response"] = v.lower()
        if "seed" in d:
            v = d["seed"]
            if isinstance(v, float) and v.is_integer():
                v = int(v)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2**63:
                raise CameraError(where, "seed", v, "an integer in [0, 2^63)")
            kw["seed"] = int(v)
        return replace(base, **kw)

    def with_overrides(
        self, items: Iterable[str] | Mapping[str, Any], *, where: str = "--camera"
    ) -> CameraModel:
        """A copy with some parameters changed.

        ``items`` is a mapping ``{"read_noise": 5}`` or strings ``"read_noise=5"`` as given
        on a command line (the value is read as a TOML value; an unquoted word such as
        ``srgb`` is kept as a string; a ``camera.`` prefix on the key is accepted).
        Raises :class:`CameraError` on an unknown key or a value out of range.
        """
        changes = parse_camera_overrides(items, where=where)
        return CameraModel.from_mapping({**self.to_dict(), **changes}, where=where)

    def to_dict(self) -> dict[str, Any]:
        """Every parameter by name (JSON-safe); ``from_mapping(to_dict())`` round-trips."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    # -- image formation -----------------------------------------------------------

    @property
    def max_dn(self) -> int:
        """The largest digital number, ``2^bits - 1``."""
        return (1 << self.bits) - 1

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        """``numpy.uint8`` for 8 bits, else ``numpy.uint16``."""
        return np.uint8 if self.bits <= 8 else np.uint16

    def electrons(self, radiance: NDArray) -> NDArray[np.float64]:
        """Mean collected charge (electrons) for a radiance, before any noise (step 3)."""
        return np.asarray(radiance, dtype=np.float64) * (self.exposure * self.full_well)

    def rng(self, frame: int, cam: str, seed: int | None = None) -> np.random.Generator:
        """The noise generator of one frame and camera (a function of seed, frame, cam)."""
        s = self.seed if seed is None else int(seed)
        # The key names the model's first home (omnisim.camera); kept so datasets written
        # before the move get the same noise.
        key = f"omnisim.camera:{s}:{int(frame)}:{cam}".encode()
        words = np.frombuffer(hashlib.sha256(key).digest(), dtype="<u4")
        return np.random.Generator(np.random.PCG64(np.random.SeedSequence(words.tolist())))

    def optics(
        self,
        radiance: NDArray,
        *,
        centre: tuple[float, float] | None = None,
        r_m: float | None = None,
    ) -> NDArray[np.float32]:
        """Steps 1-2: vignetting and defocus blur of a radiance image (H, W) or (H, W, C).

        ``centre`` ``(x_c, y_c)`` and ``r_m`` (pixels) default to the image centre and
        half the shorter side.
        """
        img = np.asarray(radiance, dtype=np.float32)
        if img.ndim not in (2, 3):
            raise ValueError(f"radiance has shape {img.shape}: expected (H, W) or (H, W, C)")
        h, w = img.shape[:2]
        if self.vignetting > 0:
            x_c, y_c = centre if centre is not None else (w / 2.0, h / 2.0)
            rim = float(r_m) if r_m is not None else min(w, h) / 2.0
            a = (1.0 - self.vignetting) ** -0.5 - 1.0
            # Pixel (col, row) has its centre at (col + 0.5, row + 0.5) (omniflow.conventions).
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
            rho2 = ((xx - x_c) ** 2 + (yy - y_c) ** 2) / rim**2
            v = (1.0 + a * rho2) ** -2.0
            img = img * (v[..., None] if img.ndim == 3 else v).astype(np.float32)
        if self.defocus > 0:
            import cv2

            img = cv2.GaussianBlur(
                np.ascontiguousarray(img),
                (0, 0),
                sigmaX=self.defocus,
                sigmaY=self.defocus,
                borderType=cv2.BORDER_REFLECT,
            )
        return img.astype(np.float32, copy=False)

    def apply(
        self,
        radiance: NDArray,
        *,
        frame: int,
        cam: str,
        seed: int | None = None,
        centre: tuple[float, float] | None = None,
        r_m: float | None = None,
    ) -> NDArray[np.unsignedinteger]:
        """Digital numbers a camera records of a linear radiance image.

        Parameters
        ----------
        radiance : (H, W, 3) or (H, W) float
            Linear radiance (the EXR's R, G, B). Negative or non-finite values count as 0.
        frame, cam : the frame index and camera name; with ``seed`` they fix the noise.
        seed : overrides :attr:`seed` for this call.
        centre, r_m : the unit's image centre ``(x_c, y_c)`` and rim radius (pixels) for
            the vignetting; default the image centre and half the shorter side.

        Returns
        -------
        Same shape, ``uint8`` (8 bits) or ``uint16`` (10, 12, 16 bits), values in
        ``[0, 2^bits - 1]``.
        """
        img = np.nan_to_num(np.asarray(radiance, dtype=np.float32), nan=0.0, posinf=0.0)
        img = np.maximum(img, 0.0)
        img = self.optics(img, centre=centre, r_m=r_m)
        rng = self.rng(frame, cam, seed)
        # float32 throughout: its 24-bit mantissa resolves 1e-7 of the signal, far below
        # the shot noise (1e-6 of a full 1e12 e- well).
        mu = img * np.float32(self.exposure * self.full_well)
        # Shot noise: Gaussian with the Poisson's mean and variance where mu >= 1000 e-
        # (skewness 1/sqrt(mu) <= 0.03; 4x faster), exact Poisson below.
        charge = rng.standard_normal(mu.shape, dtype=np.float32)
        charge *= np.sqrt(mu)
        charge += mu
        low = mu < POISSON_EXACT_BELOW
        if low.any():
            charge[low] = rng.poisson(mu[low])
        np.minimum(charge, np.float32(self.full_well), out=charge)
        if self.read_noise > 0:
            read = rng.standard_normal(mu.shape, dtype=np.float32)
            read *= np.float32(self.read_noise)
            charge += read
        charge *= np.float32(self.gain / self.full_well)
        v = np.clip(charge, 0.0, 1.0, out=charge)
        if self.response == "srgb":
            v = srgb_encode(v)
        v *= np.float32(self.max_dn)
        return np.rint(v, out=v).astype(self.dtype)

    def to_float(self, dn: NDArray) -> NDArray[np.float32]:
        """Digital numbers -> float32 in [0, 1] (``DN / (2^bits - 1)``; the response is
        not undone, as an ordinary image reader would give it)."""
        return (np.asarray(dn, dtype=np.float32) / np.float32(self.max_dn)).astype(np.float32)

    def grey(self, dn: NDArray) -> NDArray[np.float32]:
        """The grey float image (H, W) of digital numbers: Rec. 709 luma of :meth:`to_float`."""
        return to_grey(self.to_float(dn))

    # -- files -----------------------------------------------------------------------

    def png_bytes(self, dn: NDArray) -> bytes:
        """A PNG of digital numbers: 8-bit for 8 bits; else 16-bit, scaled to the full
        16-bit range (``round(DN * 65535 / (2^bits - 1))``) so viewers and readers that
        divide by 65535 see the same brightness; :meth:`dn_from_png` undoes it exactly."""
        import cv2

        arr = np.asarray(dn)
        if self.bits > 8:
            arr = np.rint(arr.astype(np.float64) * (65535.0 / self.max_dn)).astype(np.uint16)
        else:
            arr = arr.astype(np.uint8)
        if arr.ndim == 3:
            arr = np.ascontiguousarray(arr[..., ::-1])  # RGB -> OpenCV's BGR
        ok, buf = cv2.imencode(".png", arr)
        if not ok:  # pragma: no cover - OpenCV encodes any uint8/uint16 array
            raise ValueError("cv2.imencode failed to encode the camera image")
        return buf.tobytes()

    def dn_from_png(self, pixels: NDArray) -> NDArray[np.unsignedinteger]:
        """Digital numbers from a PNG's pixel values (RGB order) written by :meth:`png_bytes`."""
        arr = np.asarray(pixels)
        if self.bits > 8:
            if arr.dtype != np.uint16:
                raise ValueError(f"expected a 16-bit PNG for {self.bits} bits, got {arr.dtype}")
            return np.rint(arr.astype(np.float64) * (self.max_dn / 65535.0)).astype(np.uint16)
        if arr.dtype != np.uint8:
            raise ValueError(f"expected an 8-bit PNG for 8 bits, got {arr.dtype}")
        return arr

    # -- figures for the docs and tests ------------------------------------------------

    def noise_electrons(self, mu: float) -> float:
        """Predicted noise (electrons rms) at a mean charge ``mu`` below saturation:
        ``sqrt(mu + read_noise^2)`` (Poisson variance equals its mean)."""
        return math.sqrt(mu + self.read_noise**2)


#: (key, lo, hi, lo_open, hi_open, unit) of the float parameters.
_NUMBERS: tuple[tuple[str, float, float | None, bool, bool, str], ...] = (
    ("exposure", 0.0, None, True, False, "full-well fraction per unit radiance"),
    ("full_well", 0.0, MAX_FULL_WELL, True, False, "electrons"),
    ("read_noise", 0.0, None, False, False, "electrons rms"),
    ("gain", 0.0, None, True, False, "unitless"),
    ("vignetting", 0.0, 1.0, False, True, "fraction of light lost at the rim"),
    ("defocus", 0.0, MAX_DEFOCUS, False, False, "Gaussian sigma in pixels"),
    ("shutter", 0.0, 1.0, False, False, "fraction of the frame interval"),
)


def _number(
    where: str,
    key: str,
    v: Any,
    lo: float,
    hi: float | None,
    lo_open: bool,
    hi_open: bool,
    unit: str,
) -> float:
    left = "(" if lo_open else "["
    if hi is None:
        expected = f"a number {'>' if lo_open else '>='} {lo:g} ({unit})"
    else:
        expected = f"a number in {left}{lo:g}, {hi:g}{')' if hi_open else ']'} ({unit})"
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise CameraError(where, key, v, expected)
    if v < lo or (lo_open and v == lo) or (hi is not None and (v > hi or (hi_open and v == hi))):
        raise CameraError(where, key, v, expected)
    return float(v)


def srgb_encode(v: NDArray) -> NDArray[np.float64]:
    """The sRGB transfer curve (IEC 61966-2-1) of linear values in [0, 1]."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def parse_camera_overrides(
    items: Iterable[str] | Mapping[str, Any], *, where: str = "--camera"
) -> dict[str, Any]:
    """``["read_noise=5", "response=srgb"]`` (or a mapping) -> ``{"read_noise": 5, ...}``.

    Values are TOML values (``5``, ``0.5``, ``"srgb"``); anything TOML cannot read is
    kept as a string. Keys may carry a ``camera.`` prefix. Types and ranges are checked
    by :meth:`CameraModel.from_mapping`.
    """
    if isinstance(items, Mapping):
        pairs = list(items.items())
    else:
        if isinstance(items, str):
            items = [items]
        pairs = []
        for text in items:
            key, sep, raw = str(text).partition("=")
            if not sep or not key.strip():
                raise CameraError(where, str(text), None, "KEY=VALUE, e.g. read_noise=5")
            raw = raw.strip()
            try:
                value = tomllib.loads(f"v = {raw}")["v"]
            except tomllib.TOMLDecodeError:
                value = raw
            pairs.append((key.strip(), value))
    out: dict[str, Any] = {}
    for key, value in pairs:
        key = str(key)
        out[key.removeprefix("camera.")] = value
    return out


def camera_image(
    dataset: Any,
    k: int,
    cam: str,
    model: CameraModel,
    *,
    seed: int | None = None,
    grey: bool = True,
) -> NDArray[np.float32]:
    """The image a camera ``model`` takes of a dataset frame's stored radiance.

    Reads frame ``k``'s linear radiance of camera ``cam`` (the EXR), applies ``model``
    (noise fixed by ``(seed or model.seed, k, cam)``; vignetting centred on the unit's
    ``x_c, y_c`` with its ``r_m``) and returns the float image in [0, 1] that omniflow
    reads from such a PNG: grey (H, W) (Rec. 709 luma) or, with ``grey=False``,
    RGB (H, W, 3). For the dataset's own camera (``model == dataset_camera(dataset)``) this
    equals the stored PNG (:func:`read_camera_image`).

    ``dataset`` is an :class:`omniflow.io.dataset.Dataset` (anything with ``read_rgb`` and
    ``unit``).
    """
    rgb = dataset.read_rgb(k, cam)
    unit = dataset.unit(cam)
    dn = model.apply(rgb, frame=k, cam=cam, seed=seed, centre=(unit.x_c, unit.y_c), r_m=unit.r_m)
    return model.grey(dn) if grey else model.to_float(dn)


# -- a dataset's camera ----------------------------------------------------------------


def camera_from_meta(meta: Mapping[str, Any]) -> tuple[CameraModel | None, Rig | None]:
    """``(CameraModel, Rig)`` of a dataset.json with a ``camera`` section, else ``(None, None)``.

    Raises :class:`omniflow.io.dataset.DatasetError` when the section or the rig is malformed.
    """
    section = meta.get("camera")
    if section is None:
        return None, None
    try:
        model = CameraModel.from_mapping(section, where="dataset.json")
        rig = rig_from_dict(meta, where="dataset.json")
    except (CameraError, RigError) as exc:
        raise DatasetError(str(exc)) from exc
    return model, rig


def dataset_camera(dataset: Dataset) -> CameraModel | None:
    """The dataset's :class:`CameraModel` (dataset.json ``camera``), or None for a dataset
    written without one (no PNGs)."""
    return camera_from_meta(dataset.meta)[0]


def read_camera_dn(dataset: Dataset, k: int, cam: str) -> NDArray[np.unsignedinteger]:
    """Digital numbers (H, W, 3) of the camera image ``cam.png`` of frame ``k``:
    ``uint8`` for 8 bits, else ``uint16`` in ``[0, 2^bits - 1]``."""
    import cv2

    dataset.check_frame(k, cam)
    model = dataset_camera(dataset)
    path = dataset.path(k, cam, "png")
    if model is None:
        raise DatasetError(f"{dataset.dir}: dataset.json has no camera section: no camera images")
    pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise DatasetError(f"{path}: cannot read the camera image")
    if pixels.ndim == 3:
        pixels = pixels[..., ::-1]  # OpenCV's BGR -> RGB
    unit = dataset.unit(cam)
    if pixels.shape[:2] != (unit.height, unit.width):
        raise DatasetError(
            f"{path}: image is {pixels.shape[1]}x{pixels.shape[0]}, dataset.json says "
            f"{unit.width}x{unit.height}"
        )
    try:
        return model.dn_from_png(pixels)
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from exc


def read_camera_image(
    dataset: Dataset, k: int, cam: str, *, grey: bool = False
) -> NDArray[np.float32]:
    """The stored camera image of frame ``k`` as float32 in [0, 1]: RGB (H, W, 3), or
    with ``grey=True`` its Rec. 709 luma (H, W), as omniflow reads it."""
    model = dataset_camera(dataset)
    dn = read_camera_dn(dataset, k, cam)
    return model.grey(dn) if grey else model.to_float(dn)
