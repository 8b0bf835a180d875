"""The presets reproduce main's output columns bit for bit.

The reference (tests/data/preset_reference.npz) holds every column of
:func:`omniflow.pipeline.estimate` for the ``default``, ``dense`` and ``paper``
configurations on the closed-form pairs of ``test_speed_equivalence`` (the room,
with and without the textured pole), computed by main at 5662375 (before the
config was split into presets and nested options): the arrays themselves on
``room_pole``, and on ``room`` the SHA-256 of each column's bytes (dtype and shape
included), which keeps the file under 2 MB. From this repository's root::

    python tests/omniflow/test_preset_equivalence.py --write

A config refactor changes no arithmetic, so every column must be identical
(``assert_array_equal``, NaNs in the same places), not merely close.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import pytest

from omniflow.config import OmniFlowConfig
from omniflow.pipeline import estimate
from tests.omniflow.test_speed_equivalence import _scene

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "preset_reference.npz"
PRESETS = ("default", "dense", "paper")
SCENES = {"room": False, "room_pole": True}
#: Scenes whose reference is a digest per column (the arrays would pass 2 MB).
DIGESTED = ("room",)


def preset(name: str) -> OmniFlowConfig:
    """The named preset (main spelt them ``OmniFlowConfig()``, ``.dense()``, ``.paper()``)."""
    return OmniFlowConfig.preset(name)


def test_preset_spellings_agree():
    assert OmniFlowConfig.preset("default") == OmniFlowConfig()
    assert OmniFlowConfig.preset("dense") == OmniFlowConfig.dense()
    assert OmniFlowConfig.preset("paper") == OmniFlowConfig.paper()
    assert OmniFlowConfig.preset("dense", pool_k=64).pool_k == 64
    with pytest.raises(ValueError, match="preset 'fastest': expected one of"):
        OmniFlowConfig.preset("fastest")


def compute(scene_name: str, preset_name: str) -> dict[str, np.ndarray]:
    scene = _scene(SCENES[scene_name])
    f1 = [scene.render("cam1", t).astype(np.float32) for t in range(2)]
    f2 = [scene.render("cam2", t).astype(np.float32) for t in range(2)]
    res = estimate(f1, f2, scene.rig, preset(preset_name), t=0)
    out = {k: np.asarray(res[k]) for k in res.columns}
    out["n_significant"] = np.asarray(res.n_significant)
    return out


def digest(a: np.ndarray) -> np.ndarray:
    """SHA-256 of an array's dtype, shape and bytes, as 32 uint8."""
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).tobytes())
    return np.frombuffer(h.digest(), np.uint8)


@pytest.fixture(scope="module")
def reference():
    with np.load(REFERENCE) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("preset_name", PRESETS)
@pytest.mark.parametrize("scene_name", list(SCENES))
def test_preset_columns_identical(scene_name, preset_name, reference):
    key = f"{scene_name}/{preset_name}/"
    ref = {k[len(key) :]: v for k, v in reference.items() if k.startswith(key)}
    new = compute(scene_name, preset_name)
    assert sorted(new) == sorted(ref)
    assert new["theta"].size > 100
    if scene_name in DIGESTED:
        for k in ref:
            np.testing.assert_array_equal(digest(new[k]), ref[k], err_msg=k)
        return
    for k in ref:
        assert new[k].dtype == ref[k].dtype, k
        np.testing.assert_array_equal(new[k], ref[k], err_msg=k)


def _write() -> None:
    arrays = {}
    for scene_name in SCENES:
        for preset_name in PRESETS:
            for k, v in compute(scene_name, preset_name).items():
                arrays[f"{scene_name}/{preset_name}/{k}"] = (
                    digest(v) if scene_name in DIGESTED else v
                )
    tmp = REFERENCE.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(REFERENCE)
    print(f"wrote {REFERENCE} ({len(arrays)} arrays, {REFERENCE.stat().st_size} bytes)")


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        _write()
    else:
        sys.exit("usage: python " + __file__ + " --write")
