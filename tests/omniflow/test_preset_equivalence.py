"""The presets reproduce main's output columns.

The reference (tests/data/preset_reference.npz) holds every column of
:func:`omniflow.pipeline.estimate` for the ``default``, ``dense`` and ``paper``
configurations on the closed-form pairs of ``test_speed_equivalence`` (the room,
with and without the textured pole): on ``room_pole`` the arrays themselves, computed
by main at 5662375 (before the config was split into presets and nested options); on
``room`` a fingerprint of each column (the SHA-256 of its NaN mask and dtype, and its
size, sum, sum of squares, sum of magnitudes and 64 evenly spaced values), which
keeps the file under 2 MB. From this repository's root::

    python -m tests.omniflow.test_preset_equivalence --write

which rewrites the room fingerprints only (the room_pole arrays stay main 5662375's).
A config refactor changes no arithmetic, so NaNs must sit in the same places and the
values agree to 1e-12 relative (the issue's bound for "bit-identical"): bit-identity
itself does not survive a numpy upgrade (numpy 2.4.6 against the 2.3 that wrote the
reference: the paper preset's columns differ by 1e-16 relative, summation order).
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
    assert OmniFlowConfig.preset("dense", pooling={"pool_k": 64}).pooling.pool_k == 64
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


#: Relative agreement of every value with the reference (module docstring).
RTOL = 1e-12


def fingerprint(a: np.ndarray) -> dict[str, np.ndarray]:
    """The NaN mask's digest (with dtype and shape), and float statistics of the values."""
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    nan = np.isnan(a) if a.dtype.kind == "f" else np.zeros(a.shape, bool)
    h.update(np.packbits(nan).tobytes())
    v = np.where(nan, 0.0, a).astype(np.float64).ravel()
    picks = v[np.linspace(0, v.size - 1, 64).astype(int)] if v.size else np.zeros(64)
    stats = np.concatenate([[v.size, v.sum(), (v * v).sum(), np.abs(v).sum()], picks])
    return {"nan": np.frombuffer(h.digest(), np.uint8), "stats": stats}


def _close(new: np.ndarray, ref: np.ndarray, what: str) -> None:
    """Equal NaNs, and values within RTOL of the column's largest magnitude."""
    np.testing.assert_array_equal(np.isnan(new), np.isnan(ref), err_msg=what)
    scale = float(np.nanmax(np.abs(ref))) if np.isfinite(ref).any() else 0.0
    np.testing.assert_allclose(new, ref, rtol=0, atol=RTOL * max(scale, 1e-300),
                               equal_nan=True, err_msg=what)  # fmt: skip


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
    columns = {k.rsplit("/", 1)[0] for k in ref} if scene_name in DIGESTED else set(ref)
    assert sorted(new) == sorted(columns)
    assert new["theta"].size > 100
    if scene_name in DIGESTED:
        for k in {c.rsplit("/", 1)[0] for c in ref}:
            fp = fingerprint(new[k])
            np.testing.assert_array_equal(fp["nan"], ref[f"{k}/nan"], err_msg=f"{k} NaN mask")
            _close(fp["stats"], ref[f"{k}/stats"], f"{k} statistics")
        return
    for k in ref:
        assert new[k].dtype == ref[k].dtype, k
        if new[k].dtype.kind == "f":
            _close(new[k], ref[k], k)
        else:
            np.testing.assert_array_equal(new[k], ref[k], err_msg=k)


def _write() -> None:
    with np.load(REFERENCE) as z:  # the arrays of main 5662375 are kept
        arrays = {k: z[k] for k in z.files if k.split("/", 1)[0] not in DIGESTED}
    for scene_name in DIGESTED:
        for preset_name in PRESETS:
            for k, v in compute(scene_name, preset_name).items():
                for part, a in fingerprint(v).items():
                    arrays[f"{scene_name}/{preset_name}/{k}/{part}"] = a
    tmp = REFERENCE.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(REFERENCE)
    print(f"wrote {REFERENCE} ({len(arrays)} arrays, {REFERENCE.stat().st_size} bytes)")


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        _write()
    else:
        sys.exit("usage: python " + __file__ + " --write")
