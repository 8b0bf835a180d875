"""Bad input through the installed ``omnisim`` command (issue 11): a table of cases.

Each case builds its inputs in a fresh directory, runs ``omnisim ...`` in a subprocess
(the console script, with this checkout first on PYTHONPATH) and asserts: the exit
status (2 bad input, 1 the environment), exactly one line on stderr that names the
path / key / value, no "Traceback" anywhere, no partial output (a new --out directory
is not created) and existing data untouched (every byte of the files that were there
before, the directory's lock file aside: a run takes the lock before it compares).

Renders use the fake renderer of tests/helpers/fakes.py (32 px, 1 spp); only the
Mitsuba-variant case starts Mitsuba (to ask it about CUDA).
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
OMNISIM = shutil.which("omnisim")
FAKE = ["--renderer", "tests.helpers.fakes:render_frame", "--no-progress"]

pytestmark = pytest.mark.skipif(OMNISIM is None, reason="the omnisim command is not installed")

SCENE = """
name = "bad_input"
frames = 2
frame_interval = 0.1

[render]
width = 32
height = 32
spp = 1

[rig]
d = 0.10
R = 0.05
s = 0.30

[robot]
position = [0.0, 0.0, 0.6]

[[objects]]
name = "room"
type = "room"
size = [4.0, 3.5, 3.0]

[[objects]]
name = "poster"
type = "plane"
size = [0.8, 0.6]
position = [1.2, 0.0, 0.9]
rotation = [0, -90, 0]
[objects.texture]
type = "image"
tile = 0.8
path = "{texture}"

[[lights]]
type = "point"
position = [0.2, -0.3, 2.6]
intensity = 6.0
"""


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env.pop("OMNISIM_FAKE_DELAY", None)
    env.update(extra)
    return env


def _png(path: Path, size: int = 16, seed: int = 0) -> Path:
    import cv2

    img = np.random.default_rng(seed).integers(0, 255, (size, size, 3), dtype=np.uint8)
    assert cv2.imwrite(str(path), img)
    return path


def _png_claiming(path: Path, w: int, h: int) -> Path:
    """A PNG whose header (IHDR) claims w x h RGB pixels, followed by a tiny IDAT."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )
    return path


def _exr(path: Path, size: int = 8) -> Path:
    import OpenEXR

    rng = np.random.default_rng(1)
    chans = {c: rng.random((size, size), dtype=np.float32) for c in "RGB"}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, chans) as f:
        f.write(str(path))
    return path


def _scene(d: Path, texture: str = "poster.png", extra: str = "") -> Path:
    if texture == "poster.png" and not (d / "poster.png").exists():
        _png(d / "poster.png")
    text = SCENE.format(texture=texture)
    p = d / "scene.toml"
    p.write_text(text + extra)
    return p


def _run(args: list[str], **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [OMNISIM, *args],
        capture_output=True,
        text=True,
        env=_env(**env),
        cwd=ROOT,
        timeout=300,
    )


def _render(d: Path, scene: Path, out: Path, frames: int | None = None) -> None:
    """A dataset made in this process (faster than the command; the same files)."""
    from omnisim.job import render_dataset

    ov = {} if frames is None else {"frames": frames}
    render_dataset(scene, out, ov, renderer=FAKE[1], progress=False)


def _snapshot(d: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(d)): p.read_bytes()
        for p in sorted(d.rglob("*"))
        if p.is_file() and p.name != ".omnisim.lock"
    }


# -- the cases ------------------------------------------------------------------------


@dataclass
class Case:
    """``setup(d) -> argv`` (may leave files in d); the expectations."""

    name: str
    setup: Callable[[Path], list[str]]
    status: int
    names: list[str]  # each must appear in the one stderr line ("{d}" is the case dir)
    fresh_out: str | None = "out"  # a --out that must not exist afterwards
    env: dict[str, str] = field(default_factory=dict)
    root_ok: bool = True  # False: root ignores file modes, the case cannot happen


