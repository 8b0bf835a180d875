"""validation: the camera model applied when the images are formed (one render, many cameras).

Skipped where ``omnisim.camera`` is absent (it lands with issue 7's camera helper).
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from validation.synthdata import demo_scene, write_synthetic_dataset

pytest.importorskip("omnisim.camera")


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("synth") / "ds"
    write_synthetic_dataset(d, demo_scene(64), 3, name="synthetic-demo", supersample=1)
    return d


def _grey(ds, overrides, k=0, cam="cam1"):
    from validation.inputs import Inputs, camera_model

    return Inputs(ds, camera_model(ds.meta, overrides), auto_exposure=True).grey(k, cam)


def test_same_camera_same_images_and_read_noise_as_requested(synth):
    from omnisim.dataset import open_dataset

    ds = open_dataset(synth)
    valid = ds.read_frame(0, "cam1")["gt.valid"] > 0.5
    quiet = _grey(ds, ["read_noise=0", "bits=16"])
    assert np.array_equal(quiet, _grey(ds, ["read_noise=0", "bits=16"]))  # deterministic
    noisy = _grey(ds, ["read_noise=200", "bits=16"])
    # Same seed, frame and camera: the same shot noise, so the difference is the read noise
    # alone: 200 e- of a 20000 e- well = 0.01 per channel, Rec. 709 luma of three independent
    # channels: 0.01 * sqrt(0.2126^2 + 0.7152^2 + 0.0722^2) = 0.0075 (16 bits: no quantisation).
    diff = (noisy - quiet)[valid]
    assert np.std(diff) == pytest.approx(0.01 * np.sqrt(0.2126**2 + 0.7152**2 + 0.0722**2),
                                         rel=0.1)  # fmt: skip
    # Another frame or camera: other noise.
    assert not np.array_equal(_grey(ds, ["read_noise=0"], k=1), _grey(ds, ["read_noise=0"], k=0))


@pytest.mark.slow  # 5.2 s (docs/decisions/slow_tests.md)
def test_camera_sweep_writes_a_table_and_a_plot(synth, tmp_path):
    out = tmp_path / "r"
    p = subprocess.run(
        [sys.executable, "-m", "validation.cli", str(synth), "--out", str(out), "--variants",
         "default", "--baselines", "DIS-medium,zero-flow", "--no-progress",
         "--camera-sweep", "read_noise=0,100"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    with (out / "camera_sweep.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {r["value"] for r in rows} == {"0", "100"}
    assert {r["method"] for r in rows} >= {"DIS-medium", "zero-flow"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset"]["camera"]["read_noise"] == 0  # the report is the first level
    assert (out / "figures" / "camera_sweep.png").is_file()
    assert "Camera sweep" in (out / "report.md").read_text()


@pytest.mark.parametrize("section", ["x", [1, 2], 5])
def test_a_camera_section_that_is_not_a_table_is_refused(section):
    """A malformed camera section is an input error naming it, not silently 'no camera'
    (which would score the plain 8-bit luminance instead of the recorded camera)."""
    from validation.inputs import InputError, camera_model

    with pytest.raises(InputError, match=r"^dataset.json: camera = .*: expected a table"):
        camera_model({"camera": section})
    assert camera_model({}) is None  # no section: the plain luminance
    assert camera_model({"camera": {}}) is not None  # an empty table: the model's defaults
