"""omnisim export: Sintel, KITTI and PNG layouts, each read back with the readers their
users use (OpenCV, Pillow, flow_vis, the Sintel SDK's .dpt reader, KITTI's flow PNG
decoding as the training codes write it)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnisim.camera import dataset_camera, read_camera_dn
from omnisim.cli import main
from omnisim.dataset import open_dataset
from omnisim.export import export_dataset

SCENES = Path(__file__).resolve().parents[2] / "scenes"


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """A format version 2 render: scenes/default.toml, 3 frames, 64 px, 2 spp."""
    pytest.importorskip("mitsuba")
    from omnisim.job import render_dataset

    out = tmp_path_factory.mktemp("real") / "ds"
    ov = {"frames": 3, "render.width": 64, "render.height": 64, "render.spp": 2}
    render_dataset(SCENES / "default.toml", out, ov, progress=False)
    return out


@pytest.fixture(scope="module")
def exports(real, tmp_path_factory):
    root = tmp_path_factory.mktemp("exports")
    return {fmt: export_dataset(real, root / fmt, fmt) for fmt in ("sintel", "kitti", "png")}


def _files(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file())


def _saturation(img: np.ndarray, mask: np.ndarray) -> float:
    """Median HSV-style saturation (max - min) / max of the 8-bit colour pixels in mask."""
    img = img.astype(np.float64)
    mx, mn = img.max(-1), img.min(-1)
    return float(np.median(((mx - mn) / np.maximum(mx, 1.0))[mask]))


def sintel_depth_read(filename):
    """``depth_read`` of the MPI-Sintel SDK (sintel_io.py), as distributed."""
    f = open(filename, "rb")  # the SDK's code, verbatim in substance
    check = np.fromfile(f, dtype=np.float32, count=1)[0]
    assert check == 202021.25, "depth_read:: Wrong tag in depth file (should be: 202021.25)"
    width = np.fromfile(f, dtype=np.int32, count=1)[0]
    height = np.fromfile(f, dtype=np.int32, count=1)[0]
    size = width * height
    assert width > 0 and height > 0 and size > 1 and size < 100000000
    depth = np.fromfile(f, dtype=np.float32, count=-1).reshape((height, width))
    f.close()
    return depth


def read_kitti_flow(filename):
    """KITTI flow PNG as the flow training codes read it (e.g. RAFT's readFlowKITTI)."""
    flow = cv2.imread(str(filename), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    flow = flow[:, :, ::-1].astype(np.float32)
    flow, valid = flow[:, :, :2], flow[:, :, 2]
    flow = (flow - 2**15) / 64.0
    return flow, valid


@pytest.mark.render
def test_sintel_layout_reads_back(real, exports):
    out = exports["sintel"]
    d = open_dataset(real)
    name = d.meta["scene"]["name"]
    want = ["README.txt"]
    assert dataset_camera(d) is not None  # scenes/default.toml has a [camera]: Sintel's final pass
    for cam in ("cam1", "cam2"):
        for k in range(1, 4):
            kinds = (("clean", "png"), ("final", "png"), ("depth", "dpt"), ("segmentation", "png"))
            for kind, ext in kinds:
                want.append(f"training/{kind}/{name}_{cam}/frame_{k:04d}.{ext}")
        for k in range(1, 3):  # N - 1 flows, as in Sintel
            for kind in ("flow", "occlusions", "outside", "invalid"):
                ext = "flo" if kind == "flow" else "png"
                want.append(f"training/{kind}/{name}_{cam}/frame_{k:04d}.{ext}")
    assert _files(out) == sorted(want)
    for k in range(2):
        for cam in ("cam1", "cam2"):
            ch = d.read_frame(k, cam)
            known = d.flo_known(ch)
            folder = f"{name}_{cam}"
            base = f"frame_{k + 1:04d}"
            flow = cv2.readOpticalFlow(str(out / "training/flow" / folder / f"{base}.flo"))
            assert flow.shape == (64, 64, 2) and np.isfinite(flow).all()
            np.testing.assert_array_equal(flow[..., 0], np.where(known, ch["gt.flow.dx"], 0))
            np.testing.assert_array_equal(flow[..., 1], np.where(known, ch["gt.flow.dy"], 0))
            for kind, want_mask in (
                ("occlusions", ch["gt.flow.occluded"] > 0.5),
                ("outside", ch["gt.flow.outside"] > 0.5),
                ("invalid", ~known),
            ):
                m = cv2.imread(str(out / "training" / kind / folder / f"{base}.png"), -1)
                assert m.dtype == np.uint8 and m.ndim == 2
                assert ((m == 255) == want_mask).all() and ((m == 0) | (m == 255)).all()
            depth = sintel_depth_read(out / "training/depth" / folder / f"{base}.dpt")
            np.testing.assert_array_equal(depth, np.where(ch["gt.valid"] > 0.5, ch["gt.r"], 0))
            final = out / "training/final" / folder / f"{base}.png"
            assert final.read_bytes() == d.path(k, cam, "png").read_bytes()
            np.testing.assert_array_equal(
                cv2.imread(str(final), cv2.IMREAD_UNCHANGED)[..., ::-1], read_camera_dn(d, k, cam)
            )
            img = cv2.imread(str(out / "training/clean" / folder / f"{base}.png"), -1)
            assert img.dtype == np.uint8 and img.shape == (64, 64, 3)
            on = ch["gt.valid"] > 0.5
            unit = d.unit(cam)
            h_i, _ = unit.polar_of_pixel(*unit.pixel_centres())
            assert img[on].std() > 10  # an image, not a flat field (measured std 43)
            assert (img[h_i > unit.r_m + 1] == 0).all()  # black beyond the rim


@pytest.mark.render
def test_flow_vis_draws_the_sintel_flo_in_colour(real, exports):
    """flow_vis on the exported .flo gives a saturated picture on the mirror; on a .flo
    holding Middlebury's 1e10 (the dataset's own, outside the rim) it is white: the
    spread test separates the two (measured median saturation 0.35-0.36 vs 0.004)."""
    flow_vis = pytest.importorskip("flow_vis")
    d = open_dataset(real)
    name = d.meta["scene"]["name"]
    for cam in ("cam1", "cam2"):
        on = d.read_frame(0, cam)["gt.valid"] > 0.5
        flo = exports["sintel"] / "training/flow" / f"{name}_{cam}" / "frame_0001.flo"
        colour = flow_vis.flow_to_color(cv2.readOpticalFlow(str(flo)))
        assert _saturation(colour, on) > 0.15
        raw = flow_vis.flow_to_color(cv2.readOpticalFlow(str(d.path(0, cam, "flo"))))
        assert _saturation(raw, on) < 0.05  # what the test would catch
        # the dataset's .flo, its unknown values zeroed (as Middlebury's colour code does)
        f = cv2.readOpticalFlow(str(d.path(0, cam, "flo")))
        f[np.abs(f) >= 1e9] = 0
        assert _saturation(flow_vis.flow_to_color(f), on) > 0.15


@pytest.mark.render
def test_segmentation_is_an_indexed_png(real, exports):
    from PIL import Image

    d = open_dataset(real)
    name = d.meta["scene"]["name"]
    obj = d.read_frame(2, "cam2")["gt.object"]
    p = exports["sintel"] / "training/segmentation" / f"{name}_cam2" / "frame_0003.png"
    with Image.open(p) as im:
        assert im.mode == "P"
        np.testing.assert_array_equal(np.asarray(im), obj.astype(np.uint8))
    colour = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)  # OpenCV expands the palette
    assert colour.shape == (64, 64, 3)
    ids = np.unique(obj).astype(int)
    assert len(ids) >= 3
    colours = {tuple(colour[obj == i][0]) for i in ids}
    assert len(colours) == len(ids)  # one colour per object
    assert (colour[obj == 0] == 0).all()
    q = exports["png"] / "cam2" / "segmentation" / "000002.png"
    assert q.read_bytes() == p.read_bytes()


@pytest.mark.render
def test_kitti_flow_png_reads_back(real, exports):
    out = exports["kitti"]
    d = open_dataset(real)
    for cam in ("cam1", "cam2"):
        root = out / cam / "training"
        assert _files(root) == sorted(
            f"{kind}/{k:06d}_{s}.png"
            for k in range(2)
            for kind, suffixes in (
                ("image_2", ("10", "11")),
                ("flow_occ", ("10",)),
                ("flow_noc", ("10",)),
                ("obj_map", ("10",)),
            )
            for s in suffixes
        )
        for k in range(2):
            ch = d.read_frame(k, cam)
            raw = cv2.imread(str(root / f"flow_occ/{k:06d}_10.png"), cv2.IMREAD_UNCHANGED)
            assert raw.dtype == np.uint16 and raw.shape == (64, 64, 3)
            for kind, mask in (("flow_occ", d.flo_known(ch)), ("flow_noc", ch["gt.flow.valid"])):
                flow, valid = read_kitti_flow(root / f"{kind}/{k:06d}_{10}.png")
                assert ((valid == 1) == (mask > 0.5)).all()
                gt = np.stack([ch["gt.flow.dx"], ch["gt.flow.dy"]], -1)
                err = np.abs(flow - gt)[valid == 1]
                # 1/64 px steps: rounding error <= 1/128 px (+ float32 of the stored flow)
                assert err.max() <= 1 / 128 + 1e-4, err.max()
            png = exports["png"] / cam / "image"
            for s, j in (("10", k), ("11", k + 1)):
                assert (root / f"image_2/{k:06d}_{s}.png").read_bytes() == (
                    png / f"{j:06d}.png"
                ).read_bytes()


def test_kitti_encoding_drops_flow_that_does_not_fit(tmp_path):
    from omnisim.export import kitti_flow_png

    dx = np.array([[0.0, 511.9, 512.0, -3.25]])
    dy = np.array([[1.5, 0.0, 0.0, -600.0]])
    data, dropped = kitti_flow_png(dx, dy, np.ones_like(dx, bool))
    p = tmp_path / "f.png"
    p.write_bytes(data)
    flow, valid = read_kitti_flow(p)
    assert dropped == 2 and valid.tolist() == [[1, 1, 0, 0]]
    np.testing.assert_allclose(flow[0, :2], [[0.0, 1.5], [511.90625, 0.0]])


@pytest.mark.render
def test_png_export_8_and_16_bit(real, exports, tmp_path):
    out16 = export_dataset(real, tmp_path / "png16", "png", bits=16)
    for cam in ("cam1", "cam2"):
        a = cv2.imread(str(exports["png"] / cam / "image/000001.png"), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(out16 / cam / "image/000001.png"), cv2.IMREAD_UNCHANGED)
        assert a.dtype == np.uint8 and b.dtype == np.uint16 and a.shape == b.shape == (64, 64, 3)
        # the same tone map: the 16-bit value / 257 rounds to the 8-bit one (+- 1 code)
        assert np.abs(np.rint(b / 257.0) - a).max() <= 1
        assert b.max() > 60000  # the exposure maps the 99th percentile to white
    text = (exports["png"] / "README.txt").read_text()
    assert "format_version 2" in text and "tone map" in text


def _v1(tmp_path):
    from tests.helpers.fakes import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path / "v1", frames=2, size=32)