def render_args(scene: Path, out: Path, *more: str) -> list[str]:
    return ["render", str(scene), "--out", str(out), *FAKE, *more]


def _binary_scene(d):
    p = d / "scene.toml"
    p.write_bytes(b"\x89\xff\xfe\x00binary\x00" * 20)
    return render_args(p, d / "out")


def _not_toml(d):
    p = d / "scene.toml"
    p.write_text("name = [unclosed\n")
    return render_args(p, d / "out")


def _unknown_key(d):
    return render_args(_scene(d, extra="\nnosuch = 1\n"), d / "out")


def _out_is_file(d):
    (d / "out").write_text("precious\n")
    return render_args(_scene(d), d / "out")


def _out_under_file(d):
    (d / "afile").write_text("precious\n")
    return render_args(_scene(d), d / "afile" / "out")


def _out_read_only(d):
    (d / "ro").mkdir()
    os.chmod(d / "ro", 0o555)
    return render_args(_scene(d), d / "ro" / "out")


def _out_in_sys(d):
    return render_args(_scene(d), Path("/sys/omnisim_bad_input_test"), "--no-resource-check")


def _out_foreign(d):
    (d / "out").mkdir()
    (d / "out" / "notes.txt").write_text("precious\n")
    return render_args(_scene(d), d / "out")


# Never delete what the command did not write (issue 25): canaries where it writes.
PHOTO = b"\xff\xd8\xff\xe0 a user's photo"


def _out_frames_photo(d):
    """A folder named frames/000000 holding a user's file, no dataset.json."""
    (d / "out" / "frames" / "000000").mkdir(parents=True)
    (d / "out" / "frames" / "000000" / "my_photo.jpg").write_bytes(PHOTO)
    return render_args(_scene(d), d / "out")


def _out_dotfile(d):
    (d / "out").mkdir()
    (d / "out" / ".my_settings").write_text("precious\n")
    return render_args(_scene(d), d / "out")


def _incomplete_frame_photo(d):
    """A dataset of ours whose frame 1 the render would redo holds a user's file."""
    scene = _scene(d)
    _render(d, scene, d / "data")
    frame = d / "data" / "frames" / "000001"
    (frame / "cam1.exr").unlink()
    (frame / "my_photo.jpg").write_bytes(PHOTO)
    return render_args(scene, d / "data")


def _set(*sets: str):
    def setup(d):
        args = render_args(_scene(d), d / "out")
        for s in sets:
            args += ["--set", s]
        return args

    return setup


def _opt(*more: str):
    def setup(d):
        return render_args(_scene(d), d / "out", *more)

    return setup


def _variant(d):
    # The real renderer: the variant check must run before dataset.json is written.
    return ["render", str(_scene(d)), "--out", str(d / "out"), "--no-progress", "--set",
            'render.variant="cuda_ad_rgb"']  # fmt: skip


def _texture(make: Callable[[Path], Path]):
    def setup(d):
        tex = make(d)
        return render_args(_scene(d, texture=tex.name), d / "out")

    return setup


def _changed_asset(d):
    scene = _scene(d)
    _render(d, scene, d / "data", frames=1)
    _png(d / "poster.png", seed=99)  # the texture changes before the resume
    return render_args(scene, d / "data", "--frames", "1")


def _changed_asset_partial(d):
    scene = _scene(d)
    _render(d, scene, d / "data")
    shutil.rmtree(d / "data" / "frames" / "000001")  # as if killed after frame 0
    _png(d / "poster.png", seed=99)
    return render_args(scene, d / "data")


_HELD: list[int] = []


