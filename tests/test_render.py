"""RGB rendering through pyrender/EGL (docs/spec.md §8): pixel-aligned with the ray-traced layers,
materials and textures the right way up, per-pixel lights in photometric units, one
exposure and tone-mapping step, one renderer reused across houses, and one-line errors
when EGL cannot work.

Golden images: ``tests/golden/*.png`` were rendered with Mesa's llvmpipe. After a deliberate
change of the look, regenerate them with ``SCENEFORGE_REGEN_GOLDEN=1 pytest tests/test_render.py``
and look at them before committing.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image
from sceneforge.cli.doctor import doctor

from sceneforge.camera_sampler import CameraSamplerConfig, sample_cameras
from sceneforge.cameras import Camera, default_intrinsics, look_at_camera, pose_from_view
from sceneforge.colour import linear_to_srgb, srgb_to_linear
from sceneforge.errors import SceneforgeError
from sceneforge.houses import BUNDLED_TOY, House, Instance, Material, Room, discover, load, make_instance
from sceneforge.layers import frontal_layers
from sceneforge.raytrace import HouseTracer
from sceneforge.render import (
    RenderConfig,
    Renderer,
    house_batches,
    house_lights,
    room_lights,
    tonemap,
)
from sceneforge.render.lights import WINDOW_CONE, room_albedo, room_ambient
from sceneforge.render.sky import window_colour
from sceneforge.render.tonemap import KEY, SOFT_KNEE, aces, auto_exposure, encode, encoding_thresholds, soft

from .conftest import BREAKFAST_ROOM, box_instance, box_room, needs_shared

pytest.importorskip("pyrender", reason="pyrender is not installed (pip install 'sceneforge[render]')")

GOLDEN = Path(__file__).parent / "golden"
REGEN = os.environ.get("SCENEFORGE_REGEN_GOLDEN") == "1"
#: light every surface with exactly its base colour: rendered pixel = sRGB(linear texel × base)
UNLIT = RenderConfig(flat=True, ambient=1.0, exposure=1.0, tone="clip")


@pytest.fixture(scope="module")
def toy_houses():
    return [load(s) for s in discover(BUNDLED_TOY)]


@pytest.fixture(scope="module")
def renderer():
    with Renderer(320, 240) as r:
        yield r


def boxed_room(name="room") -> House:
    """A 4 × 3 × 4 m room of grey envelope boxes around the origin, floor at y = 0."""
    return box_room(name, size=4.0, height=3.0)


# --------------------------------------------------------------------------- alignment


def toy_views(houses, per_house=2):
    for house in houses:
        tracer = HouseTracer(house)
        cameras, _ = sample_cameras(house, per_house, np.random.default_rng(7), tracer=tracer)
        assert len(cameras) == per_house
        yield from ((house, tracer, c) for c in cameras)


def test_zbuffer_depth_equals_ray_traced_first_hit(renderer, toy_houses):
    """RGB and layers are aligned: the z-buffer (converted to planar metres) is the first hit
    of the ray through each pixel centre, within 1 mm on >= 99 % of pixels of toy-house views."""
    for house, tracer, camera in toy_views(toy_houses):
        traced = frontal_layers(house, camera, tracer).traditional_depth
        rendered = renderer.depth(house, camera)
        assert rendered.dtype == np.float32 and rendered.shape == (240, 320)
        seen = np.isfinite(traced)
        assert seen.mean() > 0.95
        assert (np.isfinite(rendered) == seen).mean() > 0.999, house.id
        close = np.abs(rendered - traced) < 1e-3
        assert close[seen].mean() >= 0.99, f"{house.id}: {close[seen].mean():.4f} of pixels within 1 mm"


@needs_shared(BREAKFAST_ROOM)
def test_textured_gltf_scene_is_aligned(renderer):
    house = load(BREAKFAST_ROOM)
    assert any(i.material.texture is not None and i.uv is not None for i in house.instances)
    tracer = HouseTracer(house)
    cameras, _ = sample_cameras(house, 1, np.random.default_rng(0), CameraSamplerConfig(max_escape_fraction=0.5),
                                tracer)
    traced = frontal_layers(house, cameras[0], tracer).traditional_depth
    seen = np.isfinite(traced)
    close = np.abs(renderer.depth(house, cameras[0]) - traced) < 1e-3
    assert close[seen].mean() >= 0.99
    assert renderer.render(house, cameras[0]).std() > 10  # textured, not blank


def test_red_box_is_red_exactly_where_d1_is_the_box():
    house = boxed_room()
    box = box_instance(house, "box", 29, (0.6, 0.5, 0.4), (0.31, 0.25, 0.73))
    box.material = Material(base_color=(1.0, 0.0, 0.0, 1.0))
    # an off-grid pose and a skewed K, so that no edge runs through pixel centres by construction
    K = default_intrinsics(160, 120) + np.array([[0, 3.0, 1.3], [0, 0, -0.7], [0, 0, 0]])
    camera = Camera(K, pose_from_view([-0.93, 1.37, -1.41], [0.55, -0.52, 1.0]), 160, 120)
    d1 = frontal_layers(house, camera).instance[0] == box.id
    assert 0.05 < d1.mean() < 0.6
    with Renderer(160, 120) as r:
        rgb = r.render(house, camera).astype(int)
    red = (rgb[..., 0] > 0) & (rgb[..., 1] == 0) & (rgb[..., 2] == 0)
    np.testing.assert_array_equal(red, d1)
    assert (rgb[~d1][:, 1] > 0).all()  # grey envelope everywhere else


def test_antialiasing_blends_edges_and_is_off_by_default():
    house = boxed_room()
    box = box_instance(house, "box", 29, (0.6, 0.5, 0.4), (0.31, 0.25, 0.73))
    box.material = Material(base_color=(1.0, 0.0, 0.0, 1.0))
    camera = look_at_camera([-0.93, 1.37, -1.41], [0.55, -0.52, 1.0], width=160, height=120)

    def blended(rgb):  # neither red (g = b = 0) nor grey (r = g = b)
        rgb = rgb.astype(int)
        return ((rgb[..., 1] > 0) & (rgb[..., 0] - rgb[..., 1] > 10)).sum()

    with Renderer(160, 120) as sharp, Renderer(160, 120, antialias=True) as smooth:
        plain, aa = sharp.render(house, camera), smooth.render(house, camera)
    assert blended(plain) == 0
    assert blended(aa) > 20  # the box outline
    assert (np.abs(plain.astype(int) - aa).max(-1) > 2).mean() < 0.1  # and nothing else changes much


# --------------------------------------------------------------------------- materials


def quad_house(texture) -> tuple[House, Camera]:
    """A 2 × 2 m textured quad facing a camera 2 m away, +Y up; uv (0, 0) at its bottom left
    as the camera sees it. ``world(u, v)`` is the point of the quad at texture coordinates u, v."""
    h = House(id="quad", instances=[])
    # the camera looks along +z with +Y up, so its right is world -x
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    make_instance(h, name="poster", category=11, label="picture", room_id=None, vertices=world(uv),
                  faces=[[0, 1, 2], [0, 2, 3]], uv=uv, material=Material((1.0, 1.0, 1.0, 1.0), texture))
    return h, look_at_camera([0, 0, 0], [0, 0, 1], width=64, height=48)


def world(uv) -> np.ndarray:
    uv = np.asarray(uv, float).reshape(-1, 2)
    return np.column_stack([1 - 2 * uv[:, 0], 2 * uv[:, 1] - 1, np.full(len(uv), 2.0)])


#: colour of each quadrant of the test texture and the uv of its centre (v = 1: top row)
QUADRANTS = {(0, 0): ((255, 0, 0), (0.25, 0.75)), (0, 1): ((0, 255, 0), (0.75, 0.75)),
             (1, 0): ((0, 0, 255), (0.25, 0.25)), (1, 1): ((255, 255, 255), (0.75, 0.25))}


def quadrant_image() -> Image.Image:
    """8 × 8 texels, one colour per 4 × 4 quadrant (row, column of quadrant from the top left)."""
    a = np.zeros((8, 8, 3), np.uint8)
    for (r, c), (colour, _) in QUADRANTS.items():
        a[4 * r:4 * r + 4, 4 * c:4 * c + 4] = colour
    return Image.fromarray(a)


@pytest.mark.parametrize("kind", ["path", "image"])
def test_texture_is_upright_and_exact(kind, tmp_path):
    """uv follow the OpenGL convention: v = 1 is the top row of the image (a file from OBJ/MTL,
    SUNCG or 3D-FRONT and a decoded image from GLB look the same)."""
    texture = quadrant_image()
    if kind == "path":
        texture.save(tmp_path / "t.png")
        texture = tmp_path / "t.png"
    house, camera = quad_house(texture)
    with Renderer(64, 48, config=UNLIT) as r:
        rgb = r.render(house, camera)
    for (row, column), (colour, uv) in QUADRANTS.items():
        ((u, v),), _ = camera.project(world(uv))
        assert (v < 24) == (row == 0) and (u < 32) == (column == 0)  # seen upright, not mirrored
        assert tuple(rgb[int(v), int(u)]) == colour


def test_unreadable_texture_names_house_and_file(tmp_path):
    (tmp_path / "broken.png").write_bytes(b"not a png")
    house, camera = quad_house(tmp_path / "broken.png")
    with Renderer(64, 48) as r, pytest.raises(SceneforgeError, match=r"house quad: .*broken.png: cannot read texture"):
        r.render(house, camera)


def test_base_colour_and_alpha():
    """Untextured: the linear base colour, sRGB-encoded; alpha is ignored (opaque, like the layers)."""
    house, camera = quad_house(None)
    house.instances[0].material = Material((0.25, 0.5, 1.0, 0.3))
    with Renderer(64, 48, config=UNLIT) as r:
        rgb = r.render(house, camera)
    expected = np.round(255 * linear_to_srgb([0.25, 0.5, 1.0]))
    np.testing.assert_allclose(rgb[24, 32], expected, atol=1)


def test_shading_is_linear_texels_times_light():
    """A mid-grey sRGB texel (128) under half the light is sRGB(0.5 · linear(128)) = 92, not
    the 64 of shading in sRGB space: textures are decoded, shaded linearly, encoded."""
    texture = Image.fromarray(np.full((4, 4, 3), 128, np.uint8))
    house, camera = quad_house(texture)
    with Renderer(64, 48, config=RenderConfig(flat=True, ambient=0.5, exposure=1.0, tone="clip")) as r:
        rgb = r.render(house, camera).astype(int)
    expected = round(255 * float(linear_to_srgb(0.5 * srgb_to_linear(128 / 255))))
    assert expected == 92
    assert (np.abs(rgb[8:40, 16:48] - expected) <= 1).all()


def test_golden_textured_quad(tmp_path):
    """The quadrant texture on a quad under a room light, as it looked (orientation, colour
    space, per-pixel falloff, exposure and tone curve); tolerance for GL drivers' rounding."""
    texture = quadrant_image()
    texture.save(tmp_path / "t.png")
    house, camera = quad_house(tmp_path / "t.png")
    house.rooms.append(Room("r", "room", 0))
    house.instances[0].room_id = "r"
    with Renderer(64, 48, config=RenderConfig(ambient=0.2, light_below_ceiling=0.0)) as r:
        rgb = r.render(house, camera)
    compare_golden(rgb, "textured_quad.png")
    # per pixel: the centre of the quad (nearest the light in front of it) is the brightest white
    white = rgb[26:46, 0:30].astype(int).sum(-1)
    assert white.std() > 1


