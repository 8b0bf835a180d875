"""Same scene, same seed, same bytes, also on a busy machine with the denoiser on.

Renders the default scene (direct light, 64 spp, Open Image Denoise) at 128 px, 3
frames, twice, each in a fresh ``omnisim render`` process, while two busy loops load
both cores; then compares every file of the two datasets byte for byte. The one
allowed difference is ``dataset.json``'s ``timing`` section (seconds per frame,
machine-dependent by nature), and the lock file, which holds the writer's pid.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.render, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
#: A busy loop that ends by itself after this many seconds (the test kills it sooner).
BURN_S = 240
BURN = f"import time\nend = time.time() + {BURN_S}\nwhile time.time() < end:\n    pass\n"


def _render(out: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "omnisim.cli", "render", str(ROOT / "scenes" / "default.toml")]
    cmd += ["--out", str(out), "--frames", "3", "--resolution", "128"]
    cmd += ["--no-progress", "--no-resource-check"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


def _files(d: Path) -> dict[str, bytes]:
    out = {}
    for p in sorted(d.rglob("*")):
        if p.is_file() and p.name not in (".omnisim.lock", ".omniflow-testbed.json"):
            out[str(p.relative_to(d))] = p.read_bytes()
    return out


def test_two_renders_under_load_give_the_same_bytes(tmp_path):
    load = [subprocess.Popen([sys.executable, "-c", BURN]) for _ in range(2)]
    try:
        _render(tmp_path / "a")
        _render(tmp_path / "b")
    finally:
        for p in load:
            p.kill()
            p.wait()
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert sorted(a) == sorted(b)
    assert len([n for n in a if n.endswith(".exr")]) == 6  # 3 frames x 2 cameras
    meta_a = json.loads(a.pop("dataset.json"))
    meta_b = json.loads(b.pop("dataset.json"))
    assert set(meta_a["timing"]["frames"]) == {"0", "1", "2"}
    meta_a.pop("timing")
    meta_b.pop("timing")
    assert meta_a == meta_b
    differ = [name for name in a if a[name] != b[name]]
    assert not differ, f"files that differ between the two renders: {differ}"
