"""The camera model (omnisim.camera): parameters, noise figures, files, determinism, errors."""

from __future__ import annotations

import json
import math
import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from omniflow.io.dataset import open_dataset
from omnisim.camera import (
    CameraError,
    CameraModel,
    camera_image,
    dataset_camera,
    read_camera_dn,
    read_camera_image,
    srgb_encode,
)
from omnisim.job import render_dataset

ROOT = Path(__file__).resolve().parents[2]
DEFAULT = ROOT / "scenes" / "default.toml"
FAKE = "tests.helpers.fakes:render_frame"
SMALL = {"render.width": 32, "render.height": 32, "frames": 2}

#: Flat patch for the noise tests: 256 x 256 x 3 = 196608 samples, so the sample standard
#: deviation has a relative standard error of 1/sqrt(2 N) = 0.16 %.
PATCH = (256, 256, 3)
#: Tolerance of measured vs predicted noise. The issue asks for 10 %; measured ratios were
#: 0.9989 .. 1.0021 over the same cases (python benchmarks/bench_camera.py), so 2 % is
#: about 10 standard errors and still fails for a missing noise term.
NOISE_RTOL = 0.02


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def _flat(model: CameraModel, mu: float) -> np.ndarray:
    """Radiance that gives a mean charge of ``mu`` electrons."""
    return np.full(PATCH, mu / (model.exposure * model.full_well), np.float32)


def _measured_dn_std(model: CameraModel, mu: float, frame: int = 0) -> float:
    dn = model.apply(_flat(model, mu), frame=frame, cam="cam1")
    return float(dn.astype(np.float64).std())


def _dn_per_electron(model: CameraModel) -> float:
    return model.gain * model.max_dn / model.full_well


# -- parameters -------------------------------------------------------------------------


def test_import_without_mitsuba():
    code = (
        "import sys; sys.modules['mitsuba'] = None; sys.modules['drjit'] = None\n"
        "import omnisim.camera, omnisim.dataset\n"
        "print(omnisim.camera.CameraModel().bits)"
    )
    p = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "8"


def test_defaults_are_a_good_machine_vision_camera():
    m = CameraModel()
    assert (m.bits, m.response, m.full_well, m.read_noise, m.gain) == (8, "linear", 2e4, 5.0, 1.0)
    # Noise at mid grey (half the full well): 1.0 % of the signal (the docs' figure).
    mu = m.full_well / 2
    assert m.noise_electrons(mu) / mu == pytest.approx(0.01, rel=0.01)


def test_round_trip_and_overrides():
    m = CameraModel(exposure=1.5, bits=12, response="srgb", vignetting=0.3, defocus=0.7, seed=9)
    assert CameraModel.from_mapping(m.to_dict()) == m
    assert CameraModel.from_mapping(json.loads(json.dumps(m.to_dict()))) == m
    assert set(m.to_dict()) == {f.name for f in fields(CameraModel)}
    o = m.with_overrides(["read_noise=12.5", "bits=16", "response=linear", "camera.seed=3"])
    assert (o.read_noise, o.bits, o.response, o.seed, o.exposure) == (12.5, 16, "linear", 3, 1.5)
    assert m.with_overrides({"gain": 2}).gain == 2.0


@pytest.mark.parametrize(
    ("item", "key", "expected"),
    [
        ("colour=1", "colour", "a known key"),
        ("read_noise=-1", "read_noise", ">= 0"),
        ("bits=0", "bits", "one of 8, 10, 12, 16"),
        ("bits=7", "bits", "one of 8, 10, 12, 16"),
        ("bits=8.5", "bits", "one of 8, 10, 12, 16"),
        ("full_well=0", "full_well", "(0, 1e+12]"),
        ("exposure=0", "exposure", "> 0"),
        ("gain=-2", "gain", "> 0"),
        ("vignetting=1", "vignetting", "[0, 1)"),
        ("defocus=-0.5", "defocus", "[0, 100]"),
        ("response=log", "response", "'linear', 'srgb'"),
        ("seed=-1", "seed", "[0, 2^63)"),
        ("exposure=nan", "exposure", "> 0"),
    ],
)
def test_bad_parameter_names_key_and_range(item, key, expected):
    with pytest.raises(CameraError) as info:
        CameraModel().with_overrides([item], where="--camera")
    msg = str(info.value)
    assert msg.startswith(f"--camera: camera.{key} = ")
    assert expected in msg and "\n" not in msg


# -- noise figures on a flat patch ------------------------------------------------------


