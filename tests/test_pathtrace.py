"""Path-traced RGB (``render --rgb pathtraced``, Mitsuba 3): the OpenCV → Mitsuba camera,
pixel alignment with the layers, byte-identical repeats, and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from sceneforge.cameras import Camera, default_intrinsics, pose_from_view
from sceneforge.errors import SceneforgeError
from sceneforge.houses import Material
from sceneforge.layers import frontal_layers
from sceneforge.render import open_renderer

from .conftest import box_instance, box_room

pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install 'sceneforge[pathtrace]')")
pathtrace = pytest.importorskip("sceneforge.render.pathtrace")


@pytest.fixture(scope="module")
def mi():
    try:
        return pathtrace._mitsuba()
    except SceneforgeError as e:
        pytest.skip(str(e))


def red_box_room():
    house = box_room("room", size=4.0, height=3.0)
    box = box_instance(house, "box", 29, (0.6, 0.5, 0.4), (0.31, 0.25, 0.73))
    box.material = Material(base_color=(1.0, 0.0, 0.0, 1.0))
    # an off-centre principal point and an off-grid pose: no edge runs through pixel centres by construction
    K = default_intrinsics(160, 120) + np.array([[0, 0, 7.3], [0, 0, -4.7], [0, 0, 0]])
    return house, box, Camera(K, pose_from_view([-0.93, 1.37, -1.41], [0.55, -0.52, 1.0]), 160, 120)


def test_mitsuba_camera_rays_are_the_layers_rays(mi):
    """The sensor of :func:`mitsuba_sensor` shoots, through each pixel centre, the ray of the
    layers' camera (same direction, starting on it at the near clip plane)."""
    _, _, camera = red_box_room()
    spec = pathtrace.mitsuba_sensor(camera)
    sensor = mi.load_dict({**spec, "to_world": mi.ScalarTransform4f(spec["to_world"].tolist()),
                           "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height}})
    origins, directions, _ = camera.rays()
    for i, j in [(0, 0), (0, 159), (119, 0), (119, 159), (60, 80), (17, 123)]:
        position = mi.Point2f((j + 0.5) / camera.width, (i + 0.5) / camera.height)
        ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5, 0.5))
        k = i * camera.width + j
        np.testing.assert_allclose(np.ravel(ray.d), directions[k], atol=1e-5)
        along = np.ravel(ray.o) - origins[k]
        np.testing.assert_allclose(along, np.dot(along, directions[k]) * directions[k], atol=1e-5)


def test_path_traced_silhouettes_are_on_d1_edges(mi):
    """The red box is red on every pixel D1 gives it and on no other, but for the pixels its
    outline crosses (each pixel integrates its square): those lie on D1's edges."""
    house, box, camera = red_box_room()
    d1 = frontal_layers(house, camera).instance[0] == box.id
    # undenoised: the denoiser's filter mixes neighbouring colours, which this exact test would see
    with open_renderer("pathtraced", 160, 120, samples=8, denoise=False) as r:
        rgb = r.render(house, camera).astype(int)
    # a pure red diffuse surface reflects no green or blue, whatever light it gets; the grey
    # walls always reflect some (even where the box's light tints them)
    red = (rgb[..., 0] > 0) & (rgb[..., 1] == 0) & (rgb[..., 2] == 0)
    edge = ndimage.binary_dilation(d1) & ~ndimage.binary_erosion(d1)
    assert d1.sum() > 500 and edge.sum() < 0.3 * d1.sum()
    assert (red == d1)[~edge].all()
    assert (red != d1).sum() < 0.5 * edge.sum()  # most edge pixels still agree


def test_same_view_path_traced_twice_is_byte_identical(mi):
    # denoised, the default: the denoiser keeps the frames deterministic
    house, _, camera = red_box_room()
    with open_renderer("pathtraced", 160, 120, samples=4, seed=3) as a:
        first = a.render(house, camera)
        assert np.array_equal(a.render(house, camera), first)
    with open_renderer("pathtraced", 160, 120, samples=4, seed=3) as b:
        assert np.array_equal(b.render(house, camera), first)
    with open_renderer("pathtraced", 160, 120, samples=4, seed=4) as c:
        assert not np.array_equal(c.render(house, camera), first)  # the seed matters


def test_non_square_pixels_are_a_one_line_error(mi):
    house, _, camera = red_box_room()
    K = camera.K.copy()
    K[1, 1] *= 1.1
    with open_renderer("pathtraced", 160, 120, samples=1) as r, \
            pytest.raises(SceneforgeError, match="square pixels and no skew") as e:
        r.render(house, Camera(K, camera.cam_to_world, 160, 120))
    assert "\n" not in str(e.value)


