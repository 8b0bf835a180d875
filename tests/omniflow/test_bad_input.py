"""Bad input to the installed ``omniflow`` command: one line, the right exit status, no damage.

Every case runs the console script ``omniflow`` (as installed by ``pip install
-e .``, with this checkout first on PYTHONPATH) in a subprocess and asserts:

- the exit status: 2 for bad input (a file, rig, dataset or option the user
  gave), 1 where the machine refuses (permission denied, read-only or full
  file system);
- exactly one line on standard error, ``omniflow: error: ...``, naming the
  path, option or value (a fragment of it is checked), and neither a Python
  traceback nor the words "internal error" (an uncaught exception the
  command's handler turned into a line);
- nothing changed on disk: every file under the case's folder and the shared
  inputs has the same bytes afterwards, so the old outputs in ``--out``
  (flow.csv, flow.json and a picture of an earlier run) are untouched, and no
  staging folder or new file is left behind.

The cases that need a read-only or full file system, or permissions that bind
root, run the command inside ``unshare -m`` (a private tmpfs) or ``setpriv``
(capabilities dropped); they are skipped where those tools cannot do it.

Zero matches (black, constant, lens-capped frames) is not an error: exit 0,
one warning line, empty outputs with every column, moved into place as a set.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import math
import os
import shlex
import shutil
import struct
import subprocess
import sys
import typing
import zlib
from pathlib import Path

import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from omniflow.io.imageio import read_exr_channels, write_exr, write_png
from omniflow.io.ownership import MARKER
from omnisim.synthetic import Motion, SyntheticScene

ROOT = Path(__file__).resolve().parents[2]
SIZE = 96
OLD = {  # an earlier run's outputs, present in --out before every case
    "flow.csv": b"# old run\nx,y\n1,2\n",
    "flow.json": b'{"command": ["omniflow", "an", "earlier", "run"]}\n',  # ours, no marker
    "flow_arrows.png": b"old picture bytes",
}


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.pop("PYTHONWARNINGS", None)
    return env


def omniflow_command() -> str:
    exe = shutil.which("omniflow")
    assert exe, "the omniflow command is not installed (pip install -e .)"
    return exe


def run_omniflow(args, *, wrap: list[str] | None = None, shell: str | None = None):
    """Run the installed command; ``wrap`` prefixes it (setpriv), ``shell`` is a bash script."""
    if shell is not None:
        cmd = [*(wrap or []), "bash", "-c", shell]
    else:
        cmd = [*(wrap or []), omniflow_command(), *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)


def snapshot(*folders: Path) -> dict[str, str]:
    """Every path under the folders with the sha256 of its bytes ('dir' for folders)."""
    state = {}
    for folder in folders:
        for path in sorted(folder.rglob("*")):
            key = str(path)
            state[key] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return state


def _toml_rig(rig: Rig, **changes) -> str:
    """The rig as a TOML file; ``changes`` maps 'rig.s' or 'cam1.r_m' to raw TOML text or None."""
    d = rig.to_dict()
    lines = ["[rig]"]
    for k, v in d["rig"].items():
        lines.append(f"{k} = {changes.get(f'rig.{k}', repr(v))}")
    for cam in d["cameras"]:
        lines += ["", "[[cameras]]"]
        for k, v in cam.items():
            if k == "v":
                continue
            text = changes.get(f"{cam['name']}.{k}", json.dumps(v))
            lines.append(f"{k} = {text}")
    return "\n".join(line for line in lines if not line.endswith("= None")) + "\n"


def _png_with_header(width: int, height: int) -> bytes:
    """A PNG whose header claims width x height pixels (its data is far shorter)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Frames of a turning robot in a textured room (3 time steps), a rig file, a dataset."""
    from validation.synthdata import write_synthetic_dataset

    d = tmp_path_factory.mktemp("inputs")
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=SIZE)
    scene = SyntheticScene.room(
        rig, wall_radius=3.0, ceiling=None, robot=Motion(yaw_rate=0.01), wavelengths=(0.2, 1.0)
    )
    for k in range(3):
        for cam in ("cam1", "cam2"):
            write_png(d / f"{cam}_{k}.png", scene.render(cam, k), bits=16)
    (d / "rig.toml").write_text(_toml_rig(rig))
    write_synthetic_dataset(d / "dataset", scene, frames=3, supersample=1)
    return {"dir": d, "rig": rig, "scene": scene}


def frames(base, steps=2):
    return [base["dir"] / f"{cam}_{k}.png" for k in range(steps) for cam in ("cam1", "cam2")]


# -- the table of bad inputs ------------------------------------------------------------------
# Each case: (setup, expected exit status, fragment of the error line). setup(base, work) makes
# whatever bad file the case needs in the case folder ``work`` and returns the arguments; the
# command always gets ``--out work/out`` unless the arguments already hold an --out.


def _files(*replace: tuple[int, Path]):
    def args(base, work):
        files = frames(base)
        for i, path in replace:
            files[i] = path(base, work) if callable(path) else path
        return [*files, "--rig", base["dir"] / "rig.toml"]

    return args


def _bad_file(name: str, data: bytes | str | None, slot: int = 3):
    """Frame ``slot`` replaced by a file ``name`` holding ``data`` (None: no such file)."""

    def make(base, work):
        path = work / name
        if isinstance(data, bytes):
            path.write_bytes(data)
        elif isinstance(data, str):
            path.write_text(data)
        return path

    return _files((slot, make))


def _cut_in_half(name: str, slot: int = 3):
    """Frame ``slot`` as a real file cut in half, inside its pixel data: libpng and
    OpenEXR print lines of their own on it (the command must still give one line)."""

    def make(base, work):
        path = work / name
        noise = np.random.default_rng(0).random((SIZE, SIZE)).astype(np.float32)
        whole = work / f"whole{path.suffix}"  # noise: the cut falls inside the pixel data
        if path.suffix == ".exr":
            write_exr(whole, noise)
        else:
            write_png(whole, noise, bits=16)
        data = whole.read_bytes()
        whole.unlink()
        path.write_bytes(data[: len(data) // 2])
        return path

    return _files((slot, make))


def _cut_frame_exr(ds):
    path = ds / "frames" / "000001" / "cam1.exr"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _image(name: str, array_fn, slot: int = 3):
    def make(base, work):
        arr = array_fn(base)
        if name.endswith(".exr"):
            return write_exr(work / name, arr)
        return write_png(work / name, arr, bits=16)

    return _files((slot, make))


def _nan_exr(value: float):
    def arr(base):
        img = base["scene"].render("cam2", 1)
        img[10, 20] = value
        return img

    return arr


def _two_channel_exr(base, work):
    img = base["scene"].render("cam2", 1)
    return write_exr(work / "ab.exr", {"A": img, "B": img})


def _same_size_set(size: int):
    def args(base, work):
        img = np.full((size, size), 0.5, np.float32)
        files = [write_png(work / f"s{i}.png", img) for i in range(4)]
        return [*files, "--rig", base["dir"] / "rig.toml"]

    return args


def _rig_text(text_fn, suffix=".toml"):
    def args(base, work):
        path = work / f"rig{suffix}"
        data = text_fn(base)
        if isinstance(data, bytes):
            path.write_bytes(data)
        else:
            path.write_text(data)
        return [*frames(base), "--rig", path]

    return args


def _rig_changed(**changes):
    return _rig_text(lambda base: _toml_rig(base["rig"], **changes))


def _tiny_rig_and_frames(base, work):
    rig = Rig.symmetric(d=0.10, R=0.05, s=0.30, size=12)
    (work / "tiny.toml").write_text(_toml_rig(rig))
    img = np.random.default_rng(0).random((12, 12)).astype(np.float32)
    files = [write_png(work / f"t{i}.png", img) for i in range(4)]
    return [*files, "--rig", work / "tiny.toml"]


def _opts(*extra, steps=2):
    return lambda base, work: [*frames(base, steps), "--rig", base["dir"] / "rig.toml", *extra]


def _dataset(edit=None, *extra):
    """A copy of the shared dataset, changed by ``edit(folder)``, read with --dataset."""

    def args(base, work):
        ds = work / "dataset"
        shutil.copytree(base["dir"] / "dataset", ds)
        if edit is not None:
            edit(ds)
        return ["--dataset", ds, *extra]

    return args


def _edit_meta(change):
    def edit(ds):
        meta = json.loads((ds / "dataset.json").read_text())
        change(meta)
        (ds / "dataset.json").write_text(json.dumps(meta))

    return edit


def _nan_in_frame(ds):
    path = ds / "frames" / "000001" / "cam1.exr"
    chans = read_exr_channels(path)
    chans["R"][5, 40] = np.nan
    write_exr(path, chans)


def _out(make_out):
    """Arguments with --out set by ``make_out(work)``."""

    def args(base, work):
        return [*frames(base), "--rig", base["dir"] / "rig.toml", "--out", make_out(work)]

    return args


def _out_file(work):
    (work / "taken").write_text("a file, not a folder")
    return work / "taken"


def _out_under_file(work):
    (work / "plain").write_text("a file")
    return work / "plain" / "out"


def _out_name_is_folder(work):
    (work / "out" / "flow_color.png").mkdir()
    return work / "out"


def _rm_big(base):
    rig = base["rig"]
    return _toml_rig(rig, **{"cam1.r_m": repr(4 * SIZE), "cam2.r_m": repr(4 * SIZE)})


CALIBRATE = ["--calibrate", "--d", "0.1", "--R", "0.05", "--s", "0.3"]

CASES = {
    # image files
    "image missing": (_bad_file("missing.png", None), 2, "missing.png: image file not found"),
    "image is a folder": (_files((3, lambda b, w: w)), 2, "not a file"),
    "text file as image": (_bad_file("notes.png", "not an image"), 2, "cannot be read as an image"),
    "empty file": (_bad_file("empty.png", b""), 2, "empty.png: cannot be read as an image"),
    "truncated png": (
        _bad_file("cut.png", _png_with_header(SIZE, SIZE)[:40]),
        2,
        "cut.png: cannot be read as an image",
    ),
    "png claiming 100000x100000": (
        _bad_file("huge.png", _png_with_header(100000, 100000)),
        2,
        "huge.png: cannot be decoded",
    ),
    "garbage exr": (_bad_file("junk.exr", bytes(range(256)) * 8), 2, "junk.exr: cannot be read"),
    "png cut in its pixel data": (_cut_in_half("half.png"), 2, "half.png: cannot be read as"),
    "exr cut in its pixel data": (_cut_in_half("half.exr"), 2, "half.exr: cannot be read as"),
    "exr without R G B or Y": (_files((3, _two_channel_exr)), 2, "ab.exr: no R, G, B or Y"),
    "nan pixel": (_image("nan.exr", _nan_exr(np.nan)), 2, "nan.exr: 1 pixel(s) are NaN"),
    "inf pixel": (_image("inf.exr", _nan_exr(np.inf)), 2, "inf.exr: 1 pixel(s) are NaN or inf"),
    "pair sizes differ": (
        _image("small.png", lambda b: np.zeros((SIZE // 2, SIZE // 2), np.float32), slot=1),
        2,
        "images differ in size",
    ),
    "time steps differ in size": (
        _image("wide.png", lambda b: np.zeros((SIZE, SIZE + 8), np.float32), slot=2),
        2,
        "wide.png is 104x96",
    ),
    "images not the rig's size": (_same_size_set(64), 2, "the images are 64x64 but"),
    "images too small for the algorithm": (_tiny_rig_and_frames, 2, "annulus"),
    "three files": (lambda b, w: [*frames(b)[:3], "--rig", b["dir"] / "rig.toml"], 2, "got 3"),
    "no input": (lambda b, w: ["--rig", b["dir"] / "rig.toml"], 2, "no input"),
    # rig files
    "rig missing": (
        lambda b, w: [*frames(b), "--rig", w / "none.toml"],
        2,
        "none.toml: rig file not found",
    ),
    "rig is a folder": (lambda b, w: [*frames(b), "--rig", w], 2, "not a file"),
    "rig binary": (_rig_text(lambda b: bytes(range(256))), 2, "rig.toml: not UTF-8 text"),
    "rig bad toml": (_rig_text(lambda b: "[rig\nd = "), 2, "rig.toml: not valid TOML"),
    "rig bad json": (_rig_text(lambda b: "{", ".json"), 2, "rig.json: not valid JSON"),
    "rig field missing": (_rig_changed(**{"rig.s": "None"}), 2, "rig.s is missing"),
    "rig negative R": (_rig_changed(**{"rig.R": "-0.05"}), 2, "R = -0.05: expected > 0"),
    "rig d is text": (_rig_changed(**{"rig.d": '"0.1"'}), 2, "rig.d = '0.1': expected a finite"),
    "rig r_m 4x the image": (_rig_text(_rm_big), 2, "r_m = 384: the rim circle lies outside"),
    "rig centre outside": (_rig_changed(**{"cam1.x_c": "500.0"}), 2, "lies outside the 96x96"),
    "rig width not integer": (_rig_changed(**{"cam2.width": "96.5"}), 2, "expected integer"),
    "rig nan in json": (
        _rig_text(lambda b: json.dumps(b["rig"].to_dict()).replace("0.05", "NaN"), ".json"),
        2,
        "expected a finite number",
    ),
    "rig cameras not a list": (
        _rig_text(lambda b: 'cameras = "two"\n[rig]\nd = 0.1\nR = 0.05\ns = 0.3\n'),
        2,
        "'cameras' must list exactly two cameras",
    ),
    "no rig": (lambda b, w: frames(b), 2, "--rig FILE is required"),
    # datasets
    "dataset missing": (lambda b, w: ["--dataset", w / "nodir"], 2, "not an omnisim dataset"),
    "dataset is a file": (
        lambda b, w: ["--dataset", b["dir"] / "rig.toml"],
        2,
        "not an omnisim dataset",
    ),
    "dataset.json binary": (
        _dataset(lambda ds: (ds / "dataset.json").write_bytes(bytes(range(256)))),
        2,
        "dataset.json: not UTF-8",
    ),
    "dataset.json not json": (
        _dataset(lambda ds: (ds / "dataset.json").write_text("{")),
        2,
        "dataset.json: not valid JSON",
    ),
    "dataset rig r_m too big": (
        _dataset(_edit_meta(lambda m: m["cameras"][0].update(r_m=400.0, v=1200.0))),
        2,
        "the rim circle lies outside",
    ),
    "frame negative": (_dataset(None, "--frame", "-1"), 2, "--frame -1"),
    "frame past the end": (_dataset(None, "--frame", "2"), 2, "--frame 2: the flow needs"),
    "frame file missing": (
        _dataset(lambda ds: (ds / "frames" / "000001" / "cam2.exr").unlink()),
        2,
        "frames/000001: frame 1 not rendered",
    ),
    "frame file corrupt": (
        _dataset(lambda ds: (ds / "frames" / "000000" / "cam1.exr").write_bytes(b"\0" * 999)),
        2,
        "cam1.exr",
    ),
    "frame exr cut in its pixel data": (_dataset(_cut_frame_exr), 2, "cam1.exr: cannot read"),
    "nan radiance in dataset": (_dataset(_nan_in_frame), 2, "NaN"),
    "dataset and images": (
        lambda b, w: [*frames(b), "--dataset", b["dir"] / "dataset"],
        2,
        "either IMAGE files or --dataset",
    ),
    "dataset with --t": (_dataset(None, "--t", "1"), 2, "--t applies to IMAGE files"),
    # options
    "n-theta 0": (_opts("--n-theta", "0"), 2, "--n-theta 0: expected an integer >= 8"),
    "n-theta negative": (_opts("--n-theta", "-3"), 2, "--n-theta -3"),
    "band 0": (_opts("--band", "0"), 2, "--band 0: expected a number in (0, 1]"),
    "band nan": (_opts("--band", "nan"), 2, "--band nan: expected a finite number"),
    "band text": (_opts("--band", "wide"), 2, "--band: invalid float value: 'wide'"),
    "flow-band 0": (_opts("--flow-band", "0"), 2, "--flow-band 0"),
    "h-step 0": (_opts("--search.h-step", "0"), 2, "--search.h-step 0: expected a number > 0"),
    "h-min inf": (
        _opts("--search.h-min", "inf"),
        2,
        "--search.h-min inf: expected a finite number",
    ),
    "patch-radius negative": (_opts("--patch-radius", "-1"), 2, "--patch-radius -1"),
    "profile-step 0": (_opts("--matching.profile-step", "0"), 2, "--matching.profile-step 0"),
    "threshold-percentile 150": (_opts("--threshold-percentile", "150"), 2, "in [0, 100)"),
    "min-score 2": (
        _opts("--matching.min-score", "2"),
        2,
        "--matching.min-score 2: expected a number in [-1, 1]",
    ),
    "uniqueness 0": (_opts("--matching.uniqueness", "0"), 2, "--matching.uniqueness 0"),
    "tangential-blur 100": (
        _opts("--matching.tangential-blur", "100"),
        2,
        "--matching.tangential-blur 100",
    ),
    "iterations negative": (_opts("--iterations", "-1"), 2, "--iterations -1"),
    "temporal-frames 1": (_opts("--fit.temporal-frames", "1"), 2, "--fit.temporal-frames 1"),
    "pool-k 0": (_opts("--pooling.pool-k", "0"), 2, "--pooling.pool-k 0"),
    "pool-range-tol negative": (
        _opts("--pooling.pool-range-tol", "-1"),
        2,
        "--pooling.pool-range-tol -1",
    ),
    "decouple-tol 0": (
        _opts("--decouple-tol", "0"),
        2,
        "--decouple-tol 0: expected a number > 0",
    ),
    "brightness-gate nan": (_opts("--brightness-gate", "nan"), 2, "--brightness-gate nan"),
    "r-max 0": (_opts("--r-max", "0"), 2, "--r-max 0"),
    "pool-min-conditioning nan": (
        _opts("--pooling.pool-min-conditioning", "nan"),
        2,
        "--pooling.pool-min-conditioning nan",
    ),
    "r-min beyond r-max": (_opts("--r-min", "20"), 2, "r_min = 20.0, r_max = 10.0"),
    "h-min beyond the rim": (
        _opts("--search.h-min", "1000"),
        2,
        "do not fit these images (--search.h-min 1000",
    ),
    "solver unknown": (_opts("--solver", "foo"), 2, "--solver: invalid choice: 'foo'"),
    "unknown option": (_opts("--bnd", "0.3"), 2, "unrecognized arguments: --bnd"),
    "arrow-scale 0": (_opts("--arrow-scale", "0"), 2, "--arrow-scale 0.0: expected"),
    "arrow-scale nan": (_opts("--arrow-scale", "nan"), 2, "--arrow-scale nan"),
    "t negative": (_opts("--t", "-1"), 2, "--t -1"),
    "t past the end": (_opts("--t", "1"), 2, "--t 1: the flow needs time steps 1 and 2"),
    "dct3d with 2 steps": (_opts("--fit.temporal", "dct3d"), 2, "dct3d needs 3 time steps"),
    "d without calibrate": (_opts("--d", "0.1"), 2, "apply with --calibrate only"),
    "calibrate negative R": (
        lambda b, w: [*frames(b), "--calibrate", "--d", "0.1", "--R", "-0.05", "--s", "0.3"],
        2,
        "--R -0.05: expected a finite length",
    ),
    "calibrate without s": (
        lambda b, w: [*frames(b), "--calibrate", "--d", "0.1", "--R", "0.05"],
        2,
        "--calibrate needs --s",
    ),
    "calibrate on blank frames": (
        lambda b, w: [*_same_size_set(SIZE)(b, w)[:4], *CALIBRATE],
        2,
        "--calibrate: image is blank",
    ),
    "no --out": (
        lambda b, w: [*frames(b), "--rig", b["dir"] / "rig.toml"],
        2,
        "the following arguments are required: --out",
    ),
    # --out
    "out is a file": (_out(_out_file), 2, "taken: exists and is not a folder"),
    "out under a file": (_out(_out_under_file), 2, "plain is a file, not a folder"),
    "an output name is a folder": (_out(_out_name_is_folder), 2, "flow_color.png: is a folder"),
    "out name too long": (_out(lambda w: w / ("x" * 300)), 2, "name too long"),
    "out is a device": (_out(lambda w: Path("/dev/null")), 2, "--out /dev/null: exists and is not"),
}

NO_OUT = {"no --out"}  # cases whose point is a missing --out


def check_clean_failure(proc, status: int, fragment: str) -> str:
    both = proc.stdout + proc.stderr
    assert "Traceback" not in both, proc.stderr
    assert "internal error" not in proc.stderr, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("omniflow: error: "), lines[0]
    assert fragment in lines[0], lines[0]
    assert proc.returncode == status, (proc.returncode, proc.stderr)
    return lines[0]


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_one_line_and_changes_nothing(base, tmp_path, name):
    setup, status, fragment = CASES[name]
    out = tmp_path / "out"
    out.mkdir()
    for file, data in OLD.items():
        (out / file).write_bytes(data)
    args = [str(a) for a in setup(base, tmp_path)]
    if "--out" not in args and name not in NO_OUT:
        args += ["--out", str(out)]
    before = snapshot(tmp_path, base["dir"])
    proc = run_omniflow(args)
    check_clean_failure(proc, status, fragment)
    assert snapshot(tmp_path, base["dir"]) == before  # old outputs untouched, nothing left


def test_every_knob_carries_its_check():
    """Each OmniFlowConfig field's metadata (omniflow.config.knob) is the one place its
    check lives: a help line for every field, a range for every numeric one, choices for
    every word; every preset lies inside. Mutation caught: a numeric knob without limits
    would reach the pipeline unchecked."""
    from omniflow.config import GROUPS, PRESETS, OmniFlowConfig, knob_fields

    hints = typing.get_type_hints(OmniFlowConfig)
    for group, cls in GROUPS.items():
        hints.update({f"{group}.{k}": v for k, v in typing.get_type_hints(cls).items()})
    numeric = []
    for name, f in knob_fields().items():
        assert f.metadata.get("help"), name
        kinds = set(typing.get_args(hints[name]) or [hints[name]])
        if {int, float} & kinds:
            numeric.append(name)
            assert f.metadata.get("limits") is not None, name
        if str in kinds:
            assert f.metadata.get("choices"), name
    assert len(numeric) >= 20  # 52 today; a change of annotation style would empty the list
    for name in PRESETS:  # every preset's values lie in their ranges (made without error)
        OmniFlowConfig.preset(name)
    with pytest.raises(
        ValueError, match=r"OmniFlowConfig.pooling.pool_k = 0: expected an integer >= 1"
    ):
        OmniFlowConfig(pooling={"pool_k": 0})


def test_debug_shows_the_traceback(base, tmp_path):
    proc = run_omniflow([*frames(base), "--rig", tmp_path / "none.toml", "--out", tmp_path / "o",
                         "--debug"])  # fmt: skip
    assert proc.returncode == 2
    assert "Traceback" in proc.stderr and "RigError" in proc.stderr
    assert proc.stderr.splitlines()[-1].startswith("omniflow: error: ")


# -- the machine refuses: permission, read-only and full file systems (exit 1) ---------------


def _can(cmd: list[str]) -> bool:
    try:
        return subprocess.run(cmd, capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def _unprivileged() -> list[str]:
    """A prefix that makes permission bits bind (root without its capabilities)."""
    if os.geteuid() != 0:
        return []
    if not _can(["setpriv", "--inh-caps=-all", "--bounding-set=-all", "true"]):
        pytest.skip("running as root and setpriv cannot drop capabilities")
    return ["setpriv", "--inh-caps=-all", "--bounding-set=-all"]


def _old_outputs(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for file, data in OLD.items():
        (out / file).write_bytes(data)


@pytest.mark.parametrize("what", ["out folder", "out parent", "input image", "rig file"])
def test_permission_denied_exits_1(base, tmp_path, what):
    wrap = _unprivileged()
    out = tmp_path / "out"
    _old_outputs(out)
    files = frames(base)
    if what == "out folder":
        out.chmod(0o555)
        fragment = f"{out}: Permission denied"
    elif what == "out parent":
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        out = locked / "new"
        fragment = str(locked)
    elif what == "input image":
        secret = tmp_path / "secret.png"
        shutil.copy(files[3], secret)
        secret.chmod(0)
        files[3] = secret
        fragment = "secret.png: Permission denied"
    else:
        rig = tmp_path / "secret.toml"
        shutil.copy(base["dir"] / "rig.toml", rig)
        rig.chmod(0)
        fragment = "secret.toml: Permission denied"
    rig = tmp_path / "secret.toml" if what == "rig file" else base["dir"] / "rig.toml"
    before = snapshot(tmp_path)
    try:
        proc = run_omniflow([*files, "--rig", rig, "--out", out], wrap=wrap)
    finally:
        for p in tmp_path.rglob("*"):
            p.chmod(0o755)
        tmp_path.chmod(0o755)
    line = check_clean_failure(proc, 1, fragment)
    assert "Permission denied" in line
    assert snapshot(tmp_path) == before  # contents only: the modes were reset above


@pytest.mark.parametrize(
    ("what", "mount", "status", "message"),
    [
        ("read-only", "mount -o remount,ro {fs}", 1, "Read-only file system"),
        ("full", "true", 1, "No space left on device"),
    ],
)
def test_read_only_or_full_file_system_exits_1(base, tmp_path, what, mount, status, message):
    # A private tmpfs (unshare -m) of 24 kB: room for the old outputs (a 4 kB page each)
    # but not the new CSV (about 180 points x 30 columns, ~50 kB); remounted read-only
    # for the first case.
    if not _can(["unshare", "-m", "--propagation", "private", "true"]):
        pytest.skip("unshare -m is not permitted here")
    fs = tmp_path / "fs"
    fs.mkdir()
    old = "; ".join(
        f"printf %s {shlex.quote(data.decode())} > {fs}/out/{name}" for name, data in OLD.items()
    )
    args = " ".join(shlex.quote(str(a)) for a in frames(base))
    script = (
        f"set -e; mount -t tmpfs -o size=24k tmpfs {fs}; mkdir {fs}/out; {old}; "
        f"{mount.format(fs=fs)}; set +e; "
        f"{shlex.quote(omniflow_command())} {args} --rig {base['dir'] / 'rig.toml'} "
        f"--out {fs}/out; rc=$?; "
        f"cd {fs}/out && ls -A | tr '\\n' ' '; echo; sha256sum {' '.join(OLD)}; exit $rc"
    )
    proc = run_omniflow([], shell=script, wrap=["unshare", "-m", "--propagation", "private"])
    assert not os.path.ismount(fs)  # the tmpfs lived only in the private mount namespace
    line = check_clean_failure(proc, status, message)
    assert f"{fs}/out" in line
    listing, *sums = proc.stdout.splitlines()
    assert sorted(listing.split()) == sorted(OLD)  # nothing new: no staging folder left
    for row in sums:
        digest, name = row.split()
        assert digest == hashlib.sha256(OLD[name]).hexdigest(), name


# -- zero matches is an answer: exit 0, one warning line, empty outputs ----------------------


def _blank_frames(base, work, kind):
    rng = np.random.default_rng(5)
    scene = base["scene"]
    imgs = []
    for _k in range(2):
        for cam in ("cam1", "cam2"):
            if kind == "black":
                img = np.zeros((SIZE, SIZE), np.float32)
            elif kind == "constant":
                img = np.full((SIZE, SIZE), 0.5, np.float32)
            elif kind == "lens cap":  # dark frame: sensor noise of 0.2 % about black
                img = np.clip(0.002 * rng.standard_normal((SIZE, SIZE)), 0, 1).astype(np.float32)
            else:  # "cam2 capped": cam1 sees the room, cam2 nothing
                img = scene.render("cam1", _k) if cam == "cam1" else np.zeros((SIZE, SIZE))
            imgs.append(write_png(work / f"{kind.replace(' ', '_')}_{cam}_{_k}.png", img))
    return imgs


@pytest.mark.parametrize("kind", ["black", "constant", "lens cap", "cam2 capped"])
def test_zero_matches_exit_0_with_empty_outputs(base, tmp_path, kind):
    out = tmp_path / "out"
    _old_outputs(out)
    (out / "notes.txt").write_text("the user's own file")
    proc = run_omniflow([*_blank_frames(base, tmp_path, kind), "--rig", base["dir"] / "rig.toml",
                         "--out", out, "--odometry"])  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("omniflow: warning: no stereo matches"), lines
    assert "0 points" in proc.stdout
    with open(out / "flow.csv") as fh:
        rows = [line for line in fh if not line.startswith("#")]
    from omniflow.pipeline import COLUMNS

    header = rows[0].strip().split(",")
    assert set(COLUMNS) <= set(header) and "time_to_contact" in header
    assert rows[1:] == []
    meta = json.loads((out / "flow.json").read_text())
    assert meta["points"] == 0 and meta["median_flow_px"] is None
    assert "error" in meta["odometry"]
    # the new set replaced the old one; the user's file stays; no staging folder is left
    expected = [*OLD, "flow_color.png", "unwarp_cam1.png", "notes.txt", MARKER]
    assert sorted(p.name for p in out.iterdir()) == sorted(expected)
    assert (out / "flow_arrows.png").read_bytes() != OLD["flow_arrows.png"]


def test_estimate_returns_an_empty_result_with_a_warning(base):
    # In-process: every column of a normal result, each of length 0, and NoMatchesWarning.
    from omniflow.pipeline import NoMatchesWarning, OmniFlowConfig, estimate

    rig, scene = base["rig"], base["scene"]
    f = [scene.render(cam, k) for k in range(2) for cam in ("cam1", "cam2")]
    full = estimate(f[0::2], f[1::2], rig)
    assert len(full) > 50  # measured about 180 points on this scene
    black = [np.zeros((SIZE, SIZE), np.float32)] * 2
    for config in (OmniFlowConfig(), OmniFlowConfig.paper()):
        with pytest.warns(NoMatchesWarning, match="no stereo matches"):
            empty = estimate(black, black, rig, config)
        assert len(empty) == 0
        assert list(empty.columns) == list(full.columns)  # same columns, same order
        assert all(v.shape == (0,) for v in empty.columns.values())
        assert empty.timings["total"] > 0


def test_success_replaces_the_old_set_and_drops_stale_pictures(base, tmp_path):
    out = tmp_path / "out"
    _old_outputs(out)
    (out / "unwarp_cam1.png").write_bytes(b"old")
    (out / "mine.txt").write_text("keep")
    proc = run_omniflow([*frames(base), "--rig", base["dir"] / "rig.toml", "--out", out,
                         "--no-pictures"])  # fmt: skip
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "flow.csv", "flow.json", "mine.txt"]
    meta = json.loads((out / "flow.json").read_text())
    assert meta["outputs"] == ["flow.csv", "flow.json"] and meta["points"] > 50
    # a new --out folder appears whole (one rename of the staging folder)
    fresh = tmp_path / "a" / "b" / "fresh"
    proc = run_omniflow([*frames(base), "--rig", base["dir"] / "rig.toml", "--out", fresh])
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in fresh.iterdir()) == sorted(
        [MARKER, "flow.csv", "flow.json", "flow_arrows.png", "flow_color.png", "unwarp_cam1.png"]
    )
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    mask = os.umask(0)
    os.umask(mask)
    assert fresh.stat().st_mode & 0o777 == 0o777 & ~mask  # not the staging folder's 0700


def test_failure_while_writing_leaves_the_old_set(base, tmp_path, monkeypatch, capsys):
    # In-process, a picture write fails after flow.csv was staged: the old flow.csv and
    # flow.json must stay as they were (the issue saw a new CSV beside an old JSON).
    import errno as errno_mod

    import omniflow.cli.pair

    def refuse(path, *args, **kwargs):
        raise OSError(errno_mod.EIO, "Input/output error", str(path))

    monkeypatch.setattr(omniflow.cli.pair, "write_png", refuse)
    out = tmp_path / "out"
    _old_outputs(out)
    before = snapshot(tmp_path)
    argv = [*map(str, frames(base)), "--rig", str(base["dir"] / "rig.toml"), "--out", str(out)]
    assert omniflow.cli.pair.main(argv) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "Input/output error" in err[0], err
    assert f"{out}/flow_arrows.png" in err[0]  # the path under --out, not the staging folder
    assert snapshot(tmp_path) == before


def test_orphaned_staging_folders_are_removed(base, tmp_path):
    # A run killed with -9 leaves its staging folder; the next run into the same place
    # removes it (its process is gone) and leaves a live process's folder alone.
    from omniflow.io.imageio import STAGING_PREFIX

    out = tmp_path / "out"
    _old_outputs(out)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    orphan = out / f"{STAGING_PREFIX}{dead}-abc"
    orphan.mkdir()
    (orphan / "flow.csv").write_text("half")
    live = out / f"{STAGING_PREFIX}{os.getpid()}-xyz"
    live.mkdir()
    proc = run_omniflow([*frames(base), "--rig", base["dir"] / "rig.toml", "--out", out,
                         "--no-pictures"])  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert not orphan.exists() and live.is_dir()
    assert math.isfinite(json.loads((out / "flow.json").read_text())["points"])


# -- never replace what omniflow did not write; one run per --out (issue 25) -----------------


@pytest.mark.parametrize(
    "name, data",
    [("flow.csv", b"x,y\n1,2\n"), ("flow.json", b'{"my": "notes"}\n'), ("flow_color.png", b"art")],
)
def test_a_users_file_with_an_output_name_is_refused(base, tmp_path, name, data):
    # --out has no marker and no flow.json of an omniflow run: the file is the user's
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_bytes(data)
    (tmp_path / "canary.txt").write_text("beside --out")
    before = snapshot(tmp_path)
    proc = run_omniflow([*frames(base), "--rig", base["dir"] / "rig.toml", "--out", out])
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert f"{out / name}: not written by omniflow" in lines[0], lines[0]
    assert snapshot(tmp_path) == before


def test_a_second_run_into_one_out_is_refused(base, tmp_path):
    out = tmp_path / "out"
    _old_outputs(out)
    before = snapshot(tmp_path)
    # "another run" holds the lock beside --out, as a running omniflow does
    fd = os.open(tmp_path / ".out.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.write(fd, b"4242\n")
        proc = run_omniflow([*frames(base), "--rig", base["dir"] / "rig.toml", "--out", out])
    finally:
        os.close(fd)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert f"{out}: another omniflow process (pid 4242) is writing this folder" in lines[0]
    assert {k: v for k, v in snapshot(tmp_path).items() if not k.endswith(".out.lock")} == before


def test_two_runs_into_one_new_out_the_second_is_refused(base, tmp_path):
    # issue 25: without the lock, one failed with "Directory not empty"
    out = tmp_path / "out"
    args = [omniflow_command(), *map(str, frames(base)), "--rig", str(base["dir"] / "rig.toml"),
            "--out", str(out)]  # fmt: skip
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env=_env()) for _ in range(2)]  # fmt: skip
    results = [(p.wait(timeout=300), p.communicate()[1]) for p in procs]
    assert sorted(status for status, _ in results) == [0, 2], results  # they overlap: seconds each
    for status, err in results:
        if status == 2:
            assert len(err.strip().splitlines()) == 1 and "another omniflow process" in err
        else:
            assert err == "", err
    assert json.loads((out / "flow.json").read_text())["points"] > 50
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no staging folder, no lock