@pytest.mark.parametrize(
    ("params", "mu"),
    [
        ({"read_noise": 0.0}, 100.0),  # shot noise only, three levels
        ({"read_noise": 0.0}, 1000.0),
        ({"read_noise": 0.0}, 10000.0),
        ({"read_noise": 20.0}, 400.0),  # shot and read equal: either missing is -29 %
        ({"read_noise": 80.0}, 1000.0),  # read noise dominant (shot alone would be 32 e-)
        ({"read_noise": 5.0, "gain": 2.0}, 3000.0),  # analog gain scales signal and noise
    ],
)
def test_noise_matches_parameters_16bit(params, mu):
    m = CameraModel(bits=16, **params)
    predicted = math.sqrt(mu + m.read_noise**2) * _dn_per_electron(m)
    assert _measured_dn_std(m, mu) == pytest.approx(predicted, rel=NOISE_RTOL)
    # The mean signal is exposure-linear (1 DN at 16 bits is 0.3 e- here).
    dn = m.apply(_flat(m, mu), frame=1, cam="cam2")
    assert dn.mean() / _dn_per_electron(m) == pytest.approx(mu, rel=2e-3, abs=0.5)


def test_noise_8bit_with_quantisation():
    # Full well 80000 e-: at mid grey the noise is 0.64 DN, and quantisation (1/sqrt(12) DN
    # in quadrature) adds 10 % (measured ratio to sqrt(sigma^2 + 1/12): 1.0008 at 40000 e-,
    # benchmarks/bench_camera.py).
    m = CameraModel(full_well=80000.0, read_noise=5.0)
    for mu in (40000.0, 40100.0, 40200.0):
        sigma = m.noise_electrons(mu) * _dn_per_electron(m)
        measured = _measured_dn_std(m, mu)
        assert measured == pytest.approx(math.hypot(sigma, 12**-0.5), rel=NOISE_RTOL)
        assert measured / sigma > 1.05  # the quantisation term is really there
    # The default camera at mid grey: 1.28 DN of noise, 1.31 DN with quantisation.
    d = CameraModel()
    sigma = d.noise_electrons(1e4) * _dn_per_electron(d)
    assert sigma == pytest.approx(1.28, abs=0.005)
    assert _measured_dn_std(d, 1e4) == pytest.approx(math.hypot(sigma, 12**-0.5), rel=NOISE_RTOL)
    # Rounding to the nearest DN is unbiased: the mean is 127.5 DN (measured 127.4995; its
    # standard error is 1.31 / sqrt(196608) = 0.003 DN); truncation would give 127.0.
    mean = d.apply(_flat(d, 1e4), frame=2, cam="cam1").astype(np.float64).mean()
    assert mean == pytest.approx(1e4 * _dn_per_electron(d), abs=0.05)


def test_srgb_response_scales_noise_by_its_slope():
    m = CameraModel(bits=16, response="srgb", read_noise=0.0)
    mu = 0.05 * m.full_well  # v = 0.05: the sRGB slope there is 2.52
    v = mu / m.full_well
    slope = 1.055 / 2.4 * v ** (1 / 2.4 - 1)
    dn = m.apply(_flat(m, mu), frame=0, cam="cam1").astype(np.float64)
    assert dn.mean() / m.max_dn == pytest.approx(srgb_encode(v), rel=1e-3)
    predicted = slope * math.sqrt(mu) / m.full_well * m.max_dn
    assert dn.std() == pytest.approx(predicted, rel=NOISE_RTOL)


def test_saturation_at_full_well_and_adc():
    m = CameraModel(bits=12, read_noise=0.0)
    dn = m.apply(_flat(m, 3 * m.full_well), frame=0, cam="cam1")
    assert dn.dtype == np.uint16 and (dn == 4095).all()
    # Read noise (5 e- = 1.0 DN here) is added to the saturated well: the ADC clips the
    # upper half, so about half the pixels read 4095 and the rest lie a few DN below.
    r = CameraModel(bits=12).apply(_flat(m, 3 * m.full_well), frame=0, cam="cam1")
    assert r.min() >= 4095 - 6 and 0.4 < (r == 4095).mean() < 0.7
    g = CameraModel(bits=12, gain=4.0)  # the ADC clips at a quarter of the well
    assert (g.apply(_flat(g, 0.3 * g.full_well), frame=0, cam="cam1") == 4095).all()
    assert CameraModel().apply(_flat(m, 0.5 * m.full_well), frame=0, cam="c").dtype == np.uint8


def test_vignetting_follows_the_cos4_law():
    # Noise made negligible: a 1e12 e- well (shot noise 1e-6 relative), no read noise.
    m = CameraModel(bits=16, full_well=1e12, read_noise=0.0, vignetting=0.4)
    h = w = 101
    centre, r_m = (50.5, 50.5), 40.0
    dn = m.apply(_flat(m, 0.5e12)[:h, :w], frame=0, cam="cam1", centre=centre, r_m=r_m)
    f = dn[..., 1].astype(np.float64) / dn[50, 50, 1]
    # Pixel (col 90, row 50) has its centre 40 px = r_m right of the centre: 1 - 0.4 there.
    assert f[50, 90] == pytest.approx(0.6, abs=2e-4)
    a = 0.6**-0.5 - 1
    assert f[50, 70] == pytest.approx((1 + a * 0.25) ** -2, abs=2e-4)  # rho = 1/2
    assert CameraModel(vignetting=0.0).optics(np.ones((8, 8)))[0, 0] == 1.0


