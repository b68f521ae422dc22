"""Picture of a PLY mesh written by ``sceneforge reconstruct``, rendered offscreen (pyrender, EGL).

The mesh is in the photo camera's gravity-aligned frame (+Y up, +Z the flattened view
direction, camera at the origin); the picture looks at it from above and behind the photo's
camera, faces coloured by height, the photo's camera a red dot.

    python scripts/render_mesh.py recon/toy_0_000.ply docs/reconstruct_mesh.png [--azimuth 25 --elevation 35]
"""

from __future__ import annotations

import argparse
import math
import os

import numpy as np


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(4, 4) camera-to-world pose of an OpenGL camera (looking down its -Z) at ``eye``."""
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(back, right), back, eye
    return pose


def render(ply: str, out: str, size=(800, 520), azimuth: float = 25.0, elevation: float = 35.0,
           distance: float = 1.5) -> None:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import matplotlib
    import pyrender
    import trimesh
    from PIL import Image

    mesh = trimesh.load(ply, process=False)
    if len(mesh.faces) == 0:
        raise SystemExit(f"{ply}: the mesh has no faces")
    y = mesh.vertices[:, 1]
    lo, hi = np.percentile(y, [1, 99])
    colours = matplotlib.colormaps["viridis"](np.clip((y - lo) / max(hi - lo, 1e-6), 0, 1))
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=(colours * 255).astype(np.uint8))
    scene = pyrender.Scene(bg_color=(1.0, 1.0, 1.0, 1.0), ambient_light=(0.45, 0.45, 0.45))
    scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
    dot = trimesh.creation.icosphere(radius=0.08)
    dot.visual.vertex_colors = (220, 30, 30, 255)
    scene.add(pyrender.Mesh.from_trimesh(dot))

    lo3, hi3 = mesh.bounds
    target = (lo3 + hi3) / 2
    radius = np.linalg.norm(hi3 - lo3) / 2
    a, e = math.radians(azimuth), math.radians(elevation)
    # behind the photo's camera (-Z), turned by the azimuth about +Y, raised by the elevation
    direction = np.array([math.sin(a) * math.cos(e), math.sin(e), -math.cos(a) * math.cos(e)])
    yfov = math.radians(45)
    eye = target + direction * distance * radius / math.tan(yfov / 2)
    pose = look_at(eye, target)
    scene.add(pyrender.PerspectiveCamera(yfov=yfov, aspectRatio=size[0] / size[1]), pose=pose)
    scene.add(pyrender.DirectionalLight(intensity=3.0), pose=pose)
    renderer = pyrender.OffscreenRenderer(*size)
    try:
        colour, _ = renderer.render(scene)
    finally:
        renderer.delete()
    Image.fromarray(colour).save(out, optimize=True)
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, height {lo:.2f}..{hi:.2f} m")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ply")
    parser.add_argument("out", help="PNG to write")
    parser.add_argument("--azimuth", type=float, default=25.0, help="degrees about +Y from behind the camera")
    parser.add_argument("--elevation", type=float, default=35.0, help="degrees above the horizontal")
    parser.add_argument("--distance", type=float, default=1.5, help="viewer distance, in mesh radii that fill the view")
    parser.add_argument("--size", type=int, nargs=2, default=(800, 520), metavar=("W", "H"))
    args = parser.parse_args()
    render(args.ply, args.out, tuple(args.size), args.azimuth, args.elevation, args.distance)


if __name__ == "__main__":
    main()
