"""benchmarks/bench_omniflow.py --versus: a second configuration timed in the same run."""

from __future__ import annotations

import json

import pytest

from benchmarks.bench_omniflow import main


def test_versus_times_the_changed_configuration_beside_the_default(tmp_path, capsys):
    out = tmp_path / "bench.json"
    argv = ["--size", "128", "--repeats", "1", "--warmup", "0", "--interval", "0",
            "--memory-sizes", "--versus", "monocular_gap=24", "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    report = json.loads(out.read_text())
    rows = {r["method"]: r for r in report["results"]}
    assert report["versus"] == ["monocular_gap=24"]
    assert rows["omniflow pair versus"]["median_s"] > 0
    assert rows["omniflow pair versus"]["points"] == rows["omniflow pair"]["points"]
    assert "omniflow pair versus" in capsys.readouterr().out


def test_a_bad_versus_field_is_one_line(capsys):
    with pytest.raises(SystemExit, match="--versus 'nope=1': expected NAME=VALUE"):
        main(["--size", "128", "--memory-sizes", "--versus", "nope=1"])
