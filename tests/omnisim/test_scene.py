"""Scene files: the library loads, overrides apply, and every error names file and key."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh

from omniflow.geometry.rig import Rig
from omnisim import geometry
from omnisim.scene import Scene, SceneError, apply_overrides, load_scene, parse_override

SCENES = sorted((Path(__file__).resolve().parents[2] / "scenes").glob("*.toml"))

# A small valid scene; tests append or replace parts of it.
BASE = """
name = "t"
frames = 3
frame_interval = 0.1

[render]
width = 64
height = 64
spp = 2

[rig]
d = 0.10
R = 0.05
s = 0.30

[robot]
position = [0.0, 0.0, 0.6]

[[objects]]
name = "room"
type = "room"
size = [6.0, 5.0, 3.0]
[objects.texture]
resolution = 64
tile = 2.0
wavelength = [0.1, 1.0]

[[lights]]
type = "point"
position = [0, 0, 2.5]
intensity = 5.0
"""


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def expect_error(path: Path, *fragments: str, overrides=None) -> str:
    with pytest.raises(SceneError) as info:
        load_scene(path, overrides)
    msg = str(info.value)
    assert str(path) in msg, msg
    for frag in fragments:
        assert frag in msg, (frag, msg)
    assert isinstance(info.value, ValueError)
    return msg


# -- the library --------------------------------------------------------------


def test_library_has_the_required_scenes():
    names = {p.stem for p in SCENES}
    assert "default" in names
    assert len(SCENES) >= 8
    readme = (SCENES[0].parent / "README.md").read_text()
    for p in SCENES:
        assert p.name in readme, f"{p.name} is not documented in scenes/README.md"


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_every_library_scene_loads_and_validates(path):
    scene = load_scene(path, {"render.width": 64, "render.height": 64, "render.spp": 1})
    assert isinstance(scene, Scene) and isinstance(scene.rig, Rig)
    assert scene.description, "each library scene describes itself"
    assert scene.frames >= 2 and scene.frame_interval > 0
    assert scene.render.width == scene.rig.cam1.width == 64
    ids = [o.id for o in scene.objects]
    assert len(set(ids)) == len(ids) and min(ids) >= 1
    assert len({o.name for o in scene.objects}) == len(ids)
    for obj in scene.objects:
        assert isinstance(obj.mesh, trimesh.Trimesh) and len(obj.mesh.faces) > 0
        assert obj.mesh.visual.uv.shape == (len(obj.mesh.vertices), 2)
        assert obj.texture.dtype == np.float32 and obj.texture.ndim == 3
        assert obj.texture.shape[2] == 3 and np.isfinite(obj.texture).all()
        assert 0 <= obj.texture.min() and obj.texture.max() <= 1
        for k in (0, scene.frames):
            pose = obj.pose(k)
            assert pose.shape == (4, 4) and np.isfinite(pose).all()
            np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
    assert scene.lights
    assert scene.robot.pose(scene.frames + 0.5).shape == (4, 4)
    # The parsed data and the source travel with the scene (dataset.json).
    assert scene.data["render"]["width"] == 64
    assert "[rig]" in scene.source


def test_default_scene_keeps_moderate_defaults():
    scene = load_scene(SCENES[[p.stem for p in SCENES].index("default")])
    assert scene.render.width <= 512 and scene.render.height <= 512
    assert scene.render.spp <= 64 and scene.frames <= 16


def test_scene_loads_deterministically():
    a = load_scene(SCENES[0])
    b = load_scene(SCENES[0])
    for oa, ob in zip(a.objects, b.objects, strict=True):
        np.testing.assert_array_equal(oa.texture, ob.texture)
        np.testing.assert_array_equal(oa.mesh.vertices, ob.mesh.vertices)


# -- the model ------------------------------------------------------------------


def test_base_scene_model(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    assert scene.name == "t" and scene.frames == 3 and scene.frame_interval == 0.1
    assert (scene.render.width, scene.render.height, scene.render.spp) == (64, 64, 2)
    assert scene.render.integrator == "direct" and scene.render.denoise == "oidn"
    assert scene.render.seed == 0
    assert [o.name for o in scene.objects] == [f"room.{p}" for p in geometry.ROOM_PARTS]
    assert [o.id for o in scene.objects] == [1, 2, 3, 4, 5, 6]
    assert scene.object_names[3] == "room.wall_xp"
    # Rig: image centre by default, rim a margin inside the image.
    assert (scene.rig.cam1.x_c, scene.rig.cam1.y_c, scene.rig.cam1.r_m) == (32.0, 32.0, 30.0)
    assert scene.rig.cam1.tip_h == 0.3 and scene.rig.cam2.tip_h == 0.0
    np.testing.assert_array_equal(scene.robot.pose(2)[:3, 3], [0, 0, 0.6])
    poses = scene.poses(1)
    assert set(poses) == {"robot", "objects"} and set(poses["objects"]) == {
        str(i) for i in range(1, 7)
    }


def test_room_faces_point_inwards(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    centre = np.array([0.0, 0.0, 1.5])
    for obj in scene.objects:
        to_centre = centre - obj.mesh.triangles_center
        assert np.all(np.einsum("ij,ij->i", obj.mesh.face_normals, to_centre) > 0), obj.name


def test_room_parts_get_distinct_textures(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    walls = [o.texture for o in scene.objects]
    assert not np.array_equal(walls[2], walls[3])


def test_motion_in_scene_uses_the_frame_interval(tmp_path):
    text = BASE.replace(
        "position = [0.0, 0.0, 0.6]",
        'position = [0.0, 0.0, 0.6]\nmotion = { type = "constant", velocity = [0.5, 0, 0],'
        " angular_velocity = [0, 0, 90] }",
    )
    scene = load_scene(write(tmp_path, text))
    pose = scene.robot.pose(2)  # t = 0.2 s
    np.testing.assert_allclose(pose[:3, 3], [0.1, 0, 0.6], atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arctan2(pose[1, 0], pose[0, 0])), 18.0)


def test_keyframes_in_scene_by_time_and_frame(tmp_path):
    text = (
        BASE
        + """
