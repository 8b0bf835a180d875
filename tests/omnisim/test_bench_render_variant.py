"""benchmarks/bench_render.py --variant: a variant this machine cannot run is one line, exit 2."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.render

ROOT = Path(__file__).resolve().parents[2]


def test_cuda_variant_without_a_gpu_is_refused_with_one_line():
    dr = pytest.importorskip("drjit")
    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA device: the benchmark would run")
    bench = str(ROOT / "benchmarks" / "bench_render.py")
    proc = subprocess.run(
        [sys.executable, bench, "--skip-default", "--variant", "cuda_ad_rgb"],
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "'cuda_ad_rgb'" in lines[0] and "llvm_ad_rgb" in lines[0]
    assert "Traceback" not in proc.stderr