def two_material_box() -> tuple[House, Instance, Camera]:
    """A box in a room: its top faces (normal +y) red, its sides blue; seen from above at a slant."""
    house = boxed_room()
    box = box_instance(house, "box", 29, (0.6, 0.5, 0.4), (0.31, 0.25, 0.73))
    normals = np.cross(*(box.vertices[box.faces[:, k]] - box.vertices[box.faces[:, 0]] for k in (1, 2)))
    box.materials = (Material((1.0, 0.0, 0.0, 1.0)), Material((0.0, 0.0, 1.0, 1.0)))
    box.face_material = np.where(normals[:, 1] > 0.5 * np.linalg.norm(normals, axis=1), 0, 1).astype(np.int32)
    assert set(box.face_material) == {0, 1}
    camera = Camera(default_intrinsics(160, 120), pose_from_view([-0.9, 1.6, -1.2], [0.6, -0.7, 1.0]), 160, 120)
    return house, box, camera


def test_box_with_two_materials_shows_each_where_its_faces_are():
    house, box, camera = two_material_box()
    layers = frontal_layers(house, camera)
    on_box = layers.instance[0] == box.id
    # the world normal of each pixel's first hit: up = a top face (red), else a side (blue)
    up = (np.einsum("ij,jhw->ihw", camera.cam_to_world[:3, :3], np.nan_to_num(layers.normal))[1] > 0.9)
    top, side = on_box & up, on_box & ~up
    assert top.sum() > 100 and side.sum() > 100
    with Renderer(160, 120) as r:
        rgb = r.render(house, camera).astype(int)
    red = (rgb[..., 0] > 0) & (rgb[..., 1] == 0) & (rgb[..., 2] == 0)
    blue = (rgb[..., 2] > 0) & (rgb[..., 0] == 0) & (rgb[..., 1] == 0)
    np.testing.assert_array_equal(red, top)
    np.testing.assert_array_equal(blue, side)


