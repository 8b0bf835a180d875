"""Regions from the ``omniflow`` command: boxes, masks, objects and automatic groups.

The pure pieces (:mod:`omniflow.applications.regions`) are checked against hand-made
points; the command against a closed-form scene with one mover: a textured
pillar (radius 0.4 m, its centre 1.6 m ahead on +X) driving straight at the
static robot at 2 cm per frame inside a textured round room, written as an
omnisim dataset (frame interval 0.1 s) so that object regions and seconds are
available. The truth of a region is :func:`omniflow.applications.regions.summarise` applied
to the exact per-point values at the same points (the scene's truth channels,
and the pillar's closed-form dr/dt and dtheta/dt).
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from omniflow.applications.regions import (
    RegionError,
    auto_groups,
    in_box,
    parse_landmark,
    parse_region,
    points_in_mask,
    summarise,
)
from omniflow.io.imageio import write_png
from omnisim.synthetic import Cylinder, Motion, SyntheticScene
from tests.helpers.scenes import paper_rig, striped_wall
from tests.omniflow.test_bad_input import base, check_clean_failure, run_omniflow, snapshot
from tests.omniflow.test_cli import read_csv

__all__ = ["base"]  # the shared bad-input fixture, used below

SIZE = 256
SPEED = 0.02  # m/frame, the pillar's speed towards the axis (along -X)


# -- the pure pieces -------------------------------------------------------------------------


def test_parse_region_forms():
    box = parse_region("door:box:350,10,20.5,80", r_m=100)
    assert (box.name, box.kind, box.box) == ("door", "box", (350.0, 10.0, 20.5, 80.0))
    mask = parse_region("m:mask:C:/masks/a.png")  # the file name keeps its colons
    assert (mask.kind, mask.path) == ("mask", "C:/masks/a.png")
    assert parse_region("o:object:7").object == 7
    assert parse_region("o:object:crosser").object == "crosser"
    assert parse_landmark("door:1.5,-2") == ("door", 1.5, -2.0)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("door", "expected NAME:box:"),
        ("door:circle:1,2", "kind 'circle'"),
        ("a b:box:0,10,0,5", "the name 'a b'"),
        ("auto1:box:0,10,0,5", "automatic groups"),
        ("d:box:0,10,0", "THETA0,THETA1,H0,H1"),
        ("d:box:0,10,0,nan", "4 finite numbers"),
        ("d:box:0,400,0,5", "theta 400"),
        ("d:box:30,30,0,5", "empty box"),
        ("d:box:0,10,5,5", "0 <= H0 < H1"),
        ("d:box:0,10,0,101", "H1 <= 100"),
        ("d:box:0,10,-1,5", "-1..5 px"),
    ],
)
def test_parse_region_rejects(text, fragment):
    with pytest.raises(RegionError, match="--region") as info:
        parse_region(text, r_m=100)
    assert fragment in str(info.value)


def test_in_box_wraps_through_360():
    theta = np.radians([-175, -10, -5, 0, 5, 10, 15, 90, 179])
    h = np.full(theta.shape, 50.0)
    # 350..10 degrees: 20 degrees across 0, both ends included
    np.testing.assert_array_equal(in_box(theta, h, (350, 10, 0, 100)), [0, 1, 1, 1, 1, 1, 0, 0, 0])
    # the same azimuths the long way round: everything but (10, 350)
    np.testing.assert_array_equal(in_box(theta, h, (10, 350, 0, 100)), [1, 1, 0, 0, 0, 1, 1, 1, 1])
    # negative degrees mean the same, and -180..180 is the full circle
    np.testing.assert_array_equal(
        in_box(theta, h, (-10, 10, 0, 100)), in_box(theta, h, (350, 10, 0, 100))
    )
    assert in_box(theta, h, (-180, 180, 0, 100)).all()
    assert not in_box(theta, h, (-180, 180, 60, 100)).any()  # the h1 range binds


def test_points_in_mask_uses_the_pixel_a_point_lies_in():
    mask = np.zeros((4, 5), bool)
    mask[1, 2] = True
    x = np.array([2.0, 2.999, 3.0, 2.5, 2.5, -0.1, np.nan])
    y = np.array([1.0, 1.999, 1.5, 0.999, 9.0, 1.5, 1.5])
    np.testing.assert_array_equal(points_in_mask(mask, x, y), [1, 1, 0, 0, 0, 0, 0])


def test_auto_groups_link_coherent_neighbours_only():
    rng = np.random.default_rng(0)
    # two blobs of 30 points 100 px apart, a scattered 20, and a blob whose halves move apart
    a = rng.normal((50, 50), 3, (30, 2))
    b = rng.normal((150, 50), 3, (30, 2))
    scattered = rng.uniform(0, 400, (20, 2)) + np.array([0.0, 200.0])
    c = rng.normal((50, 150), 3, (40, 2))
    xy = np.concatenate([a, b, scattered, c])
    vel = np.concatenate([np.tile((1.0, 0), (30, 1)), np.tile((0, 1.0), (30, 1)),
                          rng.normal(0, 1, (20, 2)),
                          np.tile((1.0, 0), (20, 1)), np.tile((-1.0, 0), (20, 1))])  # fmt: skip
    cand = np.ones(len(xy), bool)
    cand[:5] = False  # not candidates: never grouped
    labels = auto_groups(xy[:, 0], xy[:, 1], cand, link=10, min_points=15)
    # by position alone: c (40), a (25 candidates), b (30); the scattered points are alone
    assert set(labels[:5]) == {0}
    assert set(labels[5:30]) == {3} and set(labels[30:60]) == {2} and set(labels[80:]) == {1}
    assert set(labels[60:80]) == {0}
    labels = auto_groups(xy[:, 0], xy[:, 1], cand, link=10, min_points=15,
                         velocity=vel, coherence=0.5)  # fmt: skip
    # by position and velocity: c splits into its two halves (20 each)
    assert set(labels[30:60]) == {1} and set(labels[5:30]) == {2}
    assert len(set(labels[80:100])) == 1 and len(set(labels[100:])) == 1
    assert labels[80] != labels[100] and labels[80] > 0 and labels[100] > 0
    labels = auto_groups(xy[:, 0], xy[:, 1], cand, link=10, min_points=41)
    assert not labels.any()


def test_summarise_a_face_closing_head_on():
    # Points on a plane x = 2 m closing at 1 cm/frame. The centroid (bearing 0) reaches
    # the axis in 200 frames; a point at bearing b has -r / (dr/dt) = 200 / cos(b)^2, so
    # the median over bearings -20..20 deg is that of |b| = 10 deg. The home-in heading
    # turns with no bearing rate: 0.
    theta = np.radians(np.linspace(-20, 20, 41))
    r = 2.0 / np.cos(theta)
    cols = {"theta": theta, "r": r, "dr_dt": -0.01 * np.cos(theta),
            "dtheta_dt": 0.01 * np.sin(theta) / r, "dh1_dt": np.full(41, 0.5),
            "dx": np.full(41, 0.5), "dy": np.zeros(41)}  # fmt: skip
    row = summarise("face", "box", "face:box:...", cols, np.ones(41, bool), frame_interval=0.05)
    assert row["points"] == 41
    assert row["time_to_contact_frames"] == pytest.approx(200.0, rel=1e-12)
    assert row["time_to_contact_s"] == pytest.approx(10.0, rel=1e-12)
    median = 200.0 / math.cos(math.radians(10.0)) ** 2
    assert row["time_to_contact_median_frames"] == pytest.approx(median, rel=1e-12)
    assert row["bearing_deg"] == pytest.approx(0.0, abs=1e-12)
    assert row["steer_home_in_deg"] == pytest.approx(0.0, abs=1e-12)
    assert row["steer_avoid_deg"] == pytest.approx(-180.0, abs=1e-12)
    empty = summarise("none", "box", "", cols, np.zeros(41, bool), frame_interval=None)
    assert empty["points"] == 0 and math.isnan(empty["time_to_contact_frames"])


# -- the command on a closed-form scene with a mover ----------------------------------------


def mover_scene() -> SyntheticScene:
    rig = paper_rig(SIZE)
    pillar = Cylinder(
        centre=(1.6, 0.0),
        radius=0.4,
        id=3,
        name="pillar",
        texture=striped_wall(0.4, 7),
        motion=Motion(velocity=(-SPEED, 0.0)),
    )
    return SyntheticScene.room(
        rig, wall_radius=3.0, ceiling=None, wavelengths=(0.2, 1.0), bodies=[pillar]
    )


@pytest.fixture(scope="module")
def mover(tmp_path_factory):
    from validation.synthdata import write_synthetic_dataset

    d = tmp_path_factory.mktemp("mover")
    scene = mover_scene()
    write_synthetic_dataset(d / "dataset", scene, frames=2, frame_interval=0.1)
    out = d / "out"
    proc = run_omniflow(["--dataset", d / "dataset", "--out", out, "--auto-regions",
                         "--auto-min-points", "10",
                         "--region", "ahead:box:-12,12,0,126",
                         "--region", "pillar:object:pillar",
                         "--region", "behind:box:170,190,0,126"])  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    with open(out / "regions.csv") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    return {"scene": scene, "out": out, "proc": proc, "cols": read_csv(out / "flow.csv"),
            "rows": {row["name"]: row for row in rows},
            "meta": json.loads((out / "flow.json").read_text())}  # fmt: skip


def _truth_at(truth, key, x, y):
    return map_coordinates(truth[key], [y - 0.5, x - 0.5], order=1, mode="nearest")


def _true_row(scene, cols, member):
    """summarise() of the exact values at the estimate's points (the pillar's own motion)."""
    truth = scene.truth("cam1", 0)
    x, y = cols["x"][member], cols["y"][member]
    theta, r = cols["theta"][member], _truth_at(truth, "gt.r", x, y)
    exact = {"theta": theta, "r": r,
             "dr_dt": -SPEED * np.cos(theta), "dtheta_dt": SPEED * np.sin(theta) / r,
             "dh1_dt": _truth_at(truth, "gt.flow.dh", x, y),
             "dx": _truth_at(truth, "gt.flow.dx", x, y),
             "dy": _truth_at(truth, "gt.flow.dy", x, y)}  # fmt: skip
    return summarise("truth", "box", "", exact, np.ones(x.size, bool), frame_interval=0.1)


def test_regions_csv_and_json_agree(mover):
    rows, meta = mover["rows"], mover["meta"]
    assert list(rows) == ["ahead", "pillar", "behind", "auto1"]
    assert meta["outputs"] == ["flow.csv", "regions.csv", "flow_arrows.png", "flow_color.png",
                               "unwarp_cam1.png", "flow.json"]  # fmt: skip
    for row in meta["regions"]["rows"]:
        csv_row = rows[row["name"]]
        assert int(csv_row["points"]) == row["points"]
        for key in ("dx", "r", "time_to_contact_frames", "steer_home_in_deg"):
            if row[key] is None:  # JSON null: no value (not closing); an empty CSV field
                assert csv_row[key] == ""
            else:
                assert float(csv_row[key]) == pytest.approx(row[key], rel=1e-8)
    assert meta["regions"]["frame_interval_s"] == 0.1  # from the dataset
    assert float(rows["ahead"]["time_to_contact_s"]) == pytest.approx(
        0.1 * float(rows["ahead"]["time_to_contact_frames"]), rel=1e-8
    )
    # The mover is closing; what lies behind the robot is static: no contact.
    assert rows["behind"]["time_to_contact_frames"] == ""


def test_odometry_inlier_column(mover):
    # The column is the fit's inlier mask: the static room is used, the mover is not.
    cols, scene = mover["cols"], mover["scene"]
    truth = scene.truth("cam1", 0)
    obj = truth["gt.object"][np.floor(cols["y"]).astype(int), np.floor(cols["x"]).astype(int)]
    inlier = cols["odometry_inlier"]
    assert set(np.unique(inlier)) <= {0.0, 1.0}
    assert not inlier[obj == 3].any()
    # Measured: 77 % of the room's points are inliers (the rest mismatched or biased;
    # noise-free frames make the fit's robust scale small: 7e-5 m/frame).
    assert inlier[obj == 1].mean() > 0.7
    assert mover["meta"]["odometry"]["inliers"].startswith("flow.csv column odometry_inlier")


def test_auto_group_finds_the_mover(mover):
    # Measured: auto1 holds 23 points, all on the pillar (24 pillar points matched);
    # no other group of 10 or more.
    cols, scene = mover["cols"], mover["scene"]
    truth = scene.truth("cam1", 0)
    obj = truth["gt.object"][np.floor(cols["y"]).astype(int), np.floor(cols["x"]).astype(int)]
    group = cols["auto_region"]
    assert group.max() == 1
    on_pillar = obj[group == 1] == 3
    assert on_pillar.mean() >= 0.95
    assert on_pillar.sum() >= 0.8 * np.sum(obj == 3)
    assert int(mover["rows"]["auto1"]["points"]) == np.sum(group == 1)


def test_object_region_is_the_truth_object(mover):
    cols, scene = mover["cols"], mover["scene"]
    truth = scene.truth("cam1", 0)
    obj = truth["gt.object"][np.floor(cols["y"]).astype(int), np.floor(cols["x"]).astype(int)]
    assert int(mover["rows"]["pillar"]["points"]) == np.sum(obj == 3) > 0


def test_box_region_flow_and_time_to_contact_against_truth(mover):
    cols, row = mover["cols"], mover["rows"]["ahead"]
    member = in_box(cols["theta"], cols["h1"], (-12, 12, 0, 126))
    assert int(row["points"]) == member.sum() >= 15
    # The row is the region's points of flow.csv, averaged (exactly).
    for key in ("dx", "dy", "dh1_dt", "dtheta_dt"):
        assert float(row[key]) == pytest.approx(np.mean(cols[key][member]), rel=1e-6), key
    assert float(row["dr_dt_mean"]) == pytest.approx(np.mean(cols["dr_dt"][member]), rel=1e-6)
    # Against the truth at the same points. Measured on this scene (default
    # OmniFlowConfig; this test's row and truth printed): 23 points; dx 0.351 against
    # 0.328 px, dy -0.033 against -0.028, dh1_dt 0.354 against 0.332 (the radial flow
    # 7 % high); time to contact 56.3 against 60.8 frames (-7.5 %), median of the points
    # 56.5 against 61.0; home-in heading -2.15 against -2.13 deg; centroid range 1.2165
    # against 1.2156 m. Bounds: about 2x the flow errors, 10 % on the time to contact.
    truth = _true_row(mover["scene"], cols, member)
    for key in ("dx", "dy", "dh1_dt"):
        assert float(row[key]) == pytest.approx(truth[key], abs=0.05), key
    assert float(row["r"]) == pytest.approx(truth["r"], rel=0.01)
    for key in ("time_to_contact_frames", "time_to_contact_median_frames"):
        assert float(row[key]) == pytest.approx(truth[key], rel=0.10), key
    assert float(row["steer_home_in_deg"]) == pytest.approx(truth["steer_home_in_deg"], abs=0.5)


def test_monocular_columns_of_a_region(mover, tmp_path):
    """With ``--monocular-gap``, a region's row also summarises the cam1-only points in it
    (omniflow.solve.monocular): their count, mean bearing and bearing rate; without it those
    columns are empty. The pillar moves towards the axis along -X, so its true bearing rate
    is SPEED sin(theta) / r, small; its radial flow is large. Measured (this test's print):
    203 points;
    bearing rate 0.00080 against 0.00022 rad/frame, radial flow 1.225 against 1.269 px/frame
    (3.5 % short). Bounds: the row is exactly the mean of monocular.csv's points in the
    object; within 0.002 rad/frame and 10 % of the truth at them (about 3x)."""
    assert all(row["monocular_points"] == "" for row in mover["rows"].values())
    out = tmp_path / "out"
    dataset = mover["out"].parent / "dataset"
    proc = run_omniflow(["--dataset", dataset, "--out", out, "--monocular-gap", "8",
                         "--region", "pillar:object:pillar", "--no-pictures"])  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    with open(out / "regions.csv") as fh:
        row = next(csv.DictReader(line for line in fh if not line.startswith("#")))
    mono = read_csv(out / "monocular.csv")
    truth = mover["scene"].truth("cam1", 0)
    obj = truth["gt.object"][np.floor(mono["y"]).astype(int), np.floor(mono["x"]).astype(int)]
    inside = obj == 3
    assert int(row["monocular_points"]) == inside.sum() >= 20
    for key in ("dtheta_dt", "dh1_dt"):
        assert float(row[f"monocular_{key}"]) == pytest.approx(mono[key][inside].mean(), rel=1e-6)
    bearing = math.degrees(np.angle(np.mean(np.exp(1j * mono["theta"][inside]))))
    assert float(row["monocular_bearing_deg"]) == pytest.approx(bearing, abs=1e-6)
    x, y, h1 = mono["x"][inside], mono["y"][inside], mono["h1"][inside]
    true_rate = float(np.mean(_truth_at(truth, "gt.flow.hdtheta", x, y) / h1))
    true_dh = float(np.mean(_truth_at(truth, "gt.flow.dh", x, y)))
    assert float(row["monocular_dtheta_dt"]) == pytest.approx(true_rate, abs=0.002)
    assert float(row["monocular_dh1_dt"]) == pytest.approx(true_dh, rel=0.10)


def test_position_fix_from_landmark_regions(mover, tmp_path):
    # Three patches of the static wall, each given the true world centroid (gt.X, gt.Y)
    # of the points the region holds; the rig sits at world (0, 0) with yaw 0. Measured:
    # pose (0.0168, -0.0016) m, yaw -0.014 deg, rms 0.025 m: the estimated centroid
    # ranges (3.000, 3.043, 2.988 m against about 2.99 true) are the error. Bounds ~2x.
    cols, truth = mover["cols"], mover["scene"].truth("cam1", 0)
    boxes = {"w1": (80, 100, 10, 120), "w2": (170, 190, 10, 120), "w3": (260, 280, 10, 120)}
    args = ["--dataset", mover["out"].parent / "dataset", "--out", tmp_path / "out"]
    for name, box in boxes.items():
        member = in_box(cols["theta"], cols["h1"], box)
        x, y = cols["x"][member], cols["y"][member]
        world = [np.mean(_truth_at(truth, key, x, y)) for key in ("gt.X", "gt.Y")]
        args += ["--region", f"{name}:box:{','.join(map(str, box))}"]
        args += ["--landmark", f"{name}:{world[0]:.6f},{world[1]:.6f}"]
    proc = run_omniflow([*args, "--no-pictures"])
    assert proc.returncode == 0, proc.stderr
    fix = json.loads((tmp_path / "out" / "flow.json").read_text())["position_fix"]
    assert set(fix["landmarks"]) == set(boxes)
    assert math.hypot(fix["x_m"], fix["y_m"]) < 0.04
    assert abs(fix["yaw_deg"]) < 0.1
    assert fix["rms_position_m"] < 0.05


def test_regions_are_drawn(mover):
    from omniflow.io.imageio import read_image

    picture = read_image(mover["out"] / "flow_arrows.png")
    # the first region's outline colour (magenta) is on the picture
    magenta = (picture[..., 0] > 0.95) & (picture[..., 1] < 0.4) & (picture[..., 2] > 0.95)
    assert magenta.sum() > 50


# -- bad input -------------------------------------------------------------------------------


def _rig_args(base):
    files = [base["dir"] / f"{cam}_{k}.png" for k in range(2) for cam in ("cam1", "cam2")]
    return [*files, "--rig", base["dir"] / "rig.toml"]


def _wrong_size_mask(base, work):
    return write_png(work / "small.png", np.ones((40, 40), np.float32))


BAD = {
    "box beyond the rim": (lambda b, w: ["--region", "d:box:0,10,0,500"], "H1 <= "),
    "box theta out of range": (lambda b, w: ["--region", "d:box:-400,10,0,20"], "theta -400"),
    "box malformed": (lambda b, w: ["--region", "d:box:0,10"], "--region d:box:0,10: expected"),
    "unknown kind": (lambda b, w: ["--region", "d:ring:0,10"], "kind 'ring'"),
    "name twice": (
        lambda b, w: ["--region", "d:box:0,10,0,20", "--region", "d:box:20,30,0,20"],
        "the name 'd' is given twice",
    ),
    "mask missing": (lambda b, w: ["--region", f"m:mask:{w / 'none.png'}"], "none.png: image"),
    "mask wrong size": (
        lambda b, w: ["--region", f"m:mask:{_wrong_size_mask(b, w)}"],
        "the mask is 40x40; expected cam1's size 96x96",
    ),
    "object without dataset": (lambda b, w: ["--region", "o:object:wall"], "need --dataset"),
    "landmark of no region": (
        lambda b, w: ["--region", "d:box:0,10,0,20", "--landmark", "x:1,2", "--landmark", "d:1,2"],
        "no --region named 'x'",
    ),
    "one landmark": (
        lambda b, w: ["--region", "d:box:0,10,0,20", "--landmark", "d:1,2"],
        "at least 2 landmarks",
    ),
    "landmark malformed": (lambda b, w: ["--landmark", "d:1"], "--landmark d:1: expected"),
    "auto-min-points 0": (lambda b, w: ["--auto-regions", "--auto-min-points", "0"], ">= 1"),
    "auto-link nan": (lambda b, w: ["--auto-link", "nan"], "--auto-link nan"),
    "auto-residual 0.5": (lambda b, w: ["--auto-residual", "0.5"], "--auto-residual 0.5"),
    "auto-coherence 0": (lambda b, w: ["--auto-coherence", "0"], "--auto-coherence 0.0"),
    "steer-lead negative": (lambda b, w: ["--steer-lead", "-1"], "--steer-lead -1.0"),
    "frame-interval 0": (lambda b, w: ["--frame-interval", "0"], "--frame-interval 0.0"),
    "odometry weight inf": (
        lambda b, w: ["--odometry-radial-weight", "inf"],
        "--odometry-radial-weight inf",
    ),
}


@pytest.mark.parametrize("name", list(BAD))
def test_bad_region_input_is_one_line_and_changes_nothing(base, tmp_path, name):
    setup, fragment = BAD[name]
    out = tmp_path / "out"
    out.mkdir()
    (out / "regions.csv").write_text("old regions\n")
    extra = [str(a) for a in setup(base, tmp_path)]
    before = snapshot(tmp_path, base["dir"])
    proc = run_omniflow([*_rig_args(base), "--out", out, *extra])
    check_clean_failure(proc, 2, fragment)
    assert snapshot(tmp_path, base["dir"]) == before


def test_unknown_object_names_the_dataset_objects(base, tmp_path):
    out = tmp_path / "out"
    before = snapshot(tmp_path, base["dir"])
    proc = run_omniflow(["--dataset", base["dir"] / "dataset", "--out", out,
                         "--region", "o:object:crosser"])  # fmt: skip
    line = check_clean_failure(proc, 2, "--region o:object:crosser: no object 'crosser'")
    assert "1 wall" in line  # the objects the dataset has
    assert snapshot(tmp_path, base["dir"]) == before


def test_zero_matches_with_regions_is_an_empty_answer(base, tmp_path):
    # Black frames: no point, so every region row is empty (one warning line each), no
    # automatic group, no odometry fit, and the outputs are written as a set (exit 0).
    from tests.omniflow.test_bad_input import _blank_frames

    out = tmp_path / "out"
    proc = run_omniflow([*_blank_frames(base, tmp_path, "black"), "--rig",
                         base["dir"] / "rig.toml", "--out", out, "--auto-regions",
                         "--region", "d:box:0,10,0,20", "--region", "e:box:20,30,0,20",
                         "--landmark", "d:1,0", "--landmark", "e:0,1"])  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    assert lines[0].startswith("omniflow: warning: no stereo matches"), lines
    assert sorted(line.split(" (")[0] for line in lines[1:]) == [
        "omniflow: warning: region d",
        "omniflow: warning: region e",
    ]
    with open(out / "regions.csv") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    assert [(row["name"], row["points"], row["dx"]) for row in rows] == [
        ("d", "0", ""),
        ("e", "0", ""),
    ]
    meta = json.loads((out / "flow.json").read_text())
    assert "error" in meta["odometry"] and "error" in meta["regions"]["auto"]
    assert "hold no matched point" in meta["position_fix"]["error"]
    units, header = (out / "flow.csv").read_text().splitlines()[:2]
    assert "odometry_inlier" in header.split(",") and "auto_region" in header.split(",")
    # the '#' line gives every column a unit, the CLI's own columns included
    for name in header.split(","):
        assert f"; {name}: " in units or f"results; {name}: " in units, name
        unit = units.split(f"{name}: ", 1)[1].split(";")[0]
        assert unit.strip(), f"no unit for {name}"


def test_auto_min_speed_keeps_static_points_out(mover, tmp_path):
    """Mutation of --auto-min-speed (0: the relative threshold alone): on these noise-free
    frames the odometry fits the static wall to ~1e-6 m/frame, so its inlier threshold
    (2.5 robust sigma) is tiny and a second, static group appears (measured: auto2, 18
    points, own velocity 6e-6 m/frame, before the matcher's sharp-peak and alias tests;
    with them the static group has fewer than 10 points, hence --auto-min-points 5 here);
    the default floor of 1e-4 m/frame keeps it out."""
    out = tmp_path / "out"
    args = ["--auto-regions", "--auto-min-points", "5", "--auto-min-speed", "0"]
    proc = run_omniflow(["--dataset", mover["out"].parent / "dataset", "--out", out, *args])
    assert proc.returncode == 0, proc.stderr
    with open(out / "regions.csv") as fh:
        names = [r["name"] for r in csv.DictReader(ln for ln in fh if not ln.startswith("#"))]
    assert "auto2" in names and "auto2" not in mover["rows"]
