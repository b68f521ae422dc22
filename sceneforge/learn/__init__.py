"""The paper's models on sceneforge stores (SPEC §10); the only place that imports PyTorch.

- :mod:`.dataset`  — views of one or more stores as training samples, split by house
- :mod:`.networks` — frontal depth and segmentation nets, overhead nets, camera proposal
- :mod:`.eft`      — the Epipolar Feature Transformer (frontal features → overhead view)
- :mod:`.losses`   — masked Huber (equation 1), cross-entropy, L1 on heights
- :mod:`.stages`   — the training stages as objects: inputs, nets, frozen runs, loss, outputs
- :mod:`.trainer`  — the loop and its pieces: optimiser steps, validation, checkpoint, metrics
- :mod:`.train`    — one stage per run: config, the run folder, resume, loss curve
- :mod:`.predict`  — a run's predictions written in the store layout
"""

from .eft import EFTConfig, EpipolarFeatureTransformer, epipolar_geometry
from .predict import predict
from .train import STAGES, TrainConfig, load_run, train

__all__ = ["EFTConfig", "EpipolarFeatureTransformer", "STAGES", "TrainConfig", "epipolar_geometry", "load_run",
           "predict", "train"]