#: a camera line as PBRS's room_camera.txt files give it: half-FOVs to 6 decimals, so fx and fy
#: at 320×240 differ by 3.3e-7 of fx
PBRS_LINE = "-0.62 1.5 -1.13  0.48 -0.196116 0.855  0 0.980581 0.196116  0.5534 0.433896 0.83"


def test_pbrs_camera_at_320x240_path_traces(mi):
    """A PBRS camera path-traces at 320×240: its fx and fy are not equal (the file's rounding),
    the sensor shoots the layers' rays through the pixel centres to within the rounding, and
    the frame shows the box on exactly D1's pixels away from its outline."""
    from sceneforge.cameras import camera_from_pbrs

    house, box, _ = red_box_room()
    camera = camera_from_pbrs(PBRS_LINE, width=320, height=240)
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    assert fx != fy and abs(fx - fy) / fx == pytest.approx(3.3e-7, rel=0.05)
    spec = pathtrace.mitsuba_sensor(camera)
    sensor = mi.load_dict({**spec, "to_world": mi.ScalarTransform4f(spec["to_world"].tolist()),
                           "film": {"type": "hdrfilm", "width": 320, "height": 240}})
    _, directions, _ = camera.rays()
    for i, j in [(0, 0), (0, 319), (239, 0), (239, 319), (120, 160)]:
        position = mi.Point2f((j + 0.5) / 320, (i + 0.5) / 240)
        ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5, 0.5))
        # 1e-5 rad is 0.003 px at 259 px focal length
        np.testing.assert_allclose(np.ravel(ray.d), directions[i * 320 + j], atol=1e-5)
    d1 = frontal_layers(house, camera).instance[0] == box.id
    with open_renderer("pathtraced", 320, 240, samples=8, denoise=False) as r:
        rgb = r.render(house, camera).astype(int)
    red = (rgb[..., 0] > 0) & (rgb[..., 1] == 0) & (rgb[..., 2] == 0)
    edge = ndimage.binary_dilation(d1) & ~ndimage.binary_erosion(d1)
    assert d1.sum() > 1000
    assert (red == d1)[~edge].all()


def test_square_pixel_tolerance_is_the_files_rounding_not_more(mi):
    """fy off by 1e-4 of fx (10× what the tolerance allows) is still refused."""
    from sceneforge.cameras import camera_from_pbrs

    house, _, _ = red_box_room()
    camera = camera_from_pbrs(PBRS_LINE, width=320, height=240)
    K = camera.K.copy()
    K[1, 1] = K[0, 0] * (1 + 1e-4)
    with pytest.raises(SceneforgeError, match="square pixels and no skew"):
        pathtrace.mitsuba_sensor(Camera(K, camera.cam_to_world, 320, 240))


def test_unknown_mode_is_refused():
    with pytest.raises(ValueError, match="unknown RGB mode 'photo'; expected one of raster, pathtraced"):
        open_renderer("photo", 8, 8)


def test_store_records_the_rgb_mode(mi, tmp_path):
    """``render --rgb pathtraced`` writes path-traced RGB, and the store's saved config says so."""
    from click.testing import CliRunner
    from sceneforge.cli.main import cli

    from sceneforge.store import open_store

    out = tmp_path / "pt.zarr"
    res = CliRunner().invoke(cli, ["render", "bundled:toy", str(out), "--resolution", "32x24", "--views-per-house", "1",
                                   "--overhead-resolution", "16", "--rgb", "pathtraced", "--rgb-samples", "2"])
    assert res.exit_code == 0, res.output
    store = open_store(str(out))
    assert store.attrs["config"]["rgb"] | {"lighting": None} == {
        "enabled": True, "mode": "pathtraced", "antialias": False, "samples": 2, "denoise": True, "lighting": None}
    assert store.config.rgb.mode == "pathtraced"
    assert np.asarray(store.view(0)["rgb"]).std() > 5


