"""The config of ``sceneforge evaluate``: the configs of its steps in one file
(``schemas/evaluate.schema.json``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .depth_mesh import MeshingConfig
from .points import PointsConfig
from .surface import SurfaceConfig
from .voxels import VoxelConfig


@dataclass(frozen=True)
class EvaluateConfig:
    """How reconstructions are scored: surface precision/recall, voxel IoU and layered point sets."""

    #: seed of the surface and point sampling; view i draws from (seed, i)
    seed: int = 0
    #: surface sampling and matching (coverage, predictions)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    #: depth layers → meshes (coverage, predictions)
    meshing: MeshingConfig = field(default_factory=MeshingConfig)
    #: the voxel grid (voxels)
    voxels: VoxelConfig = field(default_factory=VoxelConfig)
    #: layered point sets, LaRI's Chamfer-L1 and F-score (points, predictions)
    points: PointsConfig = field(default_factory=PointsConfig)

    def to_dict(self) -> dict:
        from sceneforge.config import dataclass_to_dict

        return dataclass_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict, *, what: str = "evaluate config") -> "EvaluateConfig":
        """Validate ``data`` against ``schemas/evaluate.schema.json`` and build the config."""
        from sceneforge.config import build_config

        return build_config(cls, data, schema="evaluate", what=what)
