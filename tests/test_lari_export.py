"""Readers for other methods on a tiny store rendered with ``--intersections``: ``export
--format lari`` opens as LaRI's ScanNet++ loader opens its data and unprojects to the
store's surfaces, and the training dataset yields the K layers as tensors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image
from sceneforge.cli.main import cli

from sceneforge.depth_mesh import perspective_points
from sceneforge.errors import SceneforgeError
from sceneforge.learn.split import SPLITS, default_split_file
from sceneforge.store import open_store

#: K of the test store
LAYERS = 4
#: the sample fields of the intersection layers
FIELDS = ("intersections", "intersection_labels", "intersection_normal", "intersection_front_facing")


def run(*args):
    return CliRunner().invoke(cli, list(map(str, args)))


def render(out: Path, intersections: int) -> Path:
    from sceneforge.config import load_config
    from sceneforge.houses import BUNDLED_TOY
    from sceneforge.pipeline import render_dataset

    config = load_config(None, {"width": 40, "height": 30, "views_per_house": 1,
                                "view": {"overhead": {"resolution": 16}, "layers": {"intersections": intersections}}})
    render_dataset(BUNDLED_TOY, str(out), config)
    return out


@pytest.fixture(scope="module")
def layered(tmp_path_factory) -> Path:
    """The bundled toy houses at 40×30, one view each, RGB and K = :data:`LAYERS` layers."""
    pytest.importorskip("pyrender", reason="the render extra (pyrender) is not installed")
    return render(tmp_path_factory.mktemp("layered") / "toy.zarr", LAYERS)


@pytest.fixture
def store(layered, tmp_path) -> Path:
    """A copy of :func:`layered`, so that a test may put a split file beside it."""
    return Path(shutil.copytree(layered, tmp_path / "toy.zarr"))


def exported(store: Path, out: Path, *flags) -> str:
    res = run("export", store, out, "--format", "lari", *flags)
    assert res.exit_code == 0, res.output
    return res.output.strip()


# ------------------------------------------------------------------ LaRI's reading code
# copied from LaRI (github.com/ruili3/lari), src/utils/geometry.py: ldi_to_pts3d and
# depthmap_to_camera_coordinates (pixel centres at integer coordinates, valid where depth > 0)

def ldi_to_pts3d(ldi, camera_intrinsics):
    n_layers = ldi.shape[-1]
    pts3d = []
    mask = []
    for ll in range(n_layers):
        depth = ldi[:, :, ll]
        pts3d_l, mask_l = depthmap_to_camera_coordinates(depth, camera_intrinsics)
        pts3d.append(pts3d_l)
        mask.append(mask_l)
    pts3d = np.stack(pts3d, axis=-2)  # H W n_layer 3
    mask = np.stack(mask, axis=-1)  # H W n_layer
    return pts3d, mask


def depthmap_to_camera_coordinates(depthmap, camera_intrinsics):
    camera_intrinsics = np.float32(camera_intrinsics)
    H, W = depthmap.shape
    assert camera_intrinsics[0, 1] == 0.0
    assert camera_intrinsics[1, 0] == 0.0
    fu = camera_intrinsics[0, 0]
    fv = camera_intrinsics[1, 1]
    cu = camera_intrinsics[0, 2]
    cv = camera_intrinsics[1, 2]
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    z_cam = depthmap
    x_cam = (u - cu) * z_cam / fu
    y_cam = (v - cv) * z_cam / fv
    X_cam = np.stack((x_cam, y_cam, z_cam), axis=-1).astype(np.float32)
    valid_mask = (depthmap > 0.0)
    return X_cam, valid_mask


def lari_reads(data_path: Path, entry: str, n_ldi_layers: int):
    """One list entry read as LaRI's ``ScanNetPP._get_image_and_ldi`` reads it
    (src/datasets/scannetpp.py), then cast as ``BaseDataset.__getitem__`` casts it."""
    obj_path, img_id = entry.split(" ")
    img = Image.open(data_path / obj_path / "dslr/downscaled_undistorted_images" / f"{img_id}.JPG").convert("RGB")
    ldi = np.load(data_path / obj_path / "dslr/ldi" / f"{img_id}_ldi.npz")["ldi"][:, :, :n_ldi_layers]
    intrinsics = np.load(data_path / obj_path / "dslr/ldi" / f"{img_id}.npz")["K"]
    intrinsics_4x4 = np.zeros((4, 4)).astype(np.float32)
    intrinsics_4x4[:3, :3] = intrinsics
    intrinsics_4x4[3, 3] = 1.0
    return img, ldi.astype(np.float32), intrinsics_4x4


# ------------------------------------------------------------------------- LaRI export


def test_lari_export_opens_with_their_documented_keys_and_shapes(store, tmp_path):
    out = tmp_path / "lari"
    assert exported(store, out) == f"3 views written to {out}; lists lari_all.json (no split file)"
    s = open_store(str(store))
    entries = json.loads((out / "lari_all.json").read_text())
    assert entries == [f"{s.view(i)['house_id']} view_{i:06d}" for i in range(len(s))]
    for i, entry in enumerate(entries):
        v = s.view(i)
        H, W = v["rgb"].shape[:2]
        img, ldi, K4 = lari_reads(out, entry, LAYERS)
        assert img.size == (W, H) and ldi.shape == (H, W, LAYERS)
        # the npz holds their key as they save it, fp16 and -1 past the last surface
        saved = np.load(out / entry.split()[0] / "dslr/ldi" / f"view_{i:06d}_ldi.npz")
        assert saved["ldi"].dtype == np.float16 and set(np.unique(saved["ldi"][saved["ldi"] <= 0])) <= {-1}
        # their unprojection of the exported layers is the store's layers unprojected
        pts3d, mask = ldi_to_pts3d(ldi, K4[:3, :3])
        depth = v["intersections/depth"]  # (L, H, W)
        assert np.array_equal(mask, np.isfinite(depth).transpose(1, 2, 0))
        ours = np.stack([perspective_points(d, v["K"], np.eye(4)) for d in depth], axis=2)  # (H, W, L, 3)
        np.testing.assert_allclose(pts3d[mask], ours[mask], rtol=np.finfo(np.float16).eps, atol=1e-6)
        # the image is the store's RGB (JPEG)
        assert np.abs(np.asarray(img, dtype=float) - v["rgb"]).mean() < 4
        # sceneforge's labels beside their key, the layer axis after the pixels as in ldi
        assert set(saved.files) == {"ldi", "normal", "instance", "category", "front_facing"}
        for key in ("instance", "category", "front_facing"):
            assert np.array_equal(saved[key], v[f"intersections/{key}"].transpose(1, 2, 0)), key
        np.testing.assert_allclose(saved["normal"], v["intersections/normal"].transpose(2, 3, 0, 1),
                                   atol=1e-3, equal_nan=True)
        camera = np.load(out / entry.split()[0] / "dslr/ldi" / f"view_{i:06d}.npz")
        assert set(camera.files) == {"K", "Tr_w2c_cv"}
        np.testing.assert_allclose(camera["Tr_w2c_cv"] @ v["cam_to_world"], np.eye(4), atol=1e-5)


def test_lari_lists_follow_the_house_split_beside_the_store(store, tmp_path):
    s = open_store(str(store))
    houses = sorted({str(h) for h in s.array("house_id")[:]})
    split = {"train": houses[:2], "val": [], "test": houses[2:]}
    Path(default_split_file([str(store)])).write_text(json.dumps(
        {"version": 1, "val_fraction": 0.0, "test_fraction": 0.3, "seed": 0, "stores": [str(store)], **split}))
    out = tmp_path / "lari"
    assert "; lists lari_train.json, lari_val.json, lari_test.json (split " in exported(store, out)
    assert sorted(p.name for p in out.glob("*.json")) == sorted(f"lari_{name}.json" for name in SPLITS)
    for name in SPLITS:
        entries = json.loads((out / f"lari_{name}.json").read_text())
        assert sorted(e.split()[0] for e in entries) == split[name]


def test_a_store_without_intersection_layers_is_refused_naming_the_fix(tiny_toy_store, tmp_path):
    res = run("export", tiny_toy_store, tmp_path / "lari", "--format", "lari")
    assert res.exit_code == 1, res.output
    assert res.output.startswith("error: ") and len(res.output.strip().splitlines()) == 1
    assert "render it with --intersections K" in res.output
    assert not (tmp_path / "lari").exists()


def test_export_over_a_lari_export_needs_overwrite_and_never_takes_other_files(store, tmp_path):
    out = tmp_path / "lari"
    exported(store, out)
    res = run("export", store, out, "--format", "lari")
    assert res.exit_code == 1 and "holds an earlier export (10 files); pass --overwrite" in res.output
    # an EXR export over it replaces all of it: the folder never mixes two exports
    res = run("export", store, out, "--overwrite")
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == [f"view_{i:06d}.exr" for i in range(3)]
    exported(store, out, "--overwrite")
    house = next(p for p in out.iterdir() if p.is_dir())
    (house / "dslr" / "notes.txt").write_text("mine")
    res = run("export", store, out, "--format", "lari", "--overwrite")
    assert res.exit_code == 1 and f"holds files export did not write: {house.name}/;" in res.output
    assert (house / "dslr" / "notes.txt").read_text() == "mine"


# ------------------------------------------------------------------- training samples


def test_dataset_yields_the_intersection_layers_as_tensors(layered, tmp_path, one_torch_thread):
    torch = pytest.importorskip("torch")
    from sceneforge.learn.dataset import StoreDataset, index_stores

    s = open_store(str(layered))
    ds = StoreDataset(index_stores([str(layered)]), ("rgb", *FIELDS))
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=3)))
    H, W = s.array("depth").shape[2:]
    shapes = {"intersection_depth": ((3, LAYERS, H, W), torch.float32),
              "intersection_valid": ((3, LAYERS, H, W), torch.bool),
              "intersection_instance": ((3, LAYERS, H, W), torch.int64),
              "intersection_category": ((3, LAYERS, H, W), torch.int64),
              "intersection_normal": ((3, LAYERS, 3, H, W), torch.float32),
              "intersection_front_facing": ((3, LAYERS, H, W), torch.bool)}
    for key, (shape, dtype) in shapes.items():
        assert (tuple(batch[key].shape), batch[key].dtype) == (shape, dtype), key
    depth = s.array("intersections/depth")[:]
    np.testing.assert_array_equal(batch["intersection_depth"].numpy(), depth)  # NaN kept
    assert np.array_equal(batch["intersection_valid"].numpy(), np.isfinite(depth))
    assert batch["intersection_valid"][:, 0].any() and not batch["intersection_valid"].all()
    for key in ("instance", "category", "front_facing"):
        assert np.array_equal(batch[f"intersection_{key}"].numpy(), s.array(f"intersections/{key}")[:]), key

    plain = render(tmp_path / "plain.zarr", 0)
    with pytest.raises(SceneforgeError, match="has no intersections/depth, .* render it with --intersections K"):
        StoreDataset(index_stores([str(plain)]), ("rgb", "intersections"))[0]
