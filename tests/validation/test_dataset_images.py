"""omniflow --dataset reads the camera images the harness scores (issue: it read the clean
radiance); --radiance reads the radiance. Dataset.read_image is bit-identical to the
harness's grey input (validation.inputs.Inputs), for an 8-bit and a 12-bit camera."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.render


@pytest.fixture(scope="module", params=[8, 12])
def dataset(request, tmp_path_factory):
    pytest.importorskip("mitsuba")
    from omnisim.job import render_dataset

    out = tmp_path_factory.mktemp(f"ds{request.param}") / "ds"
    render_dataset(ROOT / "scenes/default.toml", out,
                   {"render.width": 96, "render.height": 96, "frames": 2, "render.spp": 8,
                    "camera.bits": request.param}, progress=False)  # fmt: skip
    return out


def test_read_image_is_the_harness_input(dataset):
    from omniflow.io.dataset import open_dataset
    from validation.inputs import Inputs, camera_model

    ds = open_dataset(dataset)
    inputs = Inputs(ds, camera_model(ds.meta))
    for k in (0, 1):
        for cam in ("cam1", "cam2"):
            np.testing.assert_array_equal(ds.read_image(k, cam), inputs.frame(k, cam)[1])
    # and not the radiance: the camera adds noise and quantisation
    assert np.abs(ds.read_image(0, "cam1") - ds.read_grey(0, "cam1")).max() > 1e-3


def _flow(out: Path) -> dict[str, np.ndarray]:
    from tests.omniflow.test_cli import read_csv

    return read_csv(out / "flow.csv")


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "omniflow.cli", "pair", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)  # fmt: skip


def test_omniflow_dataset_reads_the_camera_images_by_default(dataset, tmp_path):
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate

    ds = open_dataset(dataset)
    for flag, read in (([], ds.read_image), (["--radiance"], ds.read_grey)):
        out = tmp_path / ("radiance" if flag else "camera")
        proc = _run("--dataset", dataset, "--out", out, "--no-pictures", *flag)
        assert proc.returncode == 0, proc.stderr
        images = json.loads((out / "flow.json").read_text())["inputs"]["images"]
        assert images.startswith("EXR radiance" if flag else "camera images camN.png")
        f1 = [read(k, "cam1") for k in (0, 1)]
        f2 = [read(k, "cam2") for k in (0, 1)]
        res = estimate(f1, f2, ds.rig, OmniFlowConfig(), t=0)
        got = _flow(out)
        assert len(got["dx"]) == len(res["x"]) > 0
        np.testing.assert_allclose(got["dx"], res["dx"], rtol=1e-6, atol=1e-6)  # csv digits
    cam, rad = _flow(tmp_path / "camera")["dx"], _flow(tmp_path / "radiance")["dx"]
    assert cam.shape != rad.shape or not np.allclose(cam, rad)


def test_radiance_with_image_files_is_one_line(tmp_path):
    files = [tmp_path / f"{n}.png" for n in "abcd"]
    proc = _run(*files, "--rig", ROOT / "scenes/default.toml", "--out", tmp_path / "o",
                "--radiance")  # fmt: skip
    assert proc.returncode == 2 and "--radiance applies to --dataset" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
