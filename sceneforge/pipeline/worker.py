"""What a worker process keeps between tasks: the last house it loaded, its ray tracer, and
one RGB renderer (planning and shard tasks both load houses through it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..config import DatasetConfig
    from ..houses import HouseSource


class Worker:
    """The per-process cache of a worker: one house (and its tracer), one renderer."""

    def __init__(self):
        self.house_key = None
        self.house = self.tracer = None
        self.renderer_key = None
        self.renderer = None

    def load(self, source: "HouseSource", config: "DatasetConfig"):
        from ..houses import load

        key = (source, config.houses)
        if key != self.house_key:
            self.house_key = None  # a load that raises leaves no stale house behind
            self.house, self.tracer = load(source, config.houses), None
            self.house_key = key
        return self.house

    def forget_house(self) -> None:
        """Drop the cached house, so that the next :meth:`load` reads its files again."""
        self.house_key = self.house = self.tracer = None

    def tracer_of(self, house):
        from ..raytrace import HouseTracer

        if self.tracer is None:
            self.tracer = HouseTracer(house)
        return self.tracer

    def renderer_for(self, config: "DatasetConfig"):
        key = (config.width, config.height, config.rgb)
        if key != self.renderer_key:
            if self.renderer is not None:
                self.renderer.close()
            self.renderer = self.renderer_key = None
            from ..render import open_renderer

            self.renderer = open_renderer(config.rgb.mode, config.width, config.height, antialias=config.rgb.antialias,
                                          config=config.rgb.lighting, samples=config.rgb.samples,
                                          denoise=config.rgb.denoise)
            self.renderer_key = key
        return self.renderer

    def close(self) -> None:
        """Free the renderer and forget the house (the in-process executor calls this at its end)."""
        if self.renderer is not None:
            self.renderer.close()
        self.renderer = self.renderer_key = None
        self.house_key = self.house = self.tracer = None


#: the state of this process when it works as a worker (one per process by construction)
WORKER = Worker()