def _locked(d):
    scene = _scene(d)
    _render(d, scene, d / "data")
    shutil.rmtree(d / "data" / "frames" / "000001")  # work left for the second render
    fd = os.open(d / "data" / ".omnisim.lock", os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # "another render" holds the lock
    _HELD.append(fd)
    return render_args(scene, d / "data")


def _enclosed(d):
    box = """
[[objects]]
name = "shell"
type = "box"
size = [0.6, 0.6, 1.6]
position = [0.0, 0.0, 0.7]
"""
    return render_args(_scene(d, extra=box), d / "out")


def _missing_extra(d):
    fake = d / "no_trimesh" / "trimesh"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text(
        "raise ModuleNotFoundError(\"No module named 'trimesh'\", name='trimesh')\n"
    )
    return render_args(_scene(d), d / "out")


def _bad_mesh(d):
    (d / "blob.obj").write_text("v 1 2\nf 1 2 3 4 5\ngarbage\n")
    blob = """
[[objects]]
name = "blob"
type = "mesh"
path = "blob.obj"
position = [1.5, 0.5, 1.0]
"""
    return render_args(_scene(d, extra=blob), d / "out")


def _bad_environment_map(d):
    (d / "sky.exr").write_bytes(bytes(range(256)) * 2)
    sky = """
[[lights]]
type = "environment"
path = "sky.exr"
"""
    return render_args(_scene(d, extra=sky), d / "out")


def _huge_rim(meta):
    for c in meta["cameras"]:  # r_m four times the image, v kept consistent (eq. 2)
        c["v"] = c["v"] / c["r_m"] * 128.0
        c["r_m"] = 128.0


def _dataset(d, frames: int = 2) -> Path:
    _render(d, _scene(d), d / "data", frames=frames)
    return d / "data"


def _edit_meta(change: Callable[[dict], None]):
    def setup(d):
        data = _dataset(d)
        meta = json.loads((data / "dataset.json").read_text())
        change(meta)
        (data / "dataset.json").write_text(json.dumps(meta))
        return ["check", str(data)]

    return setup


def _check_incomplete(d):
    data = _dataset(d, frames=2)
    shutil.rmtree(data / "frames" / "000001")
    return ["check", str(data)]


def _check_corrupt_exr(d):
    data = _dataset(d, frames=1)
    (data / "frames" / "000000" / "cam1.exr").write_bytes(b"not an exr" * 10)
    return ["check", str(data)]


def _check_binary_meta(d):
    (d / "data").mkdir()
    (d / "data" / "dataset.json").write_bytes(b"\xff\xfe\x00\x01" * 50)
    return ["check", str(d / "data")]


def _check_not_json(d):
    (d / "data").mkdir()
    (d / "data" / "dataset.json").write_text("{not json")
    return ["check", str(d / "data")]


def _check_json_under_file(d):
    data = _dataset(d, frames=1)
    (d / "afile").write_text("precious\n")
    return ["check", str(data), "--json", str(d / "afile" / "r.json")]


def _check_json_in_no_folder(d):
    return ["check", str(_dataset(d, frames=1)), "--json", str(d / "nodir" / "r.json")]


def _check_frames(text: str):
    def setup(d):
        return ["check", str(_dataset(d, frames=1)), "--frames", text]

    return setup


def _export_with(change: Callable[[Path], None], fmt: str = "sintel"):
    """A complete 2-frame dataset, ``change(frames dir)``, then ``omnisim export``."""

    def setup(d):
        data = _dataset(d)
        change(data / "frames")
        return ["export", str(data), "--format", fmt, "--out", str(d / "out")]

    return setup


def _radiance_set(k: int, cam: str, value: float):
    """Put ``value`` (NaN, inf) into a few R pixels of frame k's EXR."""

    def change(frames: Path) -> None:
        from omnisim.dataset import read_exr, write_exr

        p = frames / f"{k:06d}" / f"{cam}.exr"
        ch = read_exr(p)
        ch["R"][10:12, 10:13] = value
        write_exr(p, ch)

    return change


def _truncate(rel: str, keep: float = 0.5):
    def change(frames: Path) -> None:
        p = frames / rel
        data = p.read_bytes()
        p.write_bytes(data[: int(len(data) * keep)])

    return change


def _short_poses(meta):
    meta["robot"]["poses"] = meta["robot"]["poses"][:1]


def _obj_poses_nan(meta):
    meta["objects"][0]["poses"][0][0][0] = None


CASES = [
    # render: the scene file
    Case("scene missing", lambda d: render_args(d / "nosuch.toml", d / "out"), 2, ["nosuch.toml"]),
    Case("scene binary", _binary_scene, 2, ["scene.toml", "UTF-8"]),
    Case("scene not TOML", _not_toml, 2, ["scene.toml", "TOML"]),
    Case("unknown key", _unknown_key, 2, ["scene.toml", "nosuch"]),
    Case("scene is a directory", lambda d: render_args(d, d / "out"), 2, ["not found"]),
    Case("rig enclosed by an object", _enclosed, 2, ["objects[2]", "shell", "encloses"]),
    Case("frames over the maximum", _set("frames=200000"), 2, ["frames", "200000", "100000"]),
    Case("format of --set", _opt("--set", "frames"), 2, ["--set", "KEY=VALUE"]),
    Case("--frames 0", _opt("--frames", "0"), 2, ["--frames", "'0'"]),
    Case("--resolution abc", _opt("--resolution", "abc"), 2, ["--resolution", "abc"]),
    Case("--spp -1", _opt("--spp", "-1"), 2, ["--spp", "-1"]),
    Case("--set render.spp=0", _set("render.spp=0"), 2, ["render.spp", "got 0"]),
    Case(
        "rig error out of range",
        _set("rig.errors.cam1.cone_angle=120"),
        2,
        ["rig.errors.cam1.cone_angle", "set by an override", "120", "[80, 100] deg"],
    ),
    Case("resolution too small", _opt("--resolution", "4"), 2, ["render.width", "4"]),
    Case(
        "resolution beyond memory or disk",
        # ~180 GiB of memory per frame, else ~4 PB of disk: refused on any machine
        _opt("--resolution", "16384", "--frames", "100000"),
        2,
        ["16384x16384", "--no-resource-check"],
    ),
    Case("variant without CUDA", _variant, 2, ["render.variant", "cuda_ad_rgb"]),
    # render: the output directory
    Case("--out is a file", _out_is_file, 2, ["{d}/out", "not a directory"], fresh_out=None),
    Case("--out under a file", _out_under_file, 2, ["afile"], fresh_out="afile/out"),
    Case(
        "--out in a read-only dir",
        _out_read_only,
        2,
        ["{d}/ro/out", "ermission denied"],
        fresh_out="ro/out",
        root_ok=False,
    ),
    Case("--out in /sys", _out_in_sys, 2, ["/sys/omnisim_bad_input_test"], fresh_out=None),
    Case("--out foreign dir", _out_foreign, 2, ["{d}/out", "not empty"], fresh_out=None),
    Case(
        "--out holds frames/000000/my_photo.jpg",
        _out_frames_photo,
        2,
        ["{d}/out/frames/000000", "no dataset.json"],
        fresh_out=None,
    ),
    Case("--out holds a dotfile", _out_dotfile, 2, ["{d}/out/.my_settings"], fresh_out=None),
    Case(
        "incomplete frame holds my_photo.jpg",
        _incomplete_frame_photo,
        2,
        ["{d}/data/frames/000001/my_photo.jpg", "not written by omnisim render"],
        fresh_out=None,
    ),
    Case(
        "changed texture on resume",
        _changed_asset,
        2,
        ["poster.png", "changed", "{d}/data"],
        fresh_out=None,
    ),
    Case(
        "changed texture, half-done",
        _changed_asset_partial,
        2,
        ["poster.png", "changed"],
        fresh_out=None,
    ),
    Case("second render, dir locked", _locked, 2, ["{d}/data", "another omnisim"], fresh_out=None),
    # render: input images
    Case(
        "PNG claiming 100000x100000",
        _texture(lambda d: _png_claiming(d / "huge.png", 100000, 100000)),
        2,
        ["huge.png", "100000x100000", "objects[1].texture.path"],
    ),
    Case(
        "PNG that is not a PNG",
        _texture(lambda d: (d / "junk.png").write_bytes(b"junk" * 30) and d / "junk.png"),
        2,
        ["junk.png", "objects[1].texture.path"],
    ),
    Case(
        "EXR that is not an EXR",
        _texture(lambda d: (d / "junk.exr").write_bytes(b"junk" * 30) and d / "junk.exr"),
        2,
        ["junk.exr", "objects[1].texture.path"],
    ),
    Case(
        "texture of the wrong kind",
        _texture(lambda d: (d / "t.txt").write_text("x") and d / "t.txt"),
        2,
        ["objects[1].texture.path", "t.txt"],
    ),
    Case("texture missing", _texture(lambda d: d / "gone.png"), 2, ["gone.png", "not found"]),
    Case("mesh file garbage", _bad_mesh, 2, ["objects[2].path", "blob.obj"]),
    Case("environment map garbage", _bad_environment_map, 2, ["lights[1].path", "sky.exr"]),
    # render: the cluster and the installation
    Case(
        "scheduler unreachable",
        _opt("--scheduler", "tcp://127.0.0.1:9", "--scheduler-timeout", "1"),
        1,
        ["tcp://127.0.0.1:9", "no Dask scheduler answered"],
    ),
    Case(
        "scheduler address malformed",
        _opt("--scheduler", "nosuch://x", "--scheduler-timeout", "1"),
        2,
        ["nosuch://x"],
    ),
    Case(
        "scheduler address without a port",
        _opt("--scheduler", "nonsense", "--scheduler-timeout", "1"),
        2,
        ["'nonsense'", "missing port number"],
    ),
    Case(
        "sim extra missing",
        _missing_extra,
        1,
        ["trimesh", "pip install", "[sim]"],
        env={"PYTHONPATH_PREPEND": "no_trimesh"},
    ),
    # check
    Case("check: no such dir", lambda d: ["check", str(d / "nope")], 2, ["nope"], fresh_out=None),
    Case("check: binary dataset.json", _check_binary_meta, 2, ["dataset.json", "UTF-8"], None),
    Case("check: dataset.json not JSON", _check_not_json, 2, ["dataset.json", "JSON"], None),
    Case("check: incomplete", _check_incomplete, 2, ["incomplete", "1 of 2", "--partial"], None),
    Case(
        "check: format_version 0",
        _edit_meta(lambda m: m.update(format_version=0)),
        2,
        ["dataset.json", "format_version = 0"],
        None,
    ),
    Case(
        "check: format_version text",
        _edit_meta(lambda m: m.update(format_version="1")),
        2,
        ["format_version = '1'"],
        None,
    ),
    Case(
        "check: robot.poses shorter than frames",
        _edit_meta(_short_poses),
        2,
        ["dataset.json", "robot.poses", "frames = 2"],
        None,
    ),
    Case(
        "check: a pose with null",
        _edit_meta(_obj_poses_nan),
        2,
        ["objects[0].poses[0][0][0]", "finite"],
        None,
    ),
    Case(
        "check: frames not a number",
        _edit_meta(lambda m: m.update(frames="two")),
        2,
        ["dataset.json", "frames"],
        None,
    ),
    Case(
        "check: r_m four times the image",
        _edit_meta(_huge_rim),
        2,
        ["dataset.json", "r_m = 128", "32x32"],
        None,
    ),
    Case("check: corrupt EXR", _check_corrupt_exr, 2, ["cam1.exr"], None),
    Case("check: --frames 5:2", _check_frames("5:2"), 2, ["--frames", "5:2"], None),
    # export (issue 25): bad data is refused, not written
    Case(
        "export: NaN radiance",
        _export_with(_radiance_set(1, "cam2", float("nan"))),
        2,
        ["{d}/data/frames/000001/cam2.exr", "6 NaN", "finite"],
    ),
    Case(
        "export: infinite radiance",
        _export_with(_radiance_set(0, "cam1", float("inf")), fmt="png"),
        2,
        ["{d}/data/frames/000000/cam1.exr", "6 infinite", "finite"],
    ),
    Case(
        "export: truncated camera PNG",
        _export_with(_truncate("000001/cam1.png")),
        2,
        ["{d}/data/frames/000001/cam1.png", "truncated"],
    ),
    Case(
        "export: camera PNG of another size",
        _export_with(lambda f: _png(f / "000000" / "cam2.png", size=16), fmt="png"),
        2,
        ["{d}/data/frames/000000/cam2.png", "is 16x16; expected 32x32"],
    ),
    Case("check: --frames abc", _check_frames("abc"), 2, ["--frames", "abc"], None),
    Case(
        "check: --json under a file",
        _check_json_under_file,
        2,
        ["--json {d}/afile/r.json", "afile is a file, not a folder"],
        "afile/r.json",
    ),
    Case(
        "check: --json in no folder",
        _check_json_in_no_folder,
        2,
        ["--json {d}/nodir/r.json", "does not exist"],
        "nodir",
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input(case: Case, tmp_path: Path):
    d = tmp_path
    if not case.root_ok and os.geteuid() == 0:
        pytest.skip("root writes into read-only directories")
    if "/sys" in case.name and not Path("/sys").is_dir():
        pytest.skip("no /sys here")
    argv = case.setup(d)
    before = _snapshot(d)
    env = dict(case.env)
    if "PYTHONPATH_PREPEND" in env:
        pre = d / env.pop("PYTHONPATH_PREPEND")
        env["PYTHONPATH"] = os.pathsep.join([str(pre), str(ROOT)])
    try:
        res = _run(argv, **env)
    finally:
        while _HELD:
            os.close(_HELD.pop())
    lines = res.stderr.splitlines()
    assert "Traceback" not in res.stderr + res.stdout, res.stderr
    assert res.returncode == case.status, (res.returncode, res.stderr)
    assert len(lines) == 1, res.stderr
    for name in case.names:
        assert name.replace("{d}", str(d)) in lines[0], (name, lines[0])
    assert _snapshot(d) == before  # existing data untouched, nothing half-written
    if case.fresh_out is not None:
        assert not (d / case.fresh_out).exists(), sorted(os.listdir(d))


# -- what the refusals let through -----------------------------------------------------


def test_partial_check_says_what_is_missing(tmp_path):
    data = _dataset(tmp_path, frames=2)
    shutil.rmtree(data / "frames" / "000001")
    res = _run(["check", str(data), "--partial"])
    assert "Traceback" not in res.stderr
    assert "1 of 2 frames rendered; checking 1 (1 missing, not checked)" in res.stdout, res.stdout


def test_exr_texture_and_environment_map_are_read(tmp_path):
    from omnisim.textures import load_image_texture

    tex = load_image_texture(_exr(tmp_path / "t.exr"))
    assert tex.shape == (8, 8, 3) and tex.dtype == np.float32
    env = """
[[lights]]
type = "environment"
path = "sky.exr"
"""
    _exr(tmp_path / "sky.exr")
    scene = _scene(tmp_path, texture="t.exr", extra=env)
    _render(tmp_path, scene, tmp_path / "out", frames=1)
    meta = json.loads((tmp_path / "out" / "dataset.json").read_text())
    assert set(meta["inputs"]["files"]) == {"t.exr", "sky.exr"}


def test_dataset_json_names_objects_kind_and_input_hashes(tmp_path):
    import hashlib

    data = _dataset(tmp_path, frames=1)
    meta = json.loads((data / "dataset.json").read_text())
    assert [o["kind"] for o in meta["objects"]] == ["room"] * 6 + ["plane"]
    entry = meta["inputs"]["files"]["poster.png"]
    assert entry["key"] == "objects[1].texture.path"
    assert entry["sha256"] == hashlib.sha256((tmp_path / "poster.png").read_bytes()).hexdigest()


def test_same_inputs_resume(tmp_path):
    """The fingerprint does not refuse a resume whose inputs are the same bytes."""
    scene = _scene(tmp_path)
    _render(tmp_path, scene, tmp_path / "data")
    shutil.rmtree(tmp_path / "data" / "frames" / "000001")
    os.utime(tmp_path / "poster.png", (1, 1))  # touched, same content
    res = _run(render_args(scene, tmp_path / "data"))
    assert res.returncode == 0 and "1 rendered now, 1 already done" in res.stdout, res.stderr


def test_debug_shows_the_traceback(tmp_path):
    res = _run(["check", str(tmp_path / "nope"), "--debug"])
    assert res.returncode == 2 and "Traceback" in res.stderr


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))


@pytest.mark.slow  # 5.6 s (docs/decisions/slow_tests.md)
def test_two_renders_into_one_directory(tmp_path):
    """The second render is refused with one line while the first runs; the first
    finishes every frame (its temporaries are not touched by the second)."""
    scene = _scene(tmp_path)
    argv = render_args(scene, tmp_path / "data", "--frames", "4")
    first = subprocess.Popen(
        [OMNISIM, *argv],
        env=_env(OMNISIM_FAKE_DELAY="1.0"),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        meta = tmp_path / "data" / "dataset.json"
        for _ in range(600):
            if meta.exists() or first.poll() is not None:
                break
            __import__("time").sleep(0.05)
        second = _run(argv)
        out, err = first.communicate(timeout=120)
    finally:
        first.kill()
        first.wait()
    assert second.returncode == 2 and len(second.stderr.splitlines()) == 1, second.stderr
    assert "another omnisim process" in second.stderr and "Traceback" not in second.stderr
    assert first.returncode == 0, err
    assert "4 rendered now" in out
    frames = sorted(p.name for p in (tmp_path / "data" / "frames").iterdir())
    assert frames == ["000000", "000001", "000002", "000003"]


# -- the Dask cluster failing -------------------------------------------------------------


@pytest.fixture
def lonely_cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
    ) as lc:
        yield lc


def test_scheduler_without_workers(tmp_path, lonely_cluster):
    from omnisim.distributed import ClusterError
    from omnisim.job import render_dataset

    lonely_cluster.scale(0)
    lonely_cluster.sync(lonely_cluster._correct_state)
    scene = _scene(tmp_path)
    with pytest.raises(ClusterError, match="has no workers"):
        render_dataset(
            scene,
            tmp_path / "out",
            renderer=FAKE[1],
            scheduler=lonely_cluster.scheduler_address,
            scheduler_timeout=1.0,
            progress=False,
        )
    assert not (tmp_path / "out").exists()  # nothing rendered: nothing left


def test_all_workers_gone_mid_run(tmp_path, lonely_cluster):
    from distributed import Client

    from omnisim.distributed import ClusterError
    from omnisim.job import render_dataset

    scene = _scene(tmp_path)
    with Client(lonely_cluster) as client:

        def retire(k):
            if k == 0:  # the only worker goes away after the first frame
                lonely_cluster.scale(0)
                lonely_cluster.sync(lonely_cluster._correct_state)

        with pytest.raises(ClusterError, match="all Dask workers are gone"):
            render_dataset(
                scene,
                tmp_path / "out",
                {"frames": 6},
                renderer=FAKE[1],
                scheduler=client,
                scheduler_timeout=2.0,
                progress=False,
                on_frame=retire,
            )
    done = sorted(p.name for p in (tmp_path / "out" / "frames").iterdir())
    assert "000000" in done and len(done) < 6  # the finished frames stay for a resume