def lamp_and_window_room(window: bool):
    """The box room with a floor lamp and a table (and a window on the left wall), seen towards the lamp."""
    from sceneforge.cameras import look_at_camera
    from sceneforge.houses import make_instance

    house = box_room("room", size=4.0, height=3.0)
    box_instance(house, "lamp", 35, (0.3, 1.2, 0.3), (1.2, 0.6, 1.2))
    box_instance(house, "table", 7, (1.0, 0.7, 0.6), (-0.5, 0.35, 0.3))
    if window:
        make_instance(house, name="window", category=9, label="window", room_id="r0",
                      vertices=[[-1.99, 1, -1], [-1.99, 2, -1], [-1.99, 2, 1], [-1.99, 1, 1]],
                      faces=[[0, 1, 2], [0, 2, 3]])
    return house, look_at_camera([0.3, 1.5, -1.8], [-0.2, -0.3, 1.0], width=80, height=60)


def test_lamp_lit_room_is_exposed_without_clipping(mi):
    """The shared exposure and tone curve: next to the lamp almost nothing clips to white."""
    house, camera = lamp_and_window_room(window=False)
    with open_renderer("pathtraced", 80, 60, samples=8) as r:
        rgb = r.render(house, camera)
    assert (rgb.max(-1) == 255).mean() < 0.005
    assert 90 < np.median(rgb) < 170


def test_auto_exposure_is_invariant_to_scaling_every_light_path_traced(mi):
    """4× every lamp and the sky: the same image with auto exposure (to a level of rounding:
    the path tracer's float32 sums), a brighter one at a fixed exposure."""
    from sceneforge.render import RenderConfig

    house, camera = lamp_and_window_room(window=True)
    images = {}
    for scale in (1.0, 4.0):
        for exposure in (None, 0.005):
            config = RenderConfig(lamp_power=800.0 * scale, sky_luminance=1000.0 * scale, exposure=exposure)
            with open_renderer("pathtraced", 80, 60, samples=4, config=config) as r:
                images[scale, exposure] = r.render(house, camera).astype(int)
    assert np.abs(images[4.0, None] - images[1.0, None]).max() <= 1
    assert (images[4.0, 0.005] - images[1.0, 0.005]).mean() > 20


def test_window_is_an_area_light_of_the_sky(mi):
    """A room with a window and no lamp: no fallback light, the window's pixels show the
    sky's radiance exactly, and the room is lit."""
    from sceneforge.render import RenderConfig, house_lights

    house, camera = lamp_and_window_room(window=True)
    house.instances = [i for i in house.instances if i.name != "lamp"]
    config = RenderConfig(sky_luminance=700.0)
    assert [light.source for light in house_lights(house, config)] == ["window"]
    camera = camera.__class__(camera.K, pose_from_view([0.5, 1.5, 0.0], [-1.0, 0.0, 0.0]), 80, 60)
    with open_renderer("pathtraced", 80, 60, samples=4, config=config, denoise=False) as r:
        radiance, seen = r.render_linear(house, camera)
    centre = radiance[28:32, 38:42]
    daylight = np.asarray(house_lights(house, config)[0].colour)  # the outdoors' mean colour
    np.testing.assert_allclose(centre, np.broadcast_to(700.0 * daylight, centre.shape), rtol=1e-5)  # every sample sees the emitter
    assert seen.all() and (radiance[55:] > 0).all()  # the floor is lit


def test_the_outdoors_lights_the_room_through_a_windows_glass(mi):
    """A window with glass (SUNCG's: a face group of opacity < 1): its glass is left out and
    the outdoors' dome (``render.sky``) shows through it and lights the room, as in the
    raster mode; the window is no emitter panel then."""
    from sceneforge.houses import make_instance
    from sceneforge.render import RenderConfig, sky

    house, camera = lamp_and_window_room(window=False)
    house.instances = [i for i in house.instances if i.name != "lamp" and not i.name.startswith("wall")]
    window = make_instance(house, name="window", category=9, label="window", room_id="r0",
                           vertices=[[-2.0, 0.5, -1], [-2.0, 0.5, 1], [-2.0, 2.5, 1], [-2.0, 2.5, -1]],
                           faces=[[0, 1, 2], [0, 2, 3]], material=Material((0.4, 0.55, 0.64, 0.5)))
    camera = camera.__class__(camera.K, pose_from_view([0.5, 1.5, 0.0], [-1.0, 0.0, 0.0]), 80, 60)
    config = RenderConfig(sky_luminance=700.0)
    with open_renderer("pathtraced", 80, 60, samples=4, config=config, denoise=False) as r:
        radiance, seen = r.render_linear(house, camera)
        scene = r._scene
    assert "sky" in {s.id() for s in scene.shapes()} and window.id is not None
    origins, directions, _ = camera.rays()
    expected = sky.radiance(directions.reshape(60, 80, 3)[28:32, 38:42]) * 700.0 * config.outdoors_seen
    np.testing.assert_allclose(radiance[28:32, 38:42], expected, rtol=0.1)  # through the glass
    assert seen.all() and (radiance[55:] > 0).all()  # the floor is lit


