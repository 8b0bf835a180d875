"""Textures for scene objects: procedural (seeded) or read from image files.

Every texture is a float32 array of shape (H, W, 3), linear RGB albedo in
[0, 1], periodic (it tiles without a seam), and covers ``tile`` metres of the
surface along both texture axes: the meshes of :mod:`omnisim.geometry` carry
UVs in units of tiles (u = surface coordinate / tile), so a UV outside [0, 1)
repeats the texture.

Texel convention (the renderer's bitmap lookup must agree): texel
``texture[i, j]`` covers u in [j / W, (j + 1) / W) and v in [i / H, (i + 1) / H),
i.e. columns run along u and rows along v, row 0 at v = 0; its centre is at
((j + 0.5) / W, (i + 0.5) / H). :func:`sample_texture` is the reference
bilinear lookup with wrap-around.

Procedural kinds (all deterministic for a given seed; numpy ``default_rng``):

``noise``
    Band-limited noise: a random Gaussian spectrum kept only on the annulus of
    spatial frequencies between ``tile / wavelength[1]`` and
    ``tile / wavelength[0]`` cycles per tile, with amplitude falling as
    ``f ** -exponent``; the inverse FFT is exactly periodic. Normalised to
    peak 1 and mapped affinely between ``colors[0]`` and ``colors[1]``
    (contrast ``contrast``), so every channel stays exactly in that band: the
    power spectrum has nothing outside it but the mean. Wavelengths are in
    metres on the surface: pick them so the features are a few to tens of
    pixels in the image (the DCT fit keeps only a quarter of the spectrum).
``grating``
    A sinusoidal grating with the given wavelength (metres) and angle
    (degrees from the u axis); the frequency is rounded to whole cycles per
    tile so the tile stays periodic. One spatial frequency: exactly
    band-limited.
``checker``
    Hard-edged checks of side ``size`` metres (rounded to an even number of
    checks per tile). Not band-limited: for aliasing and low-texture tests.
``solid``
    One colour: no texture at all (the aperture problem everywhere).
``image``
    An image file (PNG, JPEG, EXR, ...): 8/16-bit images are sRGB-decoded to
    linear unless ``srgb = false``; EXR/HDR are taken as linear.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "MAX_IMAGE_PIXELS",
    "checker_texture",
    "grating_texture",
    "load_image_texture",
    "noise_pattern",
    "noise_texture",
    "sample_texture",
    "solid_texture",
    "srgb_to_linear",
]

DEFAULT_COLORS = ((0.12, 0.12, 0.12), (0.78, 0.78, 0.78))


def _colorise(pattern: NDArray, colors: Sequence[Sequence[float]], contrast: float) -> NDArray:
    """Map a pattern in [-1, 1] affinely onto colours[0] .. colours[1] (float32 (H, W, 3))."""
    c0 = np.asarray(colors[0], dtype=np.float64)
    c1 = np.asarray(colors[1], dtype=np.float64)
    t = 0.5 + 0.5 * contrast * pattern  # in [0, 1] when |pattern| <= 1
    out = c0 + (c1 - c0) * t[..., None]
    return out.astype(np.float32)


def _freq_grid(size: int) -> tuple[NDArray, NDArray, NDArray]:
    """Integer spatial frequencies (cycles per tile) of an FFT grid: (f_u, f_v, |f|)."""
    f = np.fft.fftfreq(size, d=1.0 / size)
    fv, fu = np.meshgrid(f, f, indexing="ij")  # rows run along v, columns along u
    return fu, fv, np.hypot(fu, fv)


def noise_pattern(
    size: int, f_lo: float, f_hi: float, *, exponent: float = 1.0, seed: int = 0
) -> NDArray[np.float64]:
    """Periodic band-limited noise, shape (size, size), peak |value| 1.

    Only spatial frequencies with f_lo <= |f| <= f_hi (cycles per tile) are
    present. Raises ValueError if the band is empty or beyond Nyquist.
    """
    if not (0 < f_lo <= f_hi <= size / 2):
        raise ValueError(
            f"noise band [{f_lo:.4g}, {f_hi:.4g}] cycles per tile: expected 0 < low <= high "
            f"<= {size / 2:g} (Nyquist of {size} texels)"
        )
    rng = np.random.default_rng(seed)
    _, _, fr = _freq_grid(size)
    band = (fr >= f_lo) & (fr <= f_hi)
    if not band.any():
        raise ValueError(f"noise band [{f_lo:.4g}, {f_hi:.4g}] contains no integer frequency")
    amp = np.zeros_like(fr)
    amp[band] = fr[band] ** (-float(exponent))
    spec = amp * (rng.standard_normal(fr.shape) + 1j * rng.standard_normal(fr.shape))
    # The real part's spectrum is the Hermitian part of spec: the same (symmetric) band.
    pattern = np.fft.ifft2(spec).real
    pattern -= pattern.mean()
    peak = np.abs(pattern).max()
    return pattern / peak if peak > 0 else pattern


def noise_texture(
    *,
    tile: float,
    wavelength: tuple[float, float],
    resolution: int = 512,
    colors: Sequence[Sequence[float]] = DEFAULT_COLORS,
    contrast: float = 1.0,
    exponent: float = 1.0,
    seed: int = 0,
) -> NDArray[np.float32]:
    """Band-limited noise texture: wavelengths (min, max) in metres over a tile of ``tile`` m."""
    lam_min, lam_max = wavelength
    pattern = noise_pattern(
        resolution, tile / lam_max, tile / lam_min, exponent=exponent, seed=seed
    )
    return _colorise(pattern, colors, contrast)


def grating_texture(
    *,
    tile: float,
    wavelength: float,
    angle: float = 0.0,
    resolution: int = 512,
    colors: Sequence[Sequence[float]] = DEFAULT_COLORS,
    contrast: float = 1.0,
    phase: float = 0.0,
) -> NDArray[np.float32]:
    """Sinusoidal grating; the frequency is rounded to whole cycles per tile."""
    a = np.radians(angle)
    k_u = round(tile / wavelength * np.cos(a))
    k_v = round(tile / wavelength * np.sin(a))
    if k_u == 0 and k_v == 0:
        raise ValueError(f"grating wavelength {wavelength} m is longer than the tile ({tile} m)")
    if max(abs(k_u), abs(k_v)) > resolution / 2:
        raise ValueError(f"grating wavelength {wavelength} m is beyond Nyquist at this resolution")
    c = (np.arange(resolution) + 0.5) / resolution
    v, u = np.meshgrid(c, c, indexing="ij")
    pattern = np.cos(2 * np.pi * (k_u * u + k_v * v) + np.radians(phase))
    return _colorise(pattern, colors, contrast)


def checker_texture(
    *,
    tile: float,
    size: float,
    resolution: int = 512,
    colors: Sequence[Sequence[float]] = DEFAULT_COLORS,
) -> NDArray[np.float32]:
    """Hard-edged checker board with squares of about ``size`` metres (even count per tile)."""
    n = max(2, 2 * round(tile / (2 * size)))
    c = np.floor((np.arange(resolution) + 0.5) / resolution * n).astype(int)
    parity = (c[:, None] + c[None, :]) % 2
    return _colorise(2.0 * parity - 1.0, colors, 1.0)


def solid_texture(color: Sequence[float], resolution: int = 4) -> NDArray[np.float32]:
    """A uniform texture (small: the value is all that matters)."""
    out = np.empty((resolution, resolution, 3), dtype=np.float32)
    out[:] = np.asarray(color, dtype=np.float32)
    return out


def srgb_to_linear(x: ArrayLike) -> NDArray:
    """The sRGB transfer function inverted (IEC 61966-2-1), for values in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