[[objects]]
name = "ball"
type = "sphere"
radius = 0.2
position = [1.5, 0, 1.0]
[objects.motion]
type = "keyframes"
interpolation = "linear"
[[objects.motion.keys]]
frame = 0
position = [1.5, 0.0, 1.0]
[[objects.motion.keys]]
time = 0.4
position = [1.5, 0.8, 1.0]
rotation = [0, 0, 40]
"""
    )
    scene = load_scene(write(tmp_path, text))
    ball = scene.objects[-1]
    assert ball.name == "ball" and ball.id == 7 and ball.moving
    np.testing.assert_allclose(ball.pose(2)[:3, 3], [1.5, 0.4, 1.0], atol=1e-12)
    np.testing.assert_allclose(ball.pose(4)[:3, 3], [1.5, 0.8, 1.0])
    np.testing.assert_allclose(np.degrees(np.arctan2(ball.pose(1)[1, 0], ball.pose(1)[0, 0])), 10)


def test_explicit_ids_and_automatic_ids_do_not_clash(tmp_path):
    text = BASE.replace('name = "room"', 'name = "room"\nid = 1') + textwrap.dedent(
        """
        [[objects]]
        name = "a"
        type = "box"
        size = [0.3, 0.3, 0.3]
        position = [1.5, 1.5, 1.0]
        id = 10
        [[objects]]
        name = "b"
        type = "box"
        size = [0.3, 0.3, 0.3]
        position = [-1.5, 1.5, 1.0]
        """
    )
    scene = load_scene(write(tmp_path, text))
    assert [o.id for o in scene.objects] == [1, 2, 3, 4, 5, 6, 10, 7]
    # An explicit id inside the room's six is a clash.
    expect_error(write(tmp_path, text.replace("id = 10", "id = 4")), "objects[1].id", "not used")


def test_lights_of_every_kind(tmp_path):
    text = BASE + textwrap.dedent(
        """
        [[lights]]
        type = "area"
        position = [0, 0, 2.9]
        size = [1.0, 0.5]
        radiance = [10, 9, 8]
        [[lights]]
        type = "environment"
        radiance = 0.2
        [[lights]]
        type = "directional"
        direction = [0, 0, -2]
        irradiance = 3
        """
    )
    scene = load_scene(write(tmp_path, text))
    kinds = [light.type for light in scene.lights]
    assert kinds == ["point", "area", "environment", "directional"]
    area = scene.lights[1]
    m = area.to_world()
    np.testing.assert_allclose(m[:3, 3], [0, 0, 2.9])
    np.testing.assert_allclose(m[:3, 2], [0, 0, -1])  # the normal faces down
    np.testing.assert_allclose(
        sorted([np.linalg.norm(m[:3, 0]), np.linalg.norm(m[:3, 1])]), [0.25, 0.5]
    )
    assert np.linalg.det(m[:3, :3]) > 0
    np.testing.assert_allclose(scene.lights[3].direction, [0, 0, -1])
    np.testing.assert_allclose(scene.lights[2].radiance, [0.2, 0.2, 0.2])


# -- overrides ------------------------------------------------------------------


def test_overrides_apply_before_validation(tmp_path):
    path = write(tmp_path, BASE)
    scene = load_scene(
        path, {"render.width": 128, "render.height": 96, "render.spp": 4, "frames": 5,
               "render.seed": 7}
    )  # fmt: skip
    assert (scene.render.width, scene.render.height, scene.render.spp) == (128, 96, 4)
    assert scene.frames == 5 and scene.render.seed == 7
    assert scene.rig.cam2.width == 128 and scene.rig.cam2.r_m == 46.0
    assert scene.data["frames"] == 5 and scene.overrides["frames"] == 5
    # A bad override is named as such.
    msg = expect_error(path, "render.spp", "override", "integer", overrides={"render.spp": "x"})
    assert "render.spp" in msg
    expect_error(path, "render.sp", "unknown key", overrides={"render.sp": 3})
    expect_error(
        path,
        "objects[0].size (set by an override)",
        "list of 3",
        overrides={"objects.0.size": [1, 2]},
    )


def test_apply_overrides_indexes_lists_and_does_not_mutate():
    data = {"objects": [{"a": 1}, {"a": 2}], "render": {"spp": 1}}
    out = apply_overrides(data, {"objects.1.a": 5, "render.spp": 9, "new.key": 1}, "f")
    assert out["objects"][1]["a"] == 5 and out["render"]["spp"] == 9 and out["new"]["key"] == 1
    assert data["objects"][1]["a"] == 2 and data["render"]["spp"] == 1
    with pytest.raises(SceneError, match="index"):
        apply_overrides(data, {"objects.7.a": 1}, "f")
    with pytest.raises(SceneError, match="not a table"):
        apply_overrides(data, {"render.spp.x": 1}, "f")


def test_parse_override():
    assert parse_override("render.spp=4") == ("render.spp", 4)
    assert parse_override("frame_interval = 0.5") == ("frame_interval", 0.5)
    assert parse_override("robot.position=[1, 2, 3]") == ("robot.position", [1, 2, 3])
    assert parse_override("render.integrator=direct") == ("render.integrator", "direct")
    with pytest.raises(SceneError):
        parse_override("render.spp")


# -- errors name the file, the key and what was expected -------------------------


@pytest.mark.parametrize(
    ("old", "new", "fragments"),
    [
        ("frames = 3", "frames = 3\ncolour = 1", ["colour", "unknown key", "frames"]),
        ("spp = 2", "spp = 2\nsamples = 4", ["render.samples", "unknown key", "spp"]),
        ("wavelength = [0.1, 1.0]", "wavelength = [0.1, 1.0]\nscal = 2",
         ["objects[0].texture.scal", "unknown key", "tile"]),
        ("size = [6.0, 5.0, 3.0]", "size = [6.0, 5.0, 3.0]\nradius = 1",
         ["objects[0].radius", "unknown key"]),
        ("intensity = 5.0", "intensity = 5.0\nsize = [1, 1]", ["lights[0].size", "unknown key"]),
        ("[robot]", "[robot]\nspeed = 1", ["robot.speed", "unknown key"]),
    ],
)  # fmt: skip
def test_unknown_key(tmp_path, old, new, fragments):
    expect_error(write(tmp_path, BASE.replace(old, new, 1)), *fragments)


@pytest.mark.parametrize(
    ("old", "new", "fragments"),
    [
        ("spp = 2", 'spp = "many"', ["render.spp", "'many'", "an integer >= 1"]),
        ("spp = 2", "spp = 2.5", ["render.spp", "an integer"]),
        ("frames = 3", "frames = 0", ["frames", "an integer >= 1"]),
        ("frame_interval = 0.1", "frame_interval = -1", ["frame_interval", "> 0"]),
        ("width = 64", "width = true", ["render.width", "an integer"]),
        ("d = 0.10", 'd = "far"', ["rig.d", "a number > 0"]),
        ("position = [0.0, 0.0, 0.6]", "position = [0.0, 0.6]", ["robot.position", "list of 3"]),
        ("size = [6.0, 5.0, 3.0]", "size = [6.0, -5.0, 3.0]", ["objects[0].size", "> 0"]),
        ('type = "room"', 'type = "tent"', ["objects[0].type", "'room'"]),
        ("tile = 2.0", 'tile = 2.0\ntype = "marble"', ["objects[0].texture.type", "'noise'"]),
        ("wavelength = [0.1, 1.0]", "wavelength = [0.001, 1.0]",
         ["objects[0].texture.wavelength", "2 texels"]),
        ('type = "point"', 'type = "laser"', ["lights[0].type", "'area'"]),
        ("intensity = 5.0", 'intensity = "bright"', ["lights[0].intensity", "list of 3"]),
        ("[render]", '[render]\nintegrator = "magic"', ["render.integrator", "'path'"]),
    ],
)  # fmt: skip
def test_wrong_type_or_value(tmp_path, old, new, fragments):
    expect_error(write(tmp_path, BASE.replace(old, new, 1)), *fragments)


def test_missing_required_keys(tmp_path):
    expect_error(write(tmp_path, BASE.replace("s = 0.30\n", "")), "rig.s", "missing")
    text = BASE[: BASE.index("[[lights]]")]
    expect_error(write(tmp_path, text), "lights", "at least one")
    expect_error(write(tmp_path, BASE.replace("[rig]\nd = 0.10\nR = 0.05\ns = 0.30\n", "")), "rig")


def test_not_toml_and_no_file(tmp_path):
    expect_error(write(tmp_path, "frames = = 3"), "not valid TOML")
    with pytest.raises(SceneError, match="not found"):
        load_scene(tmp_path / "nothing.toml")


@pytest.mark.parametrize(
    ("old", "new", "fragments"),
    [
        # s <= d + R: cam1's camera would sit inside cam2's mirror.
        ("s = 0.30", "s = 0.12", ["rig.s", "expected s > d + R"]),
        # The walls within the rig's min_common_range (0.8 m): no common view.
        ("position = [0.0, 0.0, 0.6]", "position = [2.5, 0.0, 0.6]",
         ["robot.position", "min_common_range", "room"]),
        # Below the floor.
        ("position = [0.0, 0.0, 0.6]", "position = [0.0, 0.0, 0.05]",
         ["robot.position", "floor"]),
        # The rim circle leaves the image.
        ("s = 0.30", "s = 0.30\nr_m = 40", ["rig.r_m", "inside the image"]),
        ("s = 0.30", "s = 0.30\nx_c = 99", ["rig.x_c", "inside the image"]),
    ],
)  # fmt: skip
def test_impossible_rig(tmp_path, old, new, fragments):
    expect_error(write(tmp_path, BASE.replace(old, new, 1)), *fragments)


def test_robot_driving_into_a_wall_is_caught_at_the_frame(tmp_path):
    text = BASE.replace(
        "position = [0.0, 0.0, 0.6]",
        'position = [1.5, 0.0, 0.6]\nmotion = { type = "constant", velocity = [4.0, 0, 0] }',
    )
    msg = expect_error(write(tmp_path, text), "robot.motion", "frame 2", "min_common_range")
    assert "room" in msg


def test_object_entering_the_rig(tmp_path):
    text = BASE + textwrap.dedent(
        """
        [[objects]]
        name = "ram"
        type = "box"
        size = [0.2, 0.2, 0.2]
        position = [1.0, 0.0, 0.7]
        motion = { type = "constant", velocity = [-5.0, 0, 0] }
        """
    )
    expect_error(write(tmp_path, text), "objects[1].motion", "'ram'", "enters the rig", "frame 2")


def test_nothing_in_the_common_region(tmp_path):
    text = BASE[: BASE.index("[[objects]]")] + textwrap.dedent(
        """
        [[objects]]
        name = "near"
        type = "box"
        size = [0.2, 0.2, 0.2]
        position = [0.5, 0.0, 0.7]
        [[lights]]
        type = "environment"
        radiance = 1.0
        """
    )
    expect_error(write(tmp_path, text), "objects", "both cameras")


def test_missing_mesh_and_texture_files(tmp_path):
    mesh = BASE + textwrap.dedent(
        """
        [[objects]]
        name = "statue"
        type = "mesh"
        path = "meshes/statue.obj"
        position = [1.5, 0, 1]
        """
    )
    expect_error(write(tmp_path, mesh), "objects[1].path", "not found", "statue.obj")
    tex = BASE.replace("tile = 2.0", 'type = "image"\npath = "poster.png"').replace(
        "wavelength = [0.1, 1.0]\n", ""
    )
    expect_error(write(tmp_path, tex), "objects[0].texture.path", "not found", "poster.png")
    bad_suffix = mesh.replace("statue.obj", "statue.txt")
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "statue.txt").write_text("x")
    expect_error(write(tmp_path, bad_suffix), "objects[1].path", ".obj")
    (tmp_path / "meshes" / "statue.obj").write_text("this is no mesh\n")
    expect_error(write(tmp_path, mesh), "objects[1].path")


def test_library_prefix_names_the_shipped_assets(tmp_path):
    # "library:P" resolves against scenes/, wherever the scene file is (generated scenes)
    tex = BASE.replace("tile = 2.0", 'type = "image"\npath = "library:assets/poster.png"')
    scene = load_scene(write(tmp_path, tex.replace("wavelength = [0.1, 1.0]\n", "")))
    assert scene.objects[0].texture.shape == (256, 256, 3)  # poster.png is 256 x 256
    missing = tex.replace("poster.png", "nothing.png").replace("wavelength = [0.1, 1.0]\n", "")
    expect_error(write(tmp_path, missing), "objects[0].texture.path", "not found", "nothing.png")


# -- meshes from files ----------------------------------------------------------


@pytest.mark.parametrize("suffix", ["obj", "ply", "stl", "glb"])
def test_mesh_files_load_with_uvs(tmp_path, suffix):
    src = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    src.export(tmp_path / f"blob.{suffix}")
    text = BASE + textwrap.dedent(
        f"""
        [[objects]]
        name = "blob"
        type = "mesh"
        path = "blob.{suffix}"
        scale = 0.8
        position = [1.5, 0.5, 1.0]
        [objects.texture]
        tile = 0.5
        resolution = 64
        wavelength = [0.05, 0.5]
        """
    )
    scene = load_scene(write(tmp_path, text))
    blob = scene.objects[-1]
    assert blob.kind == "mesh"
    assert len(blob.mesh.faces) == len(src.faces)
    np.testing.assert_allclose(np.abs(blob.mesh.vertices).max(), 0.4, rtol=1e-6)
    uv = blob.mesh.visual.uv
    assert uv.shape == (len(blob.mesh.vertices), 2) and np.isfinite(uv).all()
    # Box projection: the UVs are two of the vertex coordinates / tile (|coordinate| <= 0.4 m).
    assert np.abs(uv).max() <= 0.4 / 0.5 + 1e-6 and np.ptp(uv[:, 0]) > 1.0


def test_mesh_file_uvs_are_kept(tmp_path):
    m = geometry.box((0.4, 0.4, 0.4), tile=0.2)
    m.export(tmp_path / "crate.obj")
    base = BASE + textwrap.dedent(
        """
        [[objects]]
        name = "crate"
        type = "mesh"
        path = "crate.obj"
        uv = "file"
        position = [1.5, 0.5, 1.0]
        """
    )
    scene = load_scene(write(tmp_path, base))
    uv = scene.objects[-1].mesh.visual.uv
    assert np.ptp(uv[:, 0]) == pytest.approx(2.0, abs=1e-6)  # 0.4 m / 0.2 m per tile
    trimesh.creation.box().export(tmp_path / "plain.stl")
    expect_error(write(tmp_path, base.replace("crate.obj", "plain.stl")), "objects[1].path", "uv")


def test_image_texture_from_file(tmp_path):
    import cv2

    img = (np.indices((32, 32)).sum(axis=0) * 4).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "poster.png"), img)
    text = BASE.replace("tile = 2.0", 'type = "image"\npath = "poster.png"\ntile = 2.0').replace(
        "wavelength = [0.1, 1.0]\n", ""
    )
    text = text.replace("resolution = 64\n", "")
    scene = load_scene(write(tmp_path, text))
    assert scene.objects[0].texture.shape == (32, 32, 3)


# -- geometry -------------------------------------------------------------------


def test_primitives_face_outwards_and_have_uvs():
    for mesh, volume in [
        (geometry.box((1, 2, 3)), 6.0),
        (geometry.cylinder(0.5, 2.0, sections=256), np.pi * 0.25 * 2),
        (geometry.sphere(1.0, sections=256), 4 / 3 * np.pi),
    ]:
        assert mesh.volume == pytest.approx(volume, rel=2e-3)  # positive: outward normals
        assert mesh.visual.uv.shape == (len(mesh.vertices), 2)
    p = geometry.plane((2, 1))
    np.testing.assert_allclose(p.face_normals, [[0, 0, 1], [0, 0, 1]])


def test_shading_normals_of_curved_primitives():
    sph = geometry.sphere(0.7, sections=32)
    np.testing.assert_allclose(sph.vertex_normals, sph.vertices / 0.7, atol=1e-12)
    cyl = geometry.cylinder(0.3, 1.0, sections=32)
    n = cyl.vertex_normals
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    side = np.abs(n[:, 2]) < 0.5
    np.testing.assert_allclose(n[side, :2], cyl.vertices[side, :2] / 0.3, atol=1e-12)
    # Every normal agrees with the faces it belongs to (outward).
    for mesh in (sph, cyl, geometry.box((1, 1, 1))):
        fn = mesh.face_normals
        vn = mesh.vertex_normals[mesh.faces]
        assert np.all(np.einsum("fij,fj->fi", vn, fn) > 0.9)


def test_cylinder_uv_wraps_a_whole_number_of_tiles():
    mesh = geometry.cylinder(0.3, 1.0, tile=0.5, caps=False)
    uv = mesh.visual.uv
    # 2 pi 0.3 / 0.5 = 3.77 -> 4 whole repeats around, so the seam matches.
    assert uv[:, 0].max() == pytest.approx(4.0)
    assert uv[:, 1].max() == pytest.approx(2.0)