def test_version_1_exports_png_but_not_sintel(tmp_path, capsys):
    v1 = _v1(tmp_path)
    assert main(["export", str(v1), "--format", "png", "--out", str(tmp_path / "p")]) == 0
    assert len(_files(tmp_path / "p")) == 1 + 2 * 2 * 2
    capsys.readouterr()
    assert main(["export", str(v1), "--format", "sintel", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "format_version 1" in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


def test_bad_input_is_one_line_exit_2_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    v1 = _v1(tmp_path)
    cases = [
        (["export", str(tmp_path / "nope"), "--format", "png"], "no dataset.json"),
        (["export", str(v1), "--format", "png"], "exists and is not an empty directory"),
    ]
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "x").write_text("x")
    for argv, msg in cases:
        out = taken if "nope" not in argv[1] else tmp_path / "o"
        assert main([*argv, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and msg in err, err
    # an output below a file
    assert main(["export", str(v1), "--format", "png", "--out", str(taken / "x" / "o")]) == 2
    assert "cannot create the output directory" in capsys.readouterr().err
    # an incomplete dataset
    inc = tmp_path / "inc"
    shutil.copytree(v1, inc)
    shutil.rmtree(inc / "frames" / "000001")
    assert main(["export", str(inc), "--format", "png", "--out", str(tmp_path / "o")]) == 2
    assert "[1] of 2 are not rendered" in capsys.readouterr().err
    # a failure half-way leaves neither OUT nor a temporary directory
    import omnisim.export as ex

    def boom(obj):
        raise ex.ExportError("disk full (simulated)")

    monkeypatch.setattr(ex, "segmentation_png", boom)
    assert main(["export", str(v1), "--format", "png", "--out", str(tmp_path / "o")]) == 2
    assert "simulated" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inc", "taken", "v1"]


def test_camera_model_images_are_exported_when_present(tmp_path):
    """A dataset whose frames hold the camera model's camK.png (omnisim.camera): the png
    layout copies them byte for byte into <cam>/camera/ (simulated here with 16-bit PNGs)."""
    v1 = _v1(tmp_path)
    d = open_dataset(v1)
    written = {}
    for k in range(d.frame_count):
        for cam in d.cameras:
            img = np.full((32, 32, 3), 1000 * (k + 1), np.uint16)
            cv2.imwrite(str(d.path(k, cam, "png")), img)
            written[(k, cam)] = d.path(k, cam, "png").read_bytes()
    out = export_dataset(v1, tmp_path / "p", "png")
    for (k, cam), data in written.items():
        assert (out / cam / "camera" / f"{k:06d}.png").read_bytes() == data