#: Largest image file accepted as a texture or environment map, in pixels (8192 x 8192,
#: the largest procedural texture; 768 MiB as float32 RGB): the size is read from the
#: file's header before decoding, so a file that claims 100000 x 100000 pixels is
#: refused without allocating it.
MAX_IMAGE_PIXELS = 8192 * 8192


def _read_exr_rgb(path: Path) -> NDArray[np.float32]:
    """An EXR's R, G, B (or Y, or its single channel) as float32 (H, W, 3), via OpenEXR."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            header = exr.header()
            (x0, y0), (x1, y1) = header["dataWindow"]
            w, h = int(x1) - int(x0) + 1, int(y1) - int(y0) + 1
            if w * h > MAX_IMAGE_PIXELS:
                raise ValueError(
                    f"{path}: the EXR claims {w}x{h} pixels; expected at most "
                    f"{MAX_IMAGE_PIXELS} pixels (e.g. 8192x8192)"
                )
            chans = exr.channels()
            names = {n.rsplit(".", 1)[-1]: n for n in chans}
            if all(c in names for c in "RGB"):
                planes = [chans[names[c]].pixels for c in "RGB"]
            elif "Y" in names or len(chans) == 1:
                plane = chans[names["Y"] if "Y" in names else next(iter(chans))].pixels
                planes = [plane] * 3
            else:
                raise ValueError(
                    f"{path}: EXR channels {sorted(chans)}; expected R, G, B (or Y, or one)"
                )
            return np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1)
    except ValueError:
        raise
    except Exception as exc:  # OpenEXR raises RuntimeError / OSError on a bad file
        raise ValueError(f"{path}: not a readable EXR ({' '.join(str(exc).split())})") from exc


def _check_image_size(path: Path) -> None:
    """Refuse an image whose header claims more than MAX_IMAGE_PIXELS, before decoding."""
    from PIL import Image, UnidentifiedImageError

    bound = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None  # Pillow's own bomb check off: the bound is ours
    try:
        with Image.open(path) as im:  # reads the header only
            w, h = im.size
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError):
        return  # not a format Pillow knows (HDR, say): OpenCV decides
    finally:
        Image.MAX_IMAGE_PIXELS = bound
    if w * h > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"{path}: the image claims {w}x{h} pixels; expected at most {MAX_IMAGE_PIXELS} "
            "pixels (e.g. 8192x8192)"
        )


def load_image_texture(path: str | Path, *, srgb: bool = True) -> NDArray[np.float32]:
    """Read an image file as a float32 (H, W, 3) linear RGB texture.

    EXR files are read with the OpenEXR package (linear, float); other formats with
    OpenCV. Integer images are scaled to [0, 1] and, with ``srgb``, decoded from sRGB;
    floating-point images (EXR, HDR) are used as they are. Raises ValueError, naming
    the file, if it cannot be read, is larger than :data:`MAX_IMAGE_PIXELS`, or holds
    NaN or infinite values.
    """
    path = Path(path)
    if path.suffix.lower() == ".exr":
        out = _read_exr_rgb(path)
    else:
        _check_image_size(path)
        import cv2

        try:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        except cv2.error as exc:
            raise ValueError(f"{path}: not a readable image ({exc.err})") from exc
        if img is None or img.size == 0:
            raise ValueError(f"{path}: not a readable image")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        img = img[..., :3][..., ::-1]  # OpenCV is BGR(A)
        if img.shape[2] < 3:
            img = np.repeat(img[..., :1], 3, axis=2)
        if np.issubdtype(img.dtype, np.integer):
            out = img.astype(np.float64) / np.iinfo(img.dtype).max
            if srgb:
                out = srgb_to_linear(out)
        else:
            out = img.astype(np.float64)
    if not np.isfinite(out).all():
        raise ValueError(f"{path}: the image holds NaN or infinite values; expected finite ones")
    return np.ascontiguousarray(out, dtype=np.float32)


def sample_texture(texture: NDArray, u: ArrayLike, v: ArrayLike) -> NDArray[np.float32]:
    """Bilinear, wrap-around lookup of ``texture`` (H, W, C) at texture coordinates (u, v).

    The reference for the texel convention in the module docstring. Returns
    shape ``u.shape + (C,)``.
    """
    tex = np.asarray(texture)
    h, w = tex.shape[:2]
    x = np.asarray(u, dtype=np.float64) * w - 0.5
    y = np.asarray(v, dtype=np.float64) * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)
