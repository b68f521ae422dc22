"""The paper's models on sceneforge stores (docs/spec.md §10); the only place that imports PyTorch.

- :mod:`.config`   — the training and prediction configs (no torch: the CLI and the schemas read them)
- :mod:`.dataset`  — views of one or more stores as training samples, split by house
- :mod:`.networks` — frontal depth and segmentation nets, overhead nets, camera proposal
- :mod:`.eft`      — the Epipolar Feature Transformer (frontal features → overhead view)
- :mod:`.losses`   — masked Huber (equation 1), cross-entropy, L1 on heights
- :mod:`.stages`   — the training stages as objects: inputs, nets, frozen runs, loss, outputs
- :mod:`.trainer`  — the loop and its pieces: optimiser steps, validation, checkpoint, metrics
- :mod:`.train`    — one stage per run: the run folder, resume, loss curve
- :mod:`.predict`  — a run's predictions written in the store layout

The names below are imported on first use, so that ``sceneforge.learn.config`` loads
without PyTorch.
"""

import importlib

#: name → the submodule that defines it
_EXPORTS = {"EFTConfig": "config", "STAGES": "config", "TrainConfig": "config",
            "EpipolarFeatureTransformer": "eft", "epipolar_geometry": "eft", "predict": "predict",
            "load_run": "train", "train": "train"}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    # importing .train or .predict set the package attribute to the submodule: the function wins, as it did
    # when these names were imported eagerly
    globals()[name] = value
    return value
