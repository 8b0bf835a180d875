"""omniflow.io.imageio (read/write, scaling, NaN checks, atomic writes) and omniflow.io.draw."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from omniflow.conventions import LUMA_WEIGHTS
from omniflow.io.draw import (
    color_wheel,
    draw_flow_arrows,
    draw_flow_points,
    flow_to_color,
    grey_background,
)
from omniflow.io.imageio import (
    ImageError,
    atomic_output,
    atomic_write_text,
    read_exr_channels,
    read_image,
    to_grey,
    write_exr,
    write_png,
)


@pytest.fixture
def ramp():
    y, x = np.mgrid[0:24, 0:32]
    return ((x + 32 * y) / (24 * 32 - 1)).astype(np.float32)  # distinct values in [0, 1]


# -- reading and writing ----------------------------------------------------------------


def test_png16_round_trip_within_half_a_step(tmp_path, ramp):
    path = write_png(tmp_path / "a.png", ramp, bits=16)
    back = read_image(path)
    assert back.dtype == np.float32 and back.shape == ramp.shape
    assert np.abs(back - ramp).max() <= 0.5 / 65535 + 1e-7
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16  # really a 16-bit file


def test_png8_and_jpeg_scaling(tmp_path):
    raw = np.array([[0, 128, 255]], np.uint8).repeat(8, 0).repeat(8, 1)
    cv2.imwrite(str(tmp_path / "a.png"), raw)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), raw / np.float32(255))
    cv2.imwrite(str(tmp_path / "a.jpg"), raw, [cv2.IMWRITE_JPEG_QUALITY, 100])
    jpg = read_image(tmp_path / "a.jpg")
    assert jpg.dtype == np.float32
    assert np.abs(jpg - raw / 255.0).max() < 0.03  # JPEG is lossy; measured 0.012


def test_colour_png_is_rgb_and_grey_uses_rec709(tmp_path):
    rgb = np.zeros((4, 5, 3), np.float32)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 1.0, 0.5, 0.25
    write_png(tmp_path / "c.png", rgb, bits=16)
    back = read_image(tmp_path / "c.png")
    assert back.shape == (4, 5, 3)
    np.testing.assert_allclose(back[0, 0], [1.0, 0.5, 0.25], atol=1e-4)  # RGB, not BGR
    grey = read_image(tmp_path / "c.png", grey=True)
    expected = np.dot([1.0, 0.5, 0.25], LUMA_WEIGHTS)
    np.testing.assert_allclose(grey, expected, atol=1e-4)


def test_exr_channels_round_trip(tmp_path, ramp):
    chans = {"R": ramp, "G": 2 * ramp, "B": 3 * ramp, "gt.r": ramp + 7.0}
    write_exr(tmp_path / "f.exr", chans)
    img = read_image(tmp_path / "f.exr")
    assert img.shape == (*ramp.shape, 3)
    np.testing.assert_array_equal(img[..., 1], 2 * ramp)  # float32 stored exactly
    np.testing.assert_array_equal(read_image(tmp_path / "f.exr", channel="gt.r"), ramp + 7.0)
    assert set(read_exr_channels(tmp_path / "f.exr")) == set(chans)
    write_exr(tmp_path / "y.exr", ramp)  # one array: written as Y
    np.testing.assert_array_equal(read_image(tmp_path / "y.exr"), ramp)


def test_to_grey_shapes():
    rgb = np.random.default_rng(0).random((3, 4, 3)).astype(np.float32)
    np.testing.assert_allclose(to_grey(rgb), rgb @ np.asarray(LUMA_WEIGHTS), rtol=1e-6)
    rgba = np.concatenate([rgb, np.ones((3, 4, 1), np.float32)], axis=2)
    np.testing.assert_array_equal(to_grey(rgba), to_grey(rgb))
    assert to_grey(rgb[..., 0]).shape == (3, 4)
    with pytest.raises(ValueError, match="shape"):
        to_grey(np.zeros((2, 2, 2)))


# -- errors name the file and the problem ------------------------------------------------


def test_missing_file(tmp_path):
    with pytest.raises(ImageError, match=r"nope\.png: image file not found"):
        read_image(tmp_path / "nope.png")


def test_unreadable_files(tmp_path):
    (tmp_path / "bad.png").write_text("not a png")
    with pytest.raises(ImageError, match=r"bad\.png: cannot be read as an image"):
        read_image(tmp_path / "bad.png")
    (tmp_path / "bad.exr").write_text("not an exr")
    with pytest.raises(ImageError, match=r"bad\.exr: cannot be read as OpenEXR"):
        read_image(tmp_path / "bad.exr")
    with pytest.raises(ImageError, match="not a file"):
        read_image(tmp_path)


def test_nan_and_inf_pixels_are_reported(tmp_path, ramp):
    bad = ramp.copy()
    bad[3, 4] = np.nan
    bad[5, 6] = np.inf
    write_exr(tmp_path / "n.exr", bad)
    msg = r"n\.exr: 2 pixel\(s\) are NaN or infinite \(first at row 3, col 4\)"
    with pytest.raises(ImageError, match=msg):
        read_image(tmp_path / "n.exr")


def test_missing_exr_channel_lists_the_channels(tmp_path, ramp):
    write_exr(tmp_path / "f.exr", {"gt.r": ramp, "gt.h": ramp})
    with pytest.raises(ImageError, match=r"no channel 'R'; the file has \['gt.h', 'gt.r'\]"):
        read_image(tmp_path / "f.exr", channel="R")
    with pytest.raises(ImageError, match="no R, G, B or Y channels"):
        read_image(tmp_path / "f.exr")


# -- atomic writes ------------------------------------------------------------------------


def test_atomic_output_leaves_no_partial_file(tmp_path):
    target = tmp_path / "out.txt"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("writer died")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    with atomic_output(tmp_path / "sub" / "new.png") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path / "sub"
        tmp.write_bytes(b"x")
    assert (tmp_path / "sub" / "new.png").read_bytes() == b"x"


def test_atomic_write_fsyncs_the_file_before_the_rename_and_the_folder_after(tmp_path, monkeypatch):
    """The one atomic writer is durable: data synced before it gets its final name, the
    rename synced after (a writer without either fails this)."""
    import os

    from omniflow.io import imageio

    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(imageio.os, "fsync", fsync)
    monkeypatch.setattr(imageio.os, "replace", replace)
    target = tmp_path / "dataset.json"
    imageio.atomic_write_bytes(target, b"{}")
    assert target.read_bytes() == b"{}"
    (kind0, tmp_name), (kind1, dst), (kind2, folder) = events
    assert kind0 == "fsync" and tmp_name.startswith(str(tmp_path / ".dataset.json.tmp."))
    assert (kind1, dst) == ("replace", str(target))
    assert (kind2, folder) == ("fsync", str(tmp_path))


# -- drawing ----------------------------------------------------------------------------------


def test_flow_to_color_matches_middlebury_conventions():
    col = flow_to_color([1.0, 0.0, 0.0, np.nan], [0.0, 0.0, 1.0, 0.0], max_flow=1.0)
    assert col.dtype == np.uint8 and col.shape == (4, 3)
    np.testing.assert_array_equal(col[0], [255, 0, 0])  # +x: red
    np.testing.assert_array_equal(col[1], [255, 255, 255])  # no motion: white
    assert col[2, 0] == 255 and col[2, 1] > 200 and col[2, 2] == 0  # +y (down): yellow
    np.testing.assert_array_equal(col[3], [0, 0, 0])  # unknown: black
    dense = flow_to_color(np.ones((5, 6)), np.zeros((5, 6)), mask=np.eye(5, 6, dtype=bool))
    assert dense.shape == (5, 6, 3)
    assert (dense[~np.eye(5, 6, dtype=bool)] == 0).all()
    # Beyond max_flow: darkened, not wrapped.
    far = flow_to_color([3.0], [0.0], max_flow=1.0)
    np.testing.assert_array_equal(far[0], [191, 0, 0])
    wheel = color_wheel(32)
    assert wheel.shape == (32, 32, 3) and (wheel[0, 0] == 0).all() and wheel[16, 16].min() > 200


def test_draw_flow_pictures(ramp):
    img = np.tile(ramp, (4, 4))  # 96 x 128
    yy, xx = np.mgrid[8:96:16, 8:128:16] + 0.5
    dx, dy = np.full(xx.shape, 1.0), np.full(xx.shape, 0.5)
    arrows = draw_flow_arrows(img, xx, yy, dx, dy, scale=10.0, legend=False)
    assert arrows.shape == (96, 128, 3) and arrows.dtype == np.uint8
    base = grey_background(img, dim=0.8)
    changed = np.any(arrows != base, axis=2)
    # Each arrow runs from (x, y) to (x + 10, y + 5): its middle pixel is drawn.
    assert changed[int(yy[2, 3] - 0.5 + 2.5), int(xx[2, 3] - 0.5 + 5)]
    assert changed.mean() < 0.5
    points = draw_flow_points(img, xx, yy, dx, dy, radius=0, key=False)
    np.testing.assert_array_equal(
        points[int(yy[0, 0]), int(xx[0, 0])], flow_to_color([1.0], [0.5])[0]
    )
    with pytest.raises(ValueError, match="equal sizes"):
        draw_flow_arrows(img, xx, yy, dx[:2], dy)


def test_the_legend_is_readable_over_a_bright_picture():
    """The legend sits on a black box: over bright texture an outline alone left the
    smallest font (a panorama 254 px high) unreadable. Mutation caught: no box."""
    white = np.ones((254, 1596))
    white[-10:] = 0.0  # a dark strip far from the legend: the 1st percentile, so the rest is bright
    pts = (np.array([800.5]), np.array([200.5]), np.array([1.0]), np.array([0.0]))
    for pic in (draw_flow_arrows(white, *pts), draw_flow_points(white, *pts)):
        label = pic[3:12, 4:60]  # behind the first characters of the text
        assert (label.max(axis=2) < 64).mean() > 0.6  # mostly the box, not the background