def test_defocus_is_a_gaussian_of_that_sigma():
    m = CameraModel(defocus=2.5)
    img = np.zeros((41, 41), np.float32)
    img[20, 20] = 1.0
    out = m.optics(img)
    _, xx = np.mgrid[0:41, 0:41]
    var = (out * (xx - 20) ** 2).sum() / out.sum()
    # cv2's sampled kernel: measured sigma 0.9999, 2.4994, 4.9982 for 1, 2.5, 5 px.
    assert math.sqrt(var) == pytest.approx(2.5, rel=0.01)
    assert out.sum() == pytest.approx(1.0, rel=1e-5)


def test_noise_is_deterministic_and_independent_per_frame_and_camera():
    m = CameraModel(bits=16)
    flat = _flat(m, 5000.0)
    a = m.apply(flat, frame=3, cam="cam1").astype(np.float64)
    assert np.array_equal(a, m.apply(flat, frame=3, cam="cam1"))
    others = [
        m.apply(flat, frame=4, cam="cam1"),
        m.apply(flat, frame=3, cam="cam2"),
        m.apply(flat, frame=3, cam="cam1", seed=1),
        CameraModel(bits=16, seed=1).apply(flat, frame=3, cam="cam1"),
    ]
    for b in others:
        b = b.astype(np.float64)
        assert not np.array_equal(a, b)
        # Independent noise: correlation coefficient ~ N(0, 1/sqrt(196608) = 0.0023).
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.02
    assert np.array_equal(others[2], others[3])


# -- datasets ---------------------------------------------------------------------------


def _render(out: Path, **overrides) -> Path:
    render_dataset(DEFAULT, out, {**SMALL, **overrides}, renderer=FAKE, progress=False)
    return out


def _files(d: Path, ext: str) -> dict[str, bytes]:
    """camK.<ext> of every frame (not the format-version-2 mask PNGs camK.occluded.png, ...)."""
    paths = sorted((d / "frames").rglob(f"cam?.{ext}"))
    return {str(p.relative_to(d)): p.read_bytes() for p in paths}


def test_same_seed_same_bytes_other_camera_seed_other_noise(tmp_path):
    a = _render(tmp_path / "a")
    b = _render(tmp_path / "b")
    c = _render(tmp_path / "c", **{"camera.seed": 1})
    for ext in ("exr", "flo", "png"):
        assert _files(a, ext) == _files(b, ext) and len(_files(a, ext)) == 4
    assert _files(a, "exr") == _files(c, "exr")
    assert _files(a, "flo") == _files(c, "flo")
    pa, pc = _files(a, "png"), _files(c, "png")
    assert pa.keys() == pc.keys() and all(pa[k] != pc[k] for k in pa)
    da, dc = open_dataset(a), open_dataset(c)
    assert not np.array_equal(read_camera_dn(da, 0, "cam1"), read_camera_dn(dc, 0, "cam1"))


def test_exr_keeps_clean_radiance_and_truth_png_is_the_model(tmp_path):
    from omnisim.scene import load_scene
    from tests.helpers import fakes

    over = {**SMALL, "camera.bits": 12, "camera.vignetting": 0.3, "camera.defocus": 0.8}
    d = _render(tmp_path / "d", **{k: v for k, v in over.items() if k not in SMALL})
    ds = open_dataset(d)
    scene = load_scene(DEFAULT, over)
    model = dataset_camera(ds)
    assert model == scene.camera and model.bits == 12
    for k in range(2):
        clean = fakes.render_frame(scene, k)
        for cam in ("cam1", "cam2"):
            chans = ds.read_frame(k, cam)
            for name, arr in clean[cam].items():
                assert np.array_equal(chans[name], arr), name
            unit = ds.unit(cam)
            want = model.apply(
                ds.read_rgb(k, cam), frame=k, cam=cam, centre=(unit.x_c, unit.y_c), r_m=unit.r_m
            )
            dn = read_camera_dn(ds, k, cam)
            assert dn.dtype == np.uint16 and np.array_equal(dn, want)
            # Read-time application equals the stored image; another camera differs.
            grey = read_camera_image(ds, k, cam, grey=True)
            assert np.array_equal(camera_image(ds, k, cam, model), grey)
            noisy = camera_image(ds, k, cam, model.with_overrides(["read_noise=200"]))
            assert noisy.shape == grey.shape and not np.array_equal(noisy, grey)
    # The 16-bit PNG holds DN * 65535 / 4095 (full range), so ordinary readers agree.
    from omniflow.io.imageio import read_image

    png = read_image(ds.path(1, "cam2", "png"))
    assert np.abs(png - read_camera_image(ds, 1, "cam2")).max() < 1e-5


