"""sceneforge: 3D house models in, multi-layer depth training data out.

Implements "3D Scene Reconstruction with Multi-layer Depth and Epipolar Transformers"
(Shin, Ren, Sudderth, Fowlkes, ICCV 2019). Conventions are stated once, in
:mod:`sceneforge.conventions`.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sceneforge")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"


def __getattr__(name: str):
    # ``sceneforge.open_store`` without importing zarr when sceneforge is imported
    if name == "open_store":
        from .store import open_store

        return open_store
    if name == "ground_truth_meshes":
        from .pipeline.gt_mesh import ground_truth_meshes

        return ground_truth_meshes
    raise AttributeError(f"module 'sceneforge' has no attribute {name!r}")