# ---- denoising (render/denoise.py) ------------------------------------------------------------


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float64 Rec. 709 luminance of an (H, W, 3) uint8 sRGB image, 0..255."""
    return rgb.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def wall_noise(rgb: np.ndarray, region) -> float:
    """median |Y - 5x5 median(Y)| over ``region`` (the issue's wall-noise measure, 0..255)."""
    y = luminance(rgb)
    return float(np.median(np.abs(y - ndimage.median_filter(y, size=5))[region]))


def edge_contrast(rgb: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(mean |ΔY| across the edges of ``mask``, mean |ΔY| of the pixel pairs 1 px off them, inside
    and outside), over horizontal and vertical neighbour pairs."""
    y = luminance(rgb)
    on, off = [], []
    for axis in (0, 1):
        a, b = np.moveaxis(mask, axis, 0), np.moveaxis(y, axis, 0)
        across = a[1:-2] != a[2:-1]  # pair (k, k+1) straddles the edge, for k = 1 .. n-3
        k = np.nonzero(across)
        on.append(np.abs(b[1:-2] - b[2:-1])[k])
        # the pairs one pixel off: (k-1, k) and (k+1, k+2), each wholly on one side
        off.append(np.abs(b[0:-3] - b[1:-2])[k])
        off.append(np.abs(b[2:-1] - b[3:])[k])
    return float(np.concatenate(on).mean()), float(np.concatenate(off).mean())


def test_denoiser_lowers_noise_on_a_flat_lit_wall(mi):
    """Facing one wall of the box room at 8 spp: the wall noise falls by at least 3x."""
    house = box_room("room", size=4.0, height=3.0)
    camera = Camera(default_intrinsics(80, 60), pose_from_view([0.0, 1.5, -1.0], [0.0, 0.0, 1.0]), 80, 60)
    wall = np.abs(frontal_layers(house, camera).depth[4] - 3.0) < 1e-6  # the wall 3 m ahead, square on
    region = ndimage.binary_erosion(wall, iterations=3)
    assert region.sum() > 1000
    frames = {}
    for denoise in (False, True):
        with open_renderer("pathtraced", 80, 60, samples=8, denoise=denoise) as r:
            frames[denoise] = r.render(house, camera)
    noisy, clean = wall_noise(frames[False], region), wall_noise(frames[True], region)
    assert noisy > 2 and clean < noisy / 3, (noisy, clean)


def test_grain_keeps_a_fraction_of_the_samples_noise(mi):
    """``RenderConfig.grain``: denoised + grain × (raw − denoised), so 1 is the raw frame and
    0 the denoised one; the default 5 % leaves a little grain (PBRS's renders show theirs)."""
    from sceneforge.render import RenderConfig

    house = box_room("room", size=4.0, height=3.0)
    camera = Camera(default_intrinsics(80, 60), pose_from_view([0.0, 1.5, -1.0], [0.0, 0.0, 1.0]), 80, 60)
    with open_renderer("pathtraced", 80, 60, samples=8, denoise=False) as r:
        raw, _ = r.render_linear(house, camera)
    frames = {}
    for grain in (0.0, 0.05, 1.0):
        with open_renderer("pathtraced", 80, 60, samples=8, config=RenderConfig(grain=grain)) as r:
            frames[grain], _ = r.render_linear(house, camera)
    np.testing.assert_allclose(frames[1.0], raw, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(frames[0.05], frames[0.0] + 0.05 * (raw - frames[0.0]), rtol=1e-9, atol=1e-9)
    assert RenderConfig().grain == 0.05
    with pytest.raises(ValueError, match="grain"):
        RenderConfig(grain=1.5)


def test_denoiser_keeps_label_edges_where_they_are(mi):
    """On the red box's D1 outline, the luminance step across the edge stays at least 1.5x
    the steps one pixel off it: the denoiser does not blur or move the edge."""
    house, box, camera = red_box_room()
    d1 = frontal_layers(house, camera).instance[0] == box.id
    with open_renderer("pathtraced", 160, 120, samples=8) as r:
        rgb = r.render(house, camera)
    on, off = edge_contrast(rgb, d1)
    assert on >= 1.5 * off, (on, off)
