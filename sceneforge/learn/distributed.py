"""Training on several processes: one per GPU, started by ``torchrun`` (docs/spec.md §10.5).

``torchrun --standalone --nproc_per_node N -m sceneforge train STORES ...`` starts N copies
of the command; each reads its place from the environment torchrun sets (``RANK``,
``WORLD_SIZE``, ``LOCAL_RANK``: :meth:`Distributed.from_env`), joins the process group
(NCCL on CUDA, gloo on the CPU) and trains a :class:`~torch.nn.parallel.DistributedDataParallel`
copy of the nets on its share of every batch (``batch_size / N`` views,
:class:`~sceneforge.learn.trainer.EpochSampler`); the gradients are averaged, so every step
is one step on the whole batch. Rank 0 alone writes the run folder (split, config,
checkpoints, metrics, logs) and validates (the others wait, up to :data:`TIMEOUT`).

BatchNorm in training mode normalises by the statistics of its batch: per process, a share
of the batch. With ``sync_batchnorm`` (the default) they are those of the whole batch, as
in one process: :class:`torch.nn.SyncBatchNorm` on CUDA, and on the CPU (where this PyTorch's
SyncBatchNorm refuses to run) :class:`GlobalBatchNorm`, the same computation with
autograd-aware all-reduces of gloo.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist
from torch import Tensor, nn

#: how long a process waits for the others at a collective: rank 0 validates alone after
#: every epoch while the others wait for the next step (the default, 10 min with NCCL, is
#: shorter than a validation of the paper's data may take)
TIMEOUT = timedelta(hours=2)


@dataclass(frozen=True)
class Distributed:
    """This process's place among the processes of a run (one process: rank 0 of 1)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1

    @classmethod
    def from_env(cls) -> "Distributed":
        """The place torchrun gives this process (its environment variables); 0 of 1 without."""
        env = os.environ
        world = int(env.get("WORLD_SIZE", 1))
        return cls(int(env.get("RANK", 0)), world, int(env.get("LOCAL_RANK", 0)),
                   int(env.get("LOCAL_WORLD_SIZE", world)))

    @property
    def enabled(self) -> bool:
        """Whether there are other processes to share the work with."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes the run folder."""
        return self.rank == 0

    def device(self, device: torch.device) -> torch.device:
        """The device of this process: GPU ``LOCAL_RANK`` when ``device`` is a GPU."""
        if self.enabled and device.type == "cuda":
            return torch.device("cuda", self.local_rank)
        return device

    def start(self, device: torch.device) -> bool:
        """Join the process group (NCCL on CUDA, else gloo); whether this call started it
        (and :meth:`stop` should end it)."""
        if not self.enabled or dist.is_initialized():
            return False
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=self.rank,
                                world_size=self.world_size, timeout=TIMEOUT)
        return True

    def stop(self) -> None:
        if dist.is_initialized():
            dist.destroy_process_group()

    def barrier(self) -> None:
        if self.enabled:
            dist.barrier()

    def sum(self, values: Tensor) -> Tensor:
        """``values`` summed over the processes (itself with one process)."""
        if not self.enabled:
            return values
        values = values.clone()
        dist.all_reduce(values)
        return values


class _AllReduceSum(torch.autograd.Function):
    """The sum over the processes of a tensor; its gradient is the sum of theirs (every
    process's loss depends on every process's input)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        x = x.clone()
        dist.all_reduce(x)
        return x

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        grad = grad.clone()
        dist.all_reduce(grad)
        return grad


def all_reduce_sum(x: Tensor) -> Tensor:
    """``x`` summed over the processes of the default group, differentiably."""
    return _AllReduceSum.apply(x)


class GlobalBatchNorm(nn.BatchNorm2d):
    """BatchNorm2d whose training-mode statistics are those of the whole batch of every
    process of the default process group (any backend, gloo on the CPU included).

    Two passes, each one all-reduce: the mean over all processes' pixels, then the mean
    squared deviation from it; both are autograd-aware (the gradient flows to every
    process's input). Running statistics are updated as BatchNorm2d updates them on the
    whole batch (unbiased variance). In eval mode, or with a single process, it is
    BatchNorm2d. Half-precision inputs (mixed precision) are normalised in float32.
    """

    def forward(self, x: Tensor) -> Tensor:
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        xf = x.float() if x.dtype in (torch.float16, torch.bfloat16) else x
        dims, shape = (0, 2, 3), (1, -1, 1, 1)
        count = torch.full((1,), xf.numel() // xf.shape[1], dtype=xf.dtype, device=xf.device)
        sums = all_reduce_sum(torch.cat([xf.sum(dims), count]))
        n = sums[-1]
        mean = sums[:-1] / n
        centred = xf - mean.view(shape)
        var = all_reduce_sum((centred * centred).sum(dims)) / n
        y = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            y = y * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                m = 1.0 / float(self.num_batches_tracked) if self.momentum is None else self.momentum
                self.running_mean.mul_(1 - m).add_(mean.detach(), alpha=m)
                self.running_var.mul_(1 - m).add_(var.detach() * (n / (n - 1)), alpha=m)
        return y.to(x.dtype)


def sync_batchnorm(net: nn.Module, device: torch.device) -> nn.Module:
    """``net`` with every BatchNorm2d computing the whole batch's statistics:
    :class:`torch.nn.SyncBatchNorm` on CUDA, :class:`GlobalBatchNorm` elsewhere. The
    parameters and buffers are the same tensors (the state dict's keys do not change)."""
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(net)
    return _to_global(net)


def _to_global(module: nn.Module) -> nn.Module:
    if type(module) is nn.BatchNorm2d:
        bn = GlobalBatchNorm(module.num_features, module.eps, module.momentum, module.affine,
                             module.track_running_stats)
        if module.affine:
            bn.weight, bn.bias = module.weight, module.bias
        if module.track_running_stats:
            bn.running_mean, bn.running_var = module.running_mean, module.running_var
            bn.num_batches_tracked = module.num_batches_tracked
        bn.train(module.training)
        return bn
    for name, child in module.named_children():
        module.add_module(name, _to_global(child))
    return module