def test_dataset_json_records_every_camera_parameter(tmp_path):
    d = _render(tmp_path / "d", **{"camera.read_noise": 7.5})
    meta = json.loads((d / "dataset.json").read_text())
    assert meta["camera"] == CameraModel(read_noise=7.5).to_dict()
    assert set(meta["camera"]) == {f.name for f in fields(CameraModel)}


def test_ci_demo_renders_with_the_camera_defaults(tmp_path):
    demo = (ROOT / ".ci" / "demo").read_text()
    (line,) = [ln for ln in demo.splitlines() if ln.strip().startswith("omnisim render")]
    argv = shlex.split(line.replace('"$out/dataset"', str(tmp_path / "ds")))
    assert "--camera" not in argv and not any(a.startswith("camera.") for a in argv)
    scene = ROOT / argv[2]
    render_dataset(scene, tmp_path / "ds", SMALL, renderer=FAKE, progress=False)
    ds = open_dataset(tmp_path / "ds")
    from omnisim.scene import load_scene

    assert ds.meta["camera"] == load_scene(scene, SMALL).camera.to_dict()
    assert set(ds.meta["camera"]) == {f.name for f in fields(CameraModel)}
    for cam in ("cam1", "cam2"):
        assert ds.path(1, cam, "png").is_file()
        assert read_camera_dn(ds, 1, cam).dtype == np.uint8


@pytest.mark.parametrize(
    ("line", "key", "expected"),
    [
        ("colour = 1", "colour", "a known key"),
        ("read_noise = -3", "read_noise", ">= 0"),
        ("bits = 0", "bits", "one of 8, 10, 12, 16"),
        ("bits = 7", "bits", "one of 8, 10, 12, 16"),
        ("full_well = 0", "full_well", "(0, 1e+12]"),
        ('response = "gamma"', "response", "'linear', 'srgb'"),
    ],
)
def test_bad_camera_in_scene_file_one_line_exit_2(tmp_path, line, key, expected):
    bad = tmp_path / "bad.toml"
    bad.write_text(DEFAULT.read_text() + f"\n[camera]\n{line}\n")
    out = tmp_path / "out"
    exe = shutil.which("omnisim")
    assert exe is not None
    p = subprocess.run(
        [exe, "render", str(bad), "--out", str(out), "--renderer", FAKE, "--no-progress"],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 2, p.stderr
    err = p.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in p.stderr, err
    assert str(bad) in err and f"camera.{key} = " in err and expected in err, err
    assert not out.exists()


def test_camera_option_on_the_command_line(tmp_path):
    from omnisim.cli import main

    out = tmp_path / "o"
    args = ["render", str(DEFAULT), "--out", str(out), "--resolution", "32", "--frames", "1"]
    fake = ["--renderer", FAKE, "--no-progress"]
    assert main([*args, "--camera", "bits=10", "--camera", "response=srgb", *fake]) == 0
    assert dataset_camera(open_dataset(out)) == CameraModel(bits=10, response="srgb")
    bad = tmp_path / "bad"
    assert main([*args[:2], "--out", str(bad), "--camera", "read_noise=-1", *fake]) == 2
    assert not bad.exists()


# -- one real render --------------------------------------------------------------------


@pytest.mark.render
def test_real_render_camera_seed_changes_png_not_exr(tmp_path):
    pytest.importorskip("mitsuba")
    small = {"render.width": 40, "render.height": 40, "render.spp": 2, "frames": 1}

    def run(name: str, **extra) -> Path:
        out = tmp_path / name
        render_dataset(DEFAULT, out, {**small, **extra}, progress=False)
        return out

    a, b, c = run("a"), run("b"), run("c", **{"camera.seed": 5})
    for ext in ("exr", "png"):
        assert _files(a, ext) == _files(b, ext)
    assert _files(a, "exr") == _files(c, "exr")
    assert all(_files(a, "png")[k] != v for k, v in _files(c, "png").items())
    # The image is well exposed: the annulus's mean is 20 .. 80 % of the range.
    ds = open_dataset(a)
    img = read_camera_image(ds, 0, "cam1", grey=True)
    u = ds.unit("cam1")
    yy, xx = np.mgrid[0:40, 0:40] + 0.5
    inside = np.hypot(xx - u.x_c, yy - u.y_c) < u.r_m
    assert 0.2 < img[inside].mean() < 0.8
