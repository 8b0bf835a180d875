"""The dataset contract: writer/reader round trips, .flo, atomic frames, resume checks."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from omniflow.geometry.rig import Rig
from omnisim import dataset as ds
from omnisim.dataset import (
    CHANNELS,
    FLO_UNKNOWN,
    DatasetError,
    DatasetMismatchError,
    DatasetWriter,
    open_dataset,
    read_flo,
)

CONTRACT = [
    "R",
    "G",
    "B",
    "gt.valid",
    "gt.r",
    "gt.theta",
    "gt.h",
    "gt.X",
    "gt.Y",
    "gt.Z",
    "gt.object",
    "gt.flow.dx",
    "gt.flow.dy",
    "gt.flow.dh",
    "gt.flow.hdtheta",
    "gt.flow.valid",
    "gt.stereo.h_other",
    "gt.stereo.valid",
]


#: Format version 2 adds these after gt.flow.valid.
CONTRACT_V2_ADDED = [
    "gt.flow.occluded",
    "gt.flow.outside",
    "gt.bflow.dx",
    "gt.bflow.dy",
    "gt.bflow.dh",
    "gt.bflow.hdtheta",
    "gt.bflow.valid",
    "gt.bflow.occluded",
    "gt.bflow.outside",
]


def make_meta(frames: int = 3, size: int = 24, seed: int = 1, version: int = 2) -> dict:
    rig = Rig.symmetric(d=0.1, R=0.05, s=0.3, size=size)
    return {
        "format": ds.FORMAT_NAME,
        "format_version": version,
        "scene": {"name": "t", "path": "/x/t.toml", "source": "# scene\n", "overrides": {}},
        **rig.to_dict(),
        "frames": frames,
        "frame_interval": 0.1,
        "render": {"width": size, "height": size, "spp": 2, "seed": seed},
        "seed": seed,
        "objects": [{"id": 1, "name": "wall", "poses": [np.eye(4).tolist()] * frames}],
        "robot": {"poses": [np.eye(4).tolist()] * frames},
        "versions": {"omnisim": "0"},
    }


def make_frame(k: int, size: int = 24, cams=("cam1", "cam2"), version: int = 2) -> dict:
    if version == 1:
        v1 = make_frame(k, size, cams)
        return {cam: {name: ch[name] for name in ds.CHANNELS_V1} for cam, ch in v1.items()}
    out = {}
    for ci, cam in enumerate(cams):
        rng = np.random.default_rng(100 * k + ci)
        ch = {name: rng.normal(size=(size, size)).astype(np.float32) for name in CHANNELS}
        for name in ("gt.valid", "gt.flow.valid", "gt.stereo.valid"):
            ch[name] = (rng.random((size, size)) > 0.3).astype(np.float32)
        for key in ("gt.flow", "gt.bflow"):  # version 2: three disjoint 0/1 masks
            split = rng.integers(0, 4, (size, size)) * ch["gt.valid"]
            for m, name in enumerate(("valid", "occluded", "outside"), start=1):
                ch[f"{key}.{name}"] = (split == m).astype(np.float32)
        ch["gt.object"] = rng.integers(0, 3, (size, size)).astype(np.float32)
        out[cam] = ch
    return out


def test_channel_names_are_the_contract():
    assert list(ds.CHANNELS_V1) == CONTRACT  # version 1
    i = CONTRACT.index("gt.flow.valid") + 1
    assert list(CHANNELS) == [*CONTRACT[:i], *CONTRACT_V2_ADDED, *CONTRACT[i:]]
    assert set(ds.CHANNEL_INFO) == set(CHANNELS)


@pytest.mark.parametrize("version", [1, 2])
def test_round_trip(tmp_path, version):
    meta = make_meta(version=version)
    w = DatasetWriter(tmp_path / "d", meta)
    frames = {k: make_frame(k, version=version) for k in range(3)}
    for k, fr in frames.items():
        w.write_frame(k, fr)
    d = open_dataset(tmp_path / "d")
    assert d.meta == json.loads(json.dumps(meta))
    assert d.frame_count == 3 and d.complete and d.frames_done() == [0, 1, 2]
    assert d.rig == Rig.symmetric(d=0.1, R=0.05, s=0.3, size=24)
    assert d.objects == {1: "wall"}
    assert sorted(p.name for p in (tmp_path / "d" / "frames").iterdir()) == [
        "000000",
        "000001",
        "000002",
    ]
    masks = ["occluded.png", "outside.png"] if version == 2 else []
    assert sorted(p.name for p in (tmp_path / "d" / "frames" / "000001").iterdir()) == [
        f"{cam}.{ext}" for cam in ("cam1", "cam2") for ext in ["exr", "flo", *masks]
    ]
    contract = CONTRACT + (CONTRACT_V2_ADDED if version == 2 else [])
    for k, fr in frames.items():
        for cam in ("cam1", "cam2"):
            got = d.read_frame(k, cam)
            assert list(sorted(got)) == sorted(contract)
            for name in contract:
                assert got[name].dtype == np.float32
                np.testing.assert_array_equal(got[name], fr[cam][name])
            rgb = d.read_rgb(k, cam)
            assert rgb.shape == (24, 24, 3)


def test_exr_is_zip_float32(tmp_path):
    import OpenEXR

    w = DatasetWriter(tmp_path / "d", make_meta(frames=1))
    w.write_frame(0, make_frame(0))
    with OpenEXR.File(str(tmp_path / "d/frames/000000/cam1.exr"), separate_channels=True) as f:
        hdr = dict(f.header())  # the header is emptied when the file closes
        assert hdr["compression"] == OpenEXR.ZIP_COMPRESSION
        assert sorted(f.channels()) == sorted(CONTRACT + CONTRACT_V2_ADDED)
        assert all(c.pixels.dtype == np.float32 for c in f.channels().values())


def test_flo_round_trip_and_opencv(tmp_path):
    rng = np.random.default_rng(3)
    dx = rng.normal(size=(7, 11)).astype(np.float32)
    dy = rng.normal(size=(7, 11)).astype(np.float32)
    valid = rng.random((7, 11)) > 0.2
    p = tmp_path / "a.flo"
    ds.write_flo(p, dx, dy, valid)
    raw = p.read_bytes()
    assert raw[:4] == b"PIEH" and len(raw) == 12 + 8 * 7 * 11
    flow, ok = read_flo(p)
    np.testing.assert_array_equal(ok, valid)
    np.testing.assert_array_equal(flow[..., 0][valid], dx[valid])
    np.testing.assert_array_equal(flow[..., 1][valid], dy[valid])
    assert np.all(flow[~valid] == np.float32(FLO_UNKNOWN))
    cvflow = cv2.readOpticalFlow(str(p))
    assert cvflow.shape == (7, 11, 2)
    np.testing.assert_array_equal(cvflow, flow)


def test_flo_reader_accepts_1e9_as_unknown(tmp_path):
    p = tmp_path / "b.flo"
    dx = np.array([[1.0, 1e9]], np.float32)
    ds.write_flo(p, dx, np.zeros_like(dx))
    _, ok = read_flo(p)
    assert ok.tolist() == [[True, False]]


def test_bad_flo(tmp_path):
    p = tmp_path / "c.flo"
    p.write_bytes(b"XXXX" + b"\0" * 20)
    with pytest.raises(DatasetError, match="magic"):
        read_flo(p)


def test_channel_contract_enforced(tmp_path):
    w = DatasetWriter(tmp_path / "d", make_meta(frames=1))
    fr = make_frame(0)
    del fr["cam1"]["gt.flow.dh"]
    with pytest.raises(DatasetError, match=r"gt\.flow\.dh"):
        w.write_frame(0, fr)
    fr = make_frame(0)
    fr["cam2"]["gt.extra"] = fr["cam2"]["R"]
    with pytest.raises(DatasetError, match=r"gt\.extra"):
        w.write_frame(0, fr)
    assert not any((tmp_path / "d" / "frames").iterdir())


def test_exception_mid_frame_leaves_no_final_name(tmp_path, monkeypatch):
    w = DatasetWriter(tmp_path / "d", make_meta(frames=2))
    files = ds.encode_frame(make_frame(0), w.cameras, k=0)
    calls = []
    real = ds._write_synced

    def failing(path, data):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt("simulated kill mid-frame")
        real(path, data)

    monkeypatch.setattr(ds, "_write_synced", failing)
    with pytest.raises(KeyboardInterrupt):
        w.write_frame_files(0, files)
    monkeypatch.setattr(ds, "_write_synced", real)
    assert not (tmp_path / "d/frames/000000").exists()
    assert not w.is_done(0) and w.todo_frames() == [0, 1]
    # A partial temporary directory left by a hard kill is removed on resume.
    (tmp_path / "d/frames/.000001.tmp.123.abcd").mkdir()
    (tmp_path / "d/frames/.000001.tmp.123.abcd/cam1.exr").write_bytes(b"partial")
    w2 = DatasetWriter(tmp_path / "d", make_meta(frames=2))
    assert not (tmp_path / "d/frames/.000001.tmp.123.abcd").exists()
    w2.write_frame_files(0, files)
    assert w2.is_done(0)
    assert (tmp_path / "d/frames/000000/cam1.exr").read_bytes() == files["cam1.exr"]


def test_resume_refuses_mismatch(tmp_path):
    DatasetWriter(tmp_path / "d", make_meta(seed=1))
    DatasetWriter(tmp_path / "d", make_meta(seed=1))  # same settings: fine
    moved = make_meta(seed=1)
    moved["scene"]["path"] = "/elsewhere/t.toml"  # same content at another path: fine
    DatasetWriter(tmp_path / "d", moved)
    with pytest.raises(DatasetMismatchError, match=r"refusing to resume.*seed"):
        DatasetWriter(tmp_path / "d", make_meta(seed=2))
    with pytest.raises(DatasetMismatchError, match="frames: 3 in the directory vs 4 now"):
        DatasetWriter(tmp_path / "d", make_meta(frames=4))
    other = make_meta()
    other["scene"]["source"] = "# another scene\n"
    with pytest.raises(DatasetMismatchError, match=r"scene\.source"):
        DatasetWriter(tmp_path / "d", other)


def test_timing_is_recorded_kept_on_resume_and_ignored_by_it(tmp_path):
    w = DatasetWriter(tmp_path / "d", make_meta(frames=3))
    w.record_timing(0, {"render": 1.0, "groundtruth": 0.5}, {"cpus": 2})
    w.record_timing(1, {"render": 3.0, "groundtruth": 0.25})
    w.close()
    meta = json.loads((tmp_path / "d" / "dataset.json").read_text())
    t = meta["timing"]
    assert t["frames"] == {
        "0": {"render": 1.0, "groundtruth": 0.5},
        "1": {"render": 3.0, "groundtruth": 0.25},
    }
    assert t["median_s"] == {"render": 2.0, "groundtruth": 0.375}  # (1 + 3) / 2, (0.5 + 0.25) / 2
    assert t["spp"] == 2  # repeated from render
    assert t["cpus"] == 2  # the context given with frame 0 is kept
    assert {k: v for k, v in meta.items() if k != "timing"} == ds._canonical(make_meta(frames=3))
    # a resume with the same settings is not refused by the timing section, and keeps it
    w2 = DatasetWriter(tmp_path / "d", make_meta(frames=3))
    w2.record_timing(2, {"render": 2.0, "groundtruth": 0.5})
    w2.close()
    t2 = json.loads((tmp_path / "d" / "dataset.json").read_text())["timing"]
    assert sorted(t2["frames"]) == ["0", "1", "2"]
    assert t2["median_s"]["render"] == 2.0  # median of 1, 3, 2


def test_refuses_non_dataset_dir(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty"):
        DatasetWriter(tmp_path / "d", make_meta())
    with pytest.raises(DatasetError, match="not an omnisim dataset"):
        open_dataset(tmp_path / "d")


def test_read_missing_frame(tmp_path):
    w = DatasetWriter(tmp_path / "d", make_meta(frames=2))
    w.write_frame(0, make_frame(0))
    d = open_dataset(tmp_path / "d")
    assert not d.complete and d.frames_done() == [0]
    with pytest.raises(DatasetError, match="not rendered"):
        d.read_frame(1, "cam1")
    with pytest.raises(DatasetError, match="unknown camera"):
        d.read_frame(0, "cam3")


def test_same_frame_same_bytes(tmp_path):
    a = ds.encode_frame(make_frame(1), ["cam1", "cam2"], k=1)
    b = ds.encode_frame(make_frame(1), ["cam1", "cam2"], k=1)
    assert a == b


# -- one writer at a time; temporaries; nothing left by a failed start --------------------

_HOLD = """
import sys, time
sys.path[:0] = {paths!r}
from omnisim.dataset import DatasetWriter
import tests.omnisim.test_dataset as t
w = DatasetWriter({d!r}, t.make_meta(frames=2))
print("held", flush=True)
time.sleep(60)
"""


def test_second_writer_in_another_process_is_refused(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    d = tmp_path / "d"
    w = DatasetWriter(d, make_meta(frames=2))
    w.write_frame(0, make_frame(0))
    (d / "frames" / ".000001.tmp.1.abcd").mkdir()  # "the other writer's" frame in progress
    root = str(Path(__file__).resolve().parents[2])
    code = _HOLD.format(paths=[root], d=str(d))
    # Held here: the other process is refused and removes nothing.
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "DatasetLockedError" in proc.stderr
    assert "another omnisim process" in proc.stderr and "use another --out" in proc.stderr
    assert (d / "frames" / ".000001.tmp.1.abcd").is_dir()
    # Same process: a second writer shares the lock (tests, threaded Dask workers).
    DatasetWriter(d, make_meta(frames=2), cleanup=False).close()
    w.close()
    # Released: another process takes it (and would now clean up).
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        assert not (d / "frames" / ".000001.tmp.1.abcd").exists()
        with pytest.raises(ds.DatasetLockedError, match=f"pid {proc.pid}"):
            DatasetWriter(d, make_meta(frames=2))
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()
    DatasetWriter(d, make_meta(frames=2)).close()  # a killed holder leaves no lock


def test_encoder_scratch_names_are_cleaned_up(tmp_path):
    """kill -9 while OpenEXR writes leaves the encoder's scratch directory: both the
    current name (.exr.tmp.*) and the old one (tmpXXXXXXXX holding x.exr) are removed
    on resume; a tmp-like directory holding anything else is not ours and stays."""
    import tempfile

    d = tmp_path / "d"
    w = DatasetWriter(d, make_meta(frames=1))
    frames = d / "frames"
    seen = []
    real = tempfile.TemporaryDirectory

    def spy(*a, **kw):
        t = real(*a, **kw)
        seen.append(Path(t.name).name)
        return t

    from pathlib import Path

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tempfile, "TemporaryDirectory", spy)
        w.write_frame(0, make_frame(0))
    assert seen and all(ds._TMP_RE.match(n) for n in seen), seen
    w.close()
    for name in (".exr.tmp.k2j4l5", "tmpab12cd34"):
        (frames / name).mkdir()
        (frames / name / "x.exr").write_bytes(b"half an exr")
    (frames / "tmpzz99zz99").mkdir()
    (frames / "tmpzz99zz99" / "notes.txt").write_text("mine")
    DatasetWriter(d, make_meta(frames=1)).close()
    assert sorted(p.name for p in frames.iterdir()) == ["000000", "tmpzz99zz99"]


def test_abandon_removes_only_what_this_start_made(tmp_path):
    d = tmp_path / "new" / "d"
    w = DatasetWriter(d, make_meta(frames=2))
    w.abandon()
    assert not (tmp_path / "new").exists()
    # An existing dataset with a frame is never touched.
    w = DatasetWriter(d, make_meta(frames=2))
    w.write_frame(0, make_frame(0))
    w.abandon()
    assert (d / "dataset.json").is_file() and w.is_done(0)
    # A resume into it made nothing, so abandoning it removes nothing.
    w2 = DatasetWriter(d, make_meta(frames=2))
    w2.abandon()
    assert (d / "dataset.json").is_file() and w2.is_done(0)


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda m: m.update(format_version=0), "format_version = 0"),
        (lambda m: m.update(format_version=True), "format_version = True"),
        (lambda m: m["robot"].update(poses=m["robot"]["poses"][:2]), "robot.poses has 2 entries"),
        (lambda m: m["objects"][0].update(poses=[[1, 2]] * 3), r"objects\[0\].poses: expected"),
    ],
)
def test_open_refuses_bad_metadata(tmp_path, change, match):
    meta = make_meta(frames=3)
    change(meta)
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=match):
        open_dataset(tmp_path / "d")


# -- format version 2 -------------------------------------------------------------------------


def test_v2_flo_holds_every_defined_flow_and_masks_beside_it(tmp_path):
    """.flo: the flow wherever gt.flow.valid, occluded or outside is 1; 1e10 only where no
    next position exists. The mask PNGs equal the channels (read back with OpenCV)."""
    w = DatasetWriter(tmp_path / "d", make_meta(frames=1))
    fr = make_frame(0)
    w.write_frame(0, fr)
    d = open_dataset(tmp_path / "d")
    for cam in ("cam1", "cam2"):
        ch = fr[cam]
        defined = (ch["gt.flow.valid"] + ch["gt.flow.occluded"] + ch["gt.flow.outside"]) > 0
        assert 0 < ch["gt.flow.occluded"].sum() and 0 < ch["gt.flow.outside"].sum()
        cv_flow = cv2.readOpticalFlow(str(d.path(0, cam, "flo")))
        np.testing.assert_array_equal(cv_flow[defined, 0], ch["gt.flow.dx"][defined])
        np.testing.assert_array_equal(cv_flow[defined, 1], ch["gt.flow.dy"][defined])
        assert (cv_flow[~defined] == FLO_UNKNOWN).all()
        _, known = d.read_flo(0, cam)
        assert (known == defined).all()
        masks = d.read_flow_masks(0, cam)
        for suffix, name in ds.MASK_FILES.items():
            png = cv2.imread(str(d.path(0, cam, suffix)), cv2.IMREAD_UNCHANGED)
            assert png.dtype == np.uint8 and set(np.unique(png)) == {0, 255}
            assert ((png == 255) == (ch[name] == 1)).all() and (masks[name] == (png == 255)).all()


def test_v2_exr_header_describes_the_frame(tmp_path):
    """Rig, camera, units and each channel's meaning are in the EXR header; the numbers
    are exact (decimal strings of the float64 in dataset.json)."""
    import OpenEXR

    meta = make_meta(frames=1)
    meta["rig"]["d"] = 0.1 + 1e-12  # a value float32 could not keep
    w = DatasetWriter(tmp_path / "d", meta)
    w.write_frame(0, make_frame(0))
    d = open_dataset(tmp_path / "d")
    with OpenEXR.File(str(d.path(0, "cam2", "exr"))) as f:
        hdr = dict(f.header())  # the header is emptied when the file closes
    assert hdr["omnisim.camera"] == "cam2" and hdr["omnisim.frame"] == "0"
    assert hdr["omnisim.format"] == "omnisim-dataset 2"
    assert float(hdr["omnisim.rig.d"]) == meta["rig"]["d"]
    for key in ("R", "s"):
        assert float(hdr[f"omnisim.rig.{key}"]) == meta["rig"][key]
    cam2 = meta["cameras"][1]
    for key in ("tip_h", "x_c", "y_c", "r_m", "v"):
        assert float(hdr[f"omnisim.cam.{key}"]) == cam2[key], key
    for name in CHANNELS:
        assert hdr[f"omnisim.channel.{name}"].startswith(f"[{ds.CHANNEL_INFO[name][0]}] ")
    assert "not depth" in hdr["omnisim.note"] and "m" in hdr["omnisim.units"]


def test_v1_dataset_reads_as_before(tmp_path):
    """A version 1 dataset: no masks, .flo unknown where gt.flow.valid is 0, V1 channels."""
    w = DatasetWriter(tmp_path / "d", make_meta(frames=1, version=1))
    fr = make_frame(0, version=1)
    w.write_frame(0, fr)
    d = open_dataset(tmp_path / "d")
    assert d.version == 1 and d.channels == ds.CHANNELS_V1 and d.complete
    assert d.read_flow_masks(0, "cam1") == {}
    _, known = d.read_flo(0, "cam1")
    assert (known == (fr["cam1"]["gt.flow.valid"] == 1)).all()
    assert sorted(p.name for p in d.frame_dir(0).iterdir()) == [
        "cam1.exr",
        "cam1.flo",
        "cam2.exr",
        "cam2.flo",
    ]


def test_version_mismatch_and_unknown_versions_are_refused(tmp_path):
    w = DatasetWriter(tmp_path / "d", make_meta(frames=1, version=1))
    with pytest.raises(DatasetError, match=r"format version 2.*format_version 1"):
        w.write_frame(0, make_frame(0))  # version 2 channels into a version 1 dataset
    with pytest.raises(DatasetError, match="format_version"):
        DatasetWriter(tmp_path / "e", make_meta(frames=1, version=3))
    meta_path = tmp_path / "d" / "dataset.json"
    for bad in (3, 0, True, "2"):
        meta = json.loads(meta_path.read_text())
        meta["format_version"] = bad
        meta_path.write_text(json.dumps(meta))
        with pytest.raises(DatasetError, match="format_version"):
            open_dataset(tmp_path / "d")
