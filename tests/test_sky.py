"""The outdoors (``sceneforge.render.sky``) and the raster mode's indirect light from a room's
mean albedo (``lights.room_albedo`` / ``room_ambient``), issue 40."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from sceneforge.houses import Material
from sceneforge.render import RenderConfig, sky
from sceneforge.render.lights import MAX_ALBEDO, house_lights, mean_texel, room_albedo, room_ambient

from .conftest import box_instance, box_room

Y = np.array([0.2126, 0.7152, 0.0722])


def test_window_light_is_daylight_of_luminance_one():
    colour = sky.window_colour()
    assert colour @ Y == pytest.approx(1.0)
    assert colour[2] > colour[1] > colour[0]  # bluer than the lamps' white
    # the cosine-weighted mean over a window's outward hemisphere: half sky, half ground
    n = 400
    mu = (np.arange(n) + 0.5) / n
    up = sky.radiance(np.stack([np.sqrt(1 - mu ** 2), mu, np.zeros(n)], -1))
    down = sky.radiance([0.0, -1.0, 0.0])
    # a vertical window: cos-weighted mean of the upper quarter-sphere ~ mean over elevation
    assert (0.5 * up.mean(0) + 0.5 * down) @ Y == pytest.approx(1.0, rel=0.15)


def test_sky_grades_to_a_blue_zenith_over_a_darker_ground():
    horizon, zenith, ground = sky.radiance([[1, 1e-3, 0], [0, 1, 0], [0, -1, 0]])
    chroma = lambda c: c[2] / c.sum()  # noqa: E731
    assert chroma(zenith) > chroma(horizon) and horizon @ Y > zenith @ Y > ground @ Y > 0
    assert ground[1] > ground[2] * 0.9  # sunlit grass and paving: not sky blue
    np.testing.assert_allclose(sky.radiance([[0, 1, 0], [3, 0.5, 4]])[0], zenith)  # any length


def test_dome_and_latlong_show_the_same_outdoors():
    v, f, c = sky.dome([1.0, 2.0, 3.0], 50.0, rings=8, segments=12)
    assert v.shape == (2 * 9 * 12, 3) and f.shape == (2 * 2 * 8 * 12, 3) and c.shape == v.shape
    np.testing.assert_allclose(np.linalg.norm(v - [1, 2, 3], axis=1), 50.0)
    up = v[:, 1] > 2.0 + 1e-9
    np.testing.assert_allclose(c[up], sky.radiance(v[up] - [1, 2, 3]))
    # the horizon twice: the sky's colour on the upper ring, the ground's on the lower
    horizon = np.abs(v[:, 1] - 2.0) < 1e-9
    assert horizon.sum() == 24
    np.testing.assert_allclose(np.unique(c[horizon] @ Y), sorted([sky.radiance([0, -1, 0]) @ Y,
                                                                  sky.radiance([1, 0, 0]) @ Y]))
    image = sky.latlong(16, 8)
    assert image.shape == (8, 16, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image[0, 0], sky.radiance([np.sin(np.pi / 16), np.cos(np.pi / 16), 0]), rtol=1e-6)
    assert image[-1, 0] @ Y < image[3, 0] @ Y  # the ground below the horizon is darker


def test_room_albedo_weighs_materials_by_area_and_decodes_textures(tmp_path):
    house = box_room("a", size=4.0, height=3.0)
    for inst in house.instances:
        inst.materials = (Material((0.5, 0.5, 0.5, 1.0)),)
    assert room_albedo(house)["r0"] == pytest.approx(0.5)
    Image.fromarray(np.full((2, 2, 3), 188, np.uint8)).save(tmp_path / "t.png")  # sRGB 188: linear 0.5
    np.testing.assert_allclose(mean_texel(tmp_path / "t.png"), 0.5, atol=4e-3)
    box = box_instance(house, "table", 7, (1.0, 1.0, 1.0), (0.0, 0.5, 0.0))
    box.materials = (Material((1.0, 1.0, 1.0, 1.0), texture=tmp_path / "t.png"),)
    box.uv = np.zeros((len(box.vertices), 2), np.float32)
    assert room_albedo(house)["r0"] == pytest.approx(0.5, abs=4e-3)
    box.uv = None  # a texture without uv counts as its base colour
    assert room_albedo(house)["r0"] > 0.5


def test_indirect_light_grows_with_the_rooms_albedo():
    """ambient × Φ / A × ρ / (1 − ρ): a white room gets much more indirect light than a grey
    one (at most ρ = MAX_ALBEDO); its colour is that of the lights."""
    config = RenderConfig()
    levels = {}
    for grey in (0.3, 0.6, 1.0):
        house = box_room("a", size=4.0, height=3.0)
        for inst in house.instances:
            inst.materials = (Material((grey, grey, grey, 1.0)),)
        (light,) = house_lights(house, config)
        ambient = room_ambient(house, config)["r0"]
        rho = min(grey, MAX_ALBEDO)
        size = np.ptp(np.concatenate([i.vertices for i in house.instances]), axis=0)
        area = 2 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
        np.testing.assert_allclose(ambient, [light.flux / area * rho / (1 - rho)] * 3)
        levels[grey] = ambient[0]
    assert levels[0.3] < levels[0.6] < levels[1.0]


def _glazed_window_house():
    """A floor and a window at z = 2 facing -z, its frame (opaque) under its pane (glass,
    d = 0.5), nothing else; a camera facing it; the (H, W) pixels that see the pane."""
    from sceneforge.cameras import look_at_camera
    from sceneforge.houses import House, Room, make_instance
    from sceneforge.render.lights import glazed_windows

    house = House(id="glazed", instances=[], rooms=[Room("a", "room", 0)])
    make_instance(house, name="floor", category=2, label="floor", room_id="a",
                  vertices=[[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], faces=[[0, 2, 1], [0, 3, 2]],
                  material=Material((0.5, 0.5, 0.5, 1.0)))
    window = make_instance(
        house, name="window", category=9, label="window", room_id="a",
        vertices=[[-1, 0.5, 2], [1, 0.5, 2], [1, 0.8, 2], [-1, 0.8, 2], [1, 2.5, 2], [-1, 2.5, 2]],
        faces=[[0, 1, 2], [0, 2, 3], [3, 2, 4], [3, 4, 5]],
        material=(Material((0.6, 0.6, 0.6, 1.0)), Material((0.4, 0.55, 0.64, 0.5))),
        face_material=np.array([0, 0, 1, 1], np.int32))
    assert glazed_windows(house) == {window.id}
    camera = look_at_camera([0, 1.5, -1.5], [0, 0.05, 1], width=64, height=48)
    origins, directions, _ = camera.rays()
    hit = origins + ((2.0 - origins[:, 2]) / directions[:, 2])[:, None] * directions
    pane = ((hit[:, 1] > 0.85) & (hit[:, 1] < 2.45) & (np.abs(hit[:, 0]) < 0.95)).reshape(48, 64)
    return house, camera, pane


def test_the_outdoors_shows_through_a_windows_glass():
    """A window with glass (a face group of opacity < 1, as SUNCG's window models have):
    the raster mode draws its frame lit like any surface and, through the glass, the
    outdoors (the dome of :func:`sky.dome`: the sky's radiance × ``sky_luminance`` along
    each ray, × ``outdoors_seen``); the window still lights the room. The layers see the
    glass as before."""
    pytest.importorskip("pyrender")
    from sceneforge.render import Renderer

    house, camera, pane = _glazed_window_house()
    config = RenderConfig(sky_luminance=900.0, outdoors_seen=1.0)
    with Renderer(64, 48, config=config) as r:
        radiance, seen = r.render_linear(house, camera)
    origins, directions, _ = camera.rays()
    hit = origins + ((2.0 - origins[:, 2]) / directions[:, 2])[:, None] * directions
    frame = ((hit[:, 1] > 0.55) & (hit[:, 1] < 0.75) & (np.abs(hit[:, 0]) < 0.95)).reshape(seen.shape)
    assert pane.sum() > 100 and frame.sum() > 20 and seen[pane].all()
    expected = sky.radiance(directions.reshape(seen.shape + (3,))[pane]) * 900.0
    np.testing.assert_allclose(radiance[pane], expected, rtol=0.1)  # per-vertex colours of the dome
    assert (radiance[frame] @ Y).max() < 0.2 * (expected @ Y).min()  # the frame is lit, not a panel
    (light,) = house_lights(house, config)
    assert light.source == "window"  # the daylight still comes in


@pytest.mark.parametrize("mode", ["raster", "pathtraced"])
def test_the_outdoors_is_seen_dimmed_and_lights_the_room_undimmed(mode):
    """``outdoors_seen`` scales the outdoors where the camera sees it through glass, and
    nothing else: every pixel that sees the dome is that fraction of itself at 1, every
    pixel that sees the room (lit through the same window) is unchanged to the bit; in the
    path tracer only the pixels the glass's edge crosses lie between the two (antialiased)."""
    mode == "raster" and pytest.importorskip("pyrender")
    mode == "pathtraced" and pytest.importorskip("mitsuba")
    from sceneforge.render import open_renderer

    house, camera, pane = _glazed_window_house()
    options = {"samples": 4, "denoise": False} if mode == "pathtraced" else {}
    radiance = {}
    for seen in (1.0, 0.1):
        with open_renderer(mode, 64, 48, config=RenderConfig(sky_luminance=900.0, outdoors_seen=seen),
                           **options) as r:
            radiance[seen] = r.render_linear(house, camera)[0] @ Y
    ratio = radiance[0.1] / radiance[1.0]
    sky_seen, room = np.isclose(ratio, 0.1, rtol=1e-5), ratio == 1.0
    assert sky_seen[pane].all() and room.sum() > 100  # the floor and the frame
    edge = ~(sky_seen | room)
    assert not edge.any() if mode == "raster" else edge.sum() < 0.05 * edge.size
    assert ((ratio[edge] > 0.1) & (ratio[edge] < 1.0)).all()


def test_zbuffer_depth_sees_a_windows_glass():
    """``Renderer.depth`` (the z-buffer) sees a glazed window's glass as the layers do, not
    the outdoors' dome behind it that the RGB shows through the glass; and the RGB after it
    is the RGB before it."""
    pytest.importorskip("pyrender")
    from sceneforge.layers import frontal_layers
    from sceneforge.render import Renderer

    house, camera, pane = _glazed_window_house()
    with Renderer(64, 48, config=RenderConfig(sky_luminance=900.0)) as r:
        before = r.render_linear(house, camera)
        depth = r.depth(house, camera)
        after = r.render_linear(house, camera)
    traced = frontal_layers(house, camera).traditional_depth
    assert pane.sum() > 100 and np.isfinite(traced[pane]).all()
    assert np.isnan(traced).any() and (np.isnan(depth) == np.isnan(traced)).all()  # no dome
    seen = np.isfinite(traced)
    assert (np.abs(depth[seen] - traced[seen]) < 1e-3).all()
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a, b)
    assert before[1][pane].all() and before[1].all()  # the RGB sees the dome everywhere