# --------------------------------------------------------------------------- lighting


def test_room_light_hangs_under_the_ceiling_centre():
    house = boxed_room()
    (light,) = room_lights(house, RenderConfig(lamp_power=500.0, light_below_ceiling=0.3)).values()
    np.testing.assert_allclose(light.position, [0, 3.1 - 0.3, 0])
    # an isotropic point source of 500 lm: 500 / 4π cd
    np.testing.assert_allclose(light.intensity, 500.0 / (4 * np.pi))
    assert light.flux == 500.0


def test_lamps_replace_the_fallback_and_windows_shine_inwards():
    house = boxed_room()
    config = RenderConfig(lamp_power=400.0, sky_luminance=1500.0)
    assert [light.source for light in house_lights(house, config)] == ["fallback"]
    lamp = box_instance(house, "lamp", 35, (0.2, 1.6, 0.2), (1.0, 0.8, 1.0))  # a floor lamp
    window = make_instance(house, name="window", category=9, label="window", room_id=lamp.room_id,
                           vertices=[[-2, 1, -1], [-2, 2, -1], [-2, 2, 1], [-2, 1, 1]], faces=[[0, 1, 2], [0, 2, 3]])
    lights = house_lights(house, config)
    assert [light.source for light in lights] == ["lamp", "window"]
    np.testing.assert_allclose(lights[0].position, [1.0, 1.6 + 0.3, 1.0])  # a standing lamp: above its top
    hanging = box_instance(house, "pendant", 35, (0.3, 0.2, 0.3), (-1.0, 2.7, 0.0))
    np.testing.assert_allclose(house_lights(house, config)[1].position, [-1.0, 2.6 - 0.3, 0.0])  # below it
    house.instances.remove(hanging)
    # the window: a 2 × 1 m Lambertian panel of 1500 cd/m² facing into the room (+x)
    np.testing.assert_allclose(lights[1].position, [-2, 1.5, 0])
    np.testing.assert_allclose(lights[1].direction, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose([lights[1].intensity, lights[1].flux], [1500.0 * 2, np.pi * 1500.0 * 2])
    assert lights[1].instance == window.id and lights[1].radiance == 1500.0
    assert window.envelope
    # a window lights its room: no fallback; without sky light the fallback comes back
    house.instances.remove(lamp)
    assert [light.source for light in house_lights(house, config)] == ["window"]
    assert [light.source for light in house_lights(house, RenderConfig(sky_luminance=0.0))] == ["fallback"]


def lit_floor():
    """An object floor in a room whose bounds' top is at y = 2 (a marker), and a camera
    looking down at it."""
    house = House(id="two", instances=[], rooms=[Room("a", "room", 0)])
    # an object (not envelope), so that D1 and its instance layer see it
    floor = make_instance(house, name="board", category=0, label="board", room_id="a",
                          vertices=[[-2, 0, 0], [2, 0, 0], [2, 0, 4], [-2, 0, 4]], faces=[[0, 2, 1], [0, 3, 2]],
                          material=Material((0.6, 0.6, 0.6, 1.0)))
    make_instance(house, name="marker", category=0, label="marker", room_id="a",
                  vertices=[[0, 2, 2], [0.01, 2, 2], [0, 2, 2.01]], faces=[[0, 1, 2]])
    camera = look_at_camera([0, 1.0, -0.5], [0, -0.6, 1], width=64, height=48)
    return house, floor, camera


def floor_points(house, floor, camera):
    """(mask (H, W) of the pixels that see the floor, world points of their first hits)."""
    hits = frontal_layers(house, camera)
    seen = hits.instance[0] == floor.id
    origins, directions, depth_scale = camera.rays()
    t = (hits.depth[0].ravel() / depth_scale)[seen.ravel()]
    return seen, origins[seen.ravel()] + t[:, None] * directions[seen.ravel()]


def test_per_pixel_light_is_lambert_over_distance_squared_from_either_side():
    """A floor lit by its room's light, per pixel: radiance = base / π · (E_ambient + I cos / d²)
    at the surface point of each pixel centre, whichever way the floor's faces are wound;
    the image is the tone-mapped radiance."""
    config = RenderConfig(ambient=0.2, lamp_power=600.0, light_below_ceiling=0.0)
    house, floor, camera = lit_floor()
    (light,) = house_lights(house, config)
    np.testing.assert_allclose(light.position, [0.0, 2.0, 2.0], atol=0.01)
    (ambient,) = room_ambient(house, config).values()
    size = np.ptp(np.concatenate([i.vertices for i in house.instances]), axis=0)
    area = 2 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    rho = room_albedo(house)["a"]  # the grey floor and a speck of white marker
    assert rho == pytest.approx(0.6, abs=1e-4)
    np.testing.assert_allclose(ambient, [0.2 * 600.0 / area * rho / (1 - rho)] * 3)  # white: a lamp's
    ambient = ambient[0]
    seen, points = floor_points(house, floor, camera)
    to_light = light.position - points
    d2 = (to_light ** 2).sum(1)
    irradiance = light.intensity * (to_light[:, 1] / np.sqrt(d2)) / np.maximum(d2, config.light_min_distance ** 2)
    expected = 0.6 / np.pi * (ambient + irradiance)
    for flip in (False, True):
        if flip:
            floor.faces = floor.faces[:, ::-1].copy()
        with Renderer(64, 48, config=config) as r:
            radiance, drawn = r.render_linear(house, camera)
            rgb = r.render(house, camera)
        assert (drawn == seen).mean() > 0.99  # the marker is a few pixels
        np.testing.assert_allclose(radiance[seen][:, 0], expected, rtol=2e-3)
        np.testing.assert_array_equal(rgb, tonemap(radiance, drawn))


def test_window_is_a_lambertian_panel_of_sky_light():
    """A room lit only by a window: the window shows the sky's radiance, and a floor point
    receives the panel's far field, L · A · cos θ_window · cos θ_floor / d²."""
    config = RenderConfig(ambient=0.0, sky_luminance=800.0)
    house, floor, camera = lit_floor()
    window = make_instance(house, name="window", category=9, label="window", room_id="a",
                           vertices=[[-0.5, 0.6, 4.0], [0.5, 0.6, 4.0], [0.5, 1.2, 4.0], [-0.5, 1.2, 4.0]],
                           faces=[[0, 2, 1], [0, 3, 2]])  # facing the camera
    camera = look_at_camera([0, 1.0, -0.5], [0, -0.25, 1], width=64, height=48)
    (light,) = house_lights(house, config)
    assert light.source == "window" and light.instance == window.id
    np.testing.assert_allclose(light.direction, [0, 0, -1], atol=1e-12)
    seen, points = floor_points(house, floor, camera)
    # the pixels whose ray meets the window plane inside the window, nothing in front of it
    origins, directions, _ = camera.rays()
    hit = origins + ((4.0 - origins[:, 2]) / directions[:, 2])[:, None] * directions
    on_window = ((hit[:, 1] > 0.61) & (hit[:, 1] < 1.19) & (np.abs(hit[:, 0]) < 0.49)).reshape(seen.shape)
    to_light = light.position - points
    d = np.sqrt((to_light ** 2).sum(1))
    cos_window = (light.direction @ -to_light.T) / d
    cos_floor = to_light[:, 1] / d
    lit = cos_window > np.cos(WINDOW_CONE)
    # of the outdoors' colour (luminance 1, daylight: bluer than white)
    colour = np.asarray(light.colour)
    np.testing.assert_allclose(colour, window_colour())
    assert colour @ [0.2126, 0.7152, 0.0722] == pytest.approx(1.0) and colour[2] > colour[1] > colour[0]
    expected = 0.6 / np.pi * 800.0 * 0.6 * np.where(lit, cos_window, 0) * cos_floor / np.maximum(d, 0.3) ** 2
    with Renderer(64, 48, config=config) as r:
        radiance, _ = r.render_linear(house, camera)
    assert on_window.sum() > 10 and lit.mean() > 0.5
    np.testing.assert_allclose(radiance[seen], expected[:, None] * colour, rtol=2e-3, atol=1e-3)
    # its own radiance (and the little it reflects)
    assert (radiance[on_window] >= 800.0 * colour * (1 - 1e-6)).all()


def test_window_shadows():
    """With ``shadows``, a box between the window and the floor shadows the floor behind it
    (window light only: those pixels go dark) and changes little elsewhere. (Lamps cast no
    shadows: pyrender 0.1.45 raises "Point light shadows not implemented".)"""
    house, floor, _ = lit_floor()
    make_instance(house, name="window", category=9, label="window", room_id="a",
                  vertices=[[-0.5, 0.6, 4.0], [0.5, 0.6, 4.0], [0.5, 1.2, 4.0], [-0.5, 1.2, 4.0]],
                  faces=[[0, 2, 1], [0, 3, 2]])
    box_instance(house, "crate", 0, (0.8, 0.5, 0.2), (0.0, 0.25, 3.0), room_id="a")
    camera = look_at_camera([0, 1.6, -0.5], [0, -0.6, 1], width=64, height=48)
    seen, points = floor_points(house, floor, camera)
    # floor points whose segment to the window's centre passes through the crate
    t = (3.0 - points[:, 2]) / (4.0 - points[:, 2])
    y, x = points[:, 1] + t * (0.9 - points[:, 1]), points[:, 0] * (1 - t)
    behind = (points[:, 2] < 2.8) & (y < 0.45) & (np.abs(x) < 0.35)
    assert behind.sum() > 10
    radiance = {}
    for shadows in (False, True):
        with Renderer(64, 48, config=RenderConfig(ambient=0.0, shadows=shadows)) as r:
            radiance[shadows] = r.render_linear(house, camera)[0][seen][:, 0]
    assert (radiance[True][behind] < 0.05 * radiance[False][behind]).mean() > 0.9
    # away from the crate: pyrender's shadow-map filtering (PCF) darkens light that grazes
    # the floor (by a tenth on most such pixels, a quarter at worst here), and never brightens
    lit = (points[:, 2] < 2.5) & (np.abs(points[:, 0]) > 1.2)
    ratio = radiance[True][lit] / radiance[False][lit]
    assert lit.sum() > 100 and ratio.min() > 0.7 and ratio.max() < 1.0 + 1e-6 and np.median(ratio) > 0.9


def lamp_lit_room() -> tuple[House, Camera]:
    """The box room with a floor lamp and a table, seen towards the lamp."""
    house = boxed_room()
    box_instance(house, "lamp", 35, (0.3, 1.2, 0.3), (1.2, 0.6, 1.2))
    box_instance(house, "table", 7, (1.0, 0.7, 0.6), (-0.5, 0.35, 0.3))
    return house, look_at_camera([0.3, 1.5, -1.8], [0.2, -0.3, 1.0], width=160, height=120)


def test_lamp_lit_room_is_exposed_without_clipping():
    """Auto exposure and the filmic curve: almost no pixel clips to white next to the lamp,
    where clipping the radiance at a brighter exposure clips a sizeable part of the view;
    the median seen pixel lands at mid-grey."""
    house, camera = lamp_lit_room()
    with Renderer(160, 120) as r:
        rgb = r.render(house, camera)
        radiance, seen = r.render_linear(house, camera)
    clipped = (rgb.max(-1) == 255).mean()
    assert clipped < 0.005, clipped
    harsh = tonemap(radiance, seen, exposure=4 * auto_exposure(radiance, seen), tone="clip")
    assert (harsh.max(-1) == 255).mean() > 0.05
    luminance = tonemap(radiance, seen, exposure=auto_exposure(radiance, seen), tone="clip") @ [0.2126, 0.7152, 0.0722]
    assert abs(np.median(luminance[seen]) - 255 * float(linear_to_srgb(KEY))) < 3


def test_auto_exposure_is_invariant_to_scaling_every_light():
    """4× every lamp and the sky (a power of two: the radiance scales exactly): the same bytes
    with auto exposure; a fixed exposure sees the change."""
    house, camera = lamp_lit_room()
    make_instance(house, name="window", category=9, label="window", room_id="r0",
                  vertices=[[-1.99, 1, -1], [-1.99, 2, -1], [-1.99, 2, 1], [-1.99, 1, 1]], faces=[[0, 1, 2], [0, 2, 3]])
    images = {}
    for scale in (1.0, 4.0):
        for exposure in (None, 0.005):
            config = RenderConfig(lamp_power=800.0 * scale, sky_luminance=1000.0 * scale, exposure=exposure)
            with Renderer(160, 120, config=config) as r:
                images[scale, exposure] = r.render(house, camera)
    np.testing.assert_array_equal(images[4.0, None], images[1.0, None])
    assert (images[4.0, 0.005].astype(int) - images[1.0, 0.005]).mean() > 20


def test_tone_curve():
    """ACES maps 0 to 0 and is increasing, white only past ~7.2; the default, soft, is the
    identity up to its knee and rolls off above it with no kink, below 1 for any finite
    value; the sRGB encoding is exact; pixels that see nothing get the background."""
    x = np.linspace(0, 10, 1001)
    y = aces(x)
    assert y[0] == 0 and (np.diff(y[x < 7.0]) > 0).all() and y[x > 7.3].min() == 1.0 and y[x < 7.0].max() < 1.0
    np.testing.assert_allclose(aces(1e-6) / 1e-6, 0.03 / 0.14, rtol=1e-3)
    assert RenderConfig().tone == "soft" and SOFT_KNEE == 0.8
    x = np.concatenate([np.linspace(0, 100, 100_001), [1e3, 1e6]])
    y = soft(x)
    np.testing.assert_array_equal(y[x <= SOFT_KNEE], x[x <= SOFT_KNEE])
    assert (np.diff(y) > 0).all() and y.max() < 1.0 and y[-1] > 0.9999
    slope = np.diff(y) / np.diff(x)
    np.testing.assert_allclose(slope[(x[:-1] > SOFT_KNEE - 0.01) & (x[:-1] < SOFT_KNEE + 0.01)], 1.0, atol=0.2)
    assert 0.95 < soft(2.0) < soft(4.0) < soft(8.0) < 1.0  # highlights graded, not clipped
    radiance = np.array([[[0.5, 0.5, 0.5], [2.0, 0.0, 1.0]]])
    seen = np.array([[True, False]])
    out = tonemap(radiance, seen, exposure=None, background=(0.0, 0.5, 1.0))
    np.testing.assert_array_equal(out[0, 1], [0, 128, 255])
    np.testing.assert_array_equal(out[0, 0], np.round(255 * linear_to_srgb(KEY)))  # mid-grey stays 18 %
    out = tonemap(radiance, seen, exposure=None, tone="aces")
    np.testing.assert_array_equal(out[0, 0], np.round(255 * linear_to_srgb(aces(KEY))))
    with pytest.raises(ValueError, match="unknown tone curve 'gamma'"):
        tonemap(radiance, seen, tone="gamma")
    # the float32 evaluation is the float64 reference's, to a level of rounding
    rng = np.random.default_rng(0)
    radiance = rng.gamma(0.7, 1.0, (200, 300, 3)).astype(np.float32)
    seen = np.ones((200, 300), bool)
    for tone, curve in (("aces", aces), ("clip", lambda v: np.clip(v, 0, 1)), ("soft", soft)):
        fast = tonemap(radiance, seen, exposure=0.8, tone=tone).astype(int)
        reference = np.round(255 * linear_to_srgb(curve(0.8 * radiance.astype(np.float64))))
        assert np.abs(fast - reference).max() <= 1 and (fast == reference).mean() > 0.999


def test_encoding_thresholds_count_to_the_byte():
    """The sRGB encoding as the GPU pass evaluates it, the number of thresholds at or below y,
    is :func:`encode`'s byte: on each side of every threshold and on a million random values."""
    thresholds = encoding_thresholds()
    assert thresholds.dtype == np.float32 and thresholds.shape == (255,) and (np.diff(thresholds) > 0).all()
    near = (thresholds.view(np.uint32)[:, None] + np.arange(-300, 300, dtype=np.int64)).astype(np.uint32).view(np.float32)
    y = np.concatenate([near.ravel(), np.random.default_rng(0).random(1_000_000, dtype=np.float32), [0.0, 1.0]])
    y = y[(y >= 0) & (y <= 1)].astype(np.float32)
    np.testing.assert_array_equal(np.searchsorted(thresholds, y, side="right"), encode(y))


#: (config, antialias) of the GPU tone-mapping check: auto and fixed exposure, each curve
#: (the default, soft; at exposure 0.05 most values lie on its shoulder), a background
#: colour, shadow maps, 4× multisampling
GPU_TONE_CASES = {
    "auto": (RenderConfig(), False),
    "fixed": (RenderConfig(exposure=0.02), False),
    "clip, background": (RenderConfig(tone="clip", background=(0.2, 0.5, 1.0)), False),
    "fixed clip, background": (RenderConfig(exposure=0.01, tone="clip", background=(1.0, 0.25, 0.0)), False),
    "shadows, antialias": (RenderConfig(shadows=True), True),
    "fixed soft, background": (RenderConfig(exposure=0.05, tone="soft", background=(0.0, 0.5, 1.0)), False),
    "aces": (RenderConfig(tone="aces"), False),
    "fixed aces": (RenderConfig(exposure=0.02, tone="aces"), False),
}
#: the most channel values of the GPU pass that may differ (by one level) from numpy's
GPU_TONE_DIFFERING = 1e-3


@pytest.mark.parametrize("case", GPU_TONE_CASES)
def test_gpu_tone_mapping_gives_numpys_bytes(case, toy_houses):
    """``render`` (exposure, tone curve and sRGB encoding in GL passes, bytes read back) is
    ``tonemap(render_linear(...))`` to within a level in at most 0.1 % of the channel values
    (on llvmpipe: none), at an odd width (rows of bytes not a multiple of 4); an exposure
    1 % off would change far more, and ``gpu_tonemap=False`` is numpy's own."""
    config, antialias = GPU_TONE_CASES[case]
    W, H = 161, 121
    diffs, off_by_1_percent = [], []
    with Renderer(W, H, config=config, antialias=antialias) as r, \
            Renderer(W, H, config=config, antialias=antialias, gpu_tonemap=False) as reference:
        for house, _, camera in toy_views(toy_houses):
            camera = camera.resized(W, H)
            rgb = r.render(house, camera)
            radiance, seen = r.render_linear(house, camera)
            expected = tonemap(radiance, seen, exposure=config.exposure, tone=config.tone, background=config.background)
            assert rgb.dtype == np.uint8 and rgb.shape == (H, W, 3) and rgb.flags.c_contiguous
            np.testing.assert_array_equal(reference.render(house, camera), expected)
            diffs.append(np.abs(rgb.astype(int) - expected).ravel())
            exposure = auto_exposure(np.nan_to_num(radiance), seen) if config.exposure is None else config.exposure
            off = tonemap(radiance, seen, exposure=1.01 * exposure, tone=config.tone, background=config.background)
            off_by_1_percent.append((off != expected).ravel())
    diff = np.concatenate(diffs)
    assert diff.max() <= 1, f"{case}: a channel value is {diff.max()} levels off"
    assert (diff > 0).mean() <= GPU_TONE_DIFFERING, f"{case}: {100 * (diff > 0).mean():.3f} % of values differ"
    assert np.concatenate(off_by_1_percent).mean() > 20 * GPU_TONE_DIFFERING


def test_gpu_auto_exposure_falls_back_to_the_mean():
    """Most of the view black (a black slab in front, flat light): the median luminance is 0,
    and the GPU path exposes by the mean of the seen pixels as numpy does (same order, same sum)."""
    house = boxed_room()
    box_instance(house, "slab", 1, (1.6, 3.0, 0.2), (-0.2, 1.5, 0.0)).materials = (Material((0.0, 0.0, 0.0, 1.0)),)
    camera = look_at_camera([0.0, 1.5, -1.2], [0.1, -0.1, 1.0], width=64, height=48)
    with Renderer(64, 48, config=RenderConfig(flat=True)) as r:
        rgb = r.render(house, camera)
        radiance, seen = r.render_linear(house, camera)
    luminance = (radiance @ np.float32([0.2126, 0.7152, 0.0722]))[seen]
    assert np.median(luminance) == 0 < luminance.mean() and seen.all()
    np.testing.assert_array_equal(rgb, tonemap(radiance, seen))
    assert (rgb.max(-1) > 0).mean() > 0.05


def test_a_room_is_lit_by_its_own_lights_only():
    """A lamp of another room, even one standing inside this room's bounds (behind the
    camera), changes no pixel: a room's geometry sees only its own room's lights."""
    house = boxed_room()
    camera = look_at_camera([0, 1.5, -1.0], [0.1, -0.2, 1.0], width=64, height=48)
    with Renderer(64, 48) as r:
        before = r.render(house, camera)
    box_instance(house, "other room's lamp", 35, (0.2, 0.2, 0.2), (0.0, 1.5, -1.8), room_id="r1")
    assert [light.room for light in house_lights(house, RenderConfig())] == ["r0", "r1"]
    with Renderer(64, 48) as r:  # a renderer keeps the scene of a house it has seen
        after = r.render(house, camera)
    assert camera.project([[0.0, 1.5, -1.8]])[1][0] <= 0  # behind the camera: not in the image
    np.testing.assert_array_equal(after, before)


def test_a_room_drawn_twice_looks_as_drawn_once():
    """SUNCG draws some rooms over one another (a storage room over a living room): rooms
    whose bounds are mostly one space share their lights (and indirect light), so the
    coinciding surfaces look alike, not striped by one room's darkness (issue 40). Here
    every surface drawn twice, each room with its own fallback: twice the light, the same
    image (automatic exposure)."""
    from dataclasses import replace

    from sceneforge.render.lights import light_rooms

    house = boxed_room()
    camera = look_at_camera([0, 1.5, -1.0], [0.1, -0.2, 1.0], width=64, height=48)
    with Renderer(64, 48) as r:
        once = r.render(house, camera)
    twice = boxed_room()
    for inst in list(twice.instances):
        twice.instances.append(replace(inst, id=len(twice.instances), room_id="r1"))
    lights = house_lights(twice, RenderConfig())
    assert [(light.room, light.source) for light in lights] == [("r0", "fallback"), ("r1", "fallback")]
    assert light_rooms(twice, lights) == [("r0", "r1"), ("r1", "r0")]
    ambient = room_ambient(twice, RenderConfig())
    np.testing.assert_allclose(ambient["r1"], ambient["r0"])
    np.testing.assert_allclose(ambient["r0"], 2 * room_ambient(house, RenderConfig())["r0"])
    with Renderer(64, 48) as r:
        np.testing.assert_array_equal(r.render(twice, camera), once)


def test_batches_group_faces_by_room_and_material():
    house, box, _ = two_material_box()
    batches = house_batches(house)
    colours = [b.material.base_color for b in batches]
    assert colours == [(0.8, 0.8, 0.8, 1.0), (1.0, 0.0, 0.0, 1.0), (0.0, 0.0, 1.0, 1.0)]
    red, blue = batches[1], batches[2]
    assert len(red.positions) == 3 * (box.face_material == 0).sum()
    assert len(blue.positions) == 3 * (box.face_material == 1).sum()


# --------------------------------------------------------------------------- lifecycle


def test_same_view_same_pixels_across_houses_and_renderers(renderer, toy_houses):
    a, b = toy_houses[:2]
    (_, _, ca), (_, _, cb) = toy_views([a, b], per_house=1)
    first = renderer.render(a, ca)
    other = renderer.render(b, cb)
    assert not np.array_equal(first, other)
    np.testing.assert_array_equal(renderer.render(a, ca), first)  # rebuilt scene, same pixels
    with Renderer(320, 240) as fresh:
        np.testing.assert_array_equal(fresh.render(a, ca), first)
    np.testing.assert_array_equal(renderer.render(a, ca), first)  # closing another renderer left this one working


def test_switching_houses_frees_the_previous_scene(renderer, toy_houses):
    camera = look_at_camera([2.0, 1.5, 2.0], [1.0, -0.2, 0.3])
    renderer.render(toy_houses[0], camera)
    primitives = [p for m in renderer._scene.meshes for p in m.primitives]
    assert primitives and all(p._in_context() for p in primitives)
    renderer.render(toy_houses[0], camera)
    assert all(p._in_context() for p in primitives)  # same house: scene kept
    renderer.render(toy_houses[1], camera)
    assert not any(p._in_context() for p in primitives)


def test_wrong_camera_size_and_closed_renderer():
    house, camera = quad_house(None)
    r = Renderer(32, 24)
    with pytest.raises(ValueError, match="camera is 64×48 but the renderer renders 32×24"):
        r.render(house, camera)
    assert r.render(house, camera.resized(32, 24)).shape == (24, 32, 3)
    r.close()
    r.close()
    with pytest.raises(SceneforgeError, match="closed"):
        r.render(house, camera.resized(32, 24))


def test_unknown_gpu_is_a_one_line_error():
    with pytest.raises(SceneforgeError, match=r"EGL device 99 does not exist; this machine has 0 \(") as e:
        Renderer(8, 8, gpu=99)
    assert "\n" not in str(e.value)


# --------------------------------------------------------------------------- golden image


def compare_golden(rgb: np.ndarray, name: str) -> None:
    """``rgb`` looks like ``tests/golden/<name>`` (tolerance: GL drivers round differently)."""
    path = GOLDEN / name
    if REGEN:
        GOLDEN.mkdir(exist_ok=True)
        Image.fromarray(rgb).save(path, optimize=True)
    golden = np.asarray(Image.open(path).convert("RGB")).astype(int)
    diff = np.abs(rgb.astype(int) - golden).max(-1)
    assert diff.mean() < 1.0 and (diff > 8).mean() < 0.01, \
        f"{name}: mean difference {diff.mean():.2f}, {100 * (diff > 8).mean():.1f} % of pixels off by > 8"


def test_golden_toy_view(toy_houses):
    """A toy-house view looks as it did."""
    camera = look_at_camera([0.4, 1.6, 3.7], [1.0, -0.3, -1.0], width=160, height=120)  # living room corner
    with Renderer(160, 120) as r:
        rgb = r.render(toy_houses[0], camera)
    compare_golden(rgb, "toy_0_000_view.png")


# --------------------------------------------------------------------------- EGL failures

FAIL_SCRIPT = textwrap.dedent("""
    from sceneforge.cli.doctor import check_rendering
    from sceneforge.errors import SceneforgeError
    from sceneforge.render import Renderer
    try:
        Renderer(8, 8)
    except SceneforgeError as e:
        print(f"error: {e}")
    for c in check_rendering(None):
        print(c.status, c.name)
""")

NO_LIBEGL = textwrap.dedent("""
    # libEGL is not installed: neither found nor loadable
    import ctypes, ctypes.util
    _find, _init = ctypes.util.find_library, ctypes.CDLL.__init__
    ctypes.util.find_library = lambda name: None if "EGL" in name else _find(name)
    def _load(self, name, *args, **kwargs):
        if name and "EGL" in str(name):
            raise OSError(f"{name}: cannot open shared object file: No such file or directory")
        _init(self, name, *args, **kwargs)
    ctypes.CDLL.__init__ = _load
""")


@pytest.mark.parametrize("broken, needs", [
    ("libEGL", "needs libEGL"),
    ("EGL vendor", "EGL lists no device) needs an EGL driver"),
    ("Mesa driver", "no OpenGL 4.1 context on EGL device 0, software) needs a working EGL driver"),
])
def test_broken_egl_is_one_line_naming_what_to_install(broken, needs, tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("PYOPENGL_PLATFORM", "EGL_DEVICE_ID")}
    if broken == "libEGL":
        (tmp_path / "sitecustomize.py").write_text(NO_LIBEGL)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp_path), env.get("PYTHONPATH")]))
    elif broken == "EGL vendor":  # libglvnd without any EGL driver
        env["__EGL_VENDOR_LIBRARY_FILENAMES"] = str(tmp_path / "none.json")
    else:  # Mesa's EGL without its DRI drivers
        env["LIBGL_DRIVERS_PATH"] = str(tmp_path)
    res = subprocess.run([sys.executable, "-c", FAIL_SCRIPT], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    errors = [line for line in res.stdout.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and needs in errors[0], res.stdout
    assert "install it with `sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri`" in errors[0]
    assert "Traceback" not in res.stdout + res.stderr
    assert any(line.startswith("FAIL ") for line in res.stdout.splitlines()), res.stdout


def test_doctor_passes_here():
    res = CliRunner().invoke(doctor, [])
    assert res.exit_code == 0, res.output
    for check in ("EGL devices", "OpenGL on EGL device", "one-frame render", "ray tracing", "open3d", "zarr", "torch"):
        assert any(line.startswith("PASS") and check in line for line in res.output.splitlines()), check
    assert "torch CUDA" in res.output


def test_doctor_counts_warnings_apart_from_passes():
    from sceneforge.cli.doctor import Check, summary_line

    assert summary_line([Check("PASS", "a", ""), Check("WARN", "b", "")]) == "2 checks: 1 passed, 1 warning"
    assert summary_line([Check("PASS", "a", ""), Check("FAIL", "b", ""), Check("FAIL", "c", "")]) == \
        "3 checks: 1 passed, 2 failed"
    assert summary_line([Check("PASS", "a", "")]) == "1 check: 1 passed"


def test_pyrender_is_imported_in_one_place_and_headless():
    # pyglet, which pyrender imports for its viewer, loads Xlib unless told it is headless:
    # on a GPU server without X11 libraries `import pyrender` failed
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    imports = [f"{p.relative_to(root)}:{n}" for folder in ("sceneforge", "cli", "benchmarks")
               for p in sorted((root / folder).rglob("*.py"))
               for n, line in enumerate(p.read_text().splitlines(), 1)
               if re.match(r"\s*(import pyrender\b|from pyrender\b)", line)]
    raster = [i for i in imports if i.startswith("sceneforge/render/raster.py")]
    assert len(raster) == 2 and imports == raster, imports  # import_pyrender, and _gl's egl platform after it
    code = ("import sys, click\n"
            "from sceneforge.cli.doctor import doctor\n"
            "try:\n    doctor.main([], standalone_mode=False)\nexcept SystemExit:\n    pass\n"
            "import pyglet\n"
            "print(pyglet.options['headless'], sorted(m for m in sys.modules if m.startswith('pyglet') and ('xlib' in m or 'x11' in m)))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "True []", res.stdout


# ------------------------------------------------------------------ depth pre-pass


@pytest.mark.parametrize("case", GPU_TONE_CASES)
def test_depth_prepass_changes_no_pixel(case, toy_houses):
    """The depth pre-pass (z-buffer first, then each pixel shaded once) gives the radiance
    and the bytes of the single pass, bit for bit, with shadows and multisampling too."""
    config, antialias = GPU_TONE_CASES[case]
    W, H = 161, 121
    with Renderer(W, H, config=config, antialias=antialias) as r, \
            Renderer(W, H, config=config, antialias=antialias) as single:
        r._gl.depth_prepass, single._gl.depth_prepass = True, False
        passes = []
        depth_pass = r._gl._depth_pass
        r._gl._depth_pass = lambda *a: passes.append(1) or depth_pass(*a)
        views = list(toy_views(toy_houses))
        for house, _, camera in views:
            camera = camera.resized(W, H)
            for a, b in zip(r.render_linear(house, camera), single.render_linear(house, camera)):
                np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(r.render(house, camera), single.render(house, camera))
    assert len(passes) == 2 * len(views)


def test_depth_prepass_keeps_the_first_of_coincident_surfaces():
    """Two boxes on the same place, red drawn before green: at equal depth the single pass
    keeps the first fragment (GL_LESS), and so must the pre-pass's shading pass (a stencil;
    with GL_LEQUAL alone the last one drawn would show)."""
    house = boxed_room()
    for name, colour in (("red", (0.8, 0.05, 0.05, 1.0)), ("green", (0.05, 0.8, 0.05, 1.0))):
        box_instance(house, name, 1, (1.0, 1.0, 1.0), (0.0, 0.5, 1.0)).materials = (Material(colour),)
    camera = look_at_camera([0.0, 1.5, -1.2], [0.0, -0.4, 1.0], width=64, height=48)
    out = {}
    for prepass in (False, True):
        with Renderer(64, 48, config=RenderConfig(flat=True)) as r:
            r._gl.depth_prepass = prepass
            out[prepass] = r.render_linear(house, camera)[0]
    box = out[False][..., 0] > 2 * out[False][..., 1]  # red wins in the single pass
    assert box.mean() > 0.05
    np.testing.assert_array_equal(out[True], out[False])


@needs_shared(BREAKFAST_ROOM)
def test_depth_prepass_changes_no_pixel_of_a_real_scene():
    """The breakfast room (1 M triangles, textures, many lights) forced through the pre-pass."""
    house = load(BREAKFAST_ROOM)
    cameras, _ = sample_cameras(house, 2, np.random.default_rng(3), tracer=HouseTracer(house))
    with Renderer(320, 240) as r, Renderer(320, 240) as single:
        r._gl.depth_prepass, single._gl.depth_prepass = True, False
        for camera in cameras:
            np.testing.assert_array_equal(r.render(house, camera), single.render(house, camera))
