"""Multi-process training (torchrun): the process group, this process's rank, and the helpers the fit
loop and the collection samplers use.

`torchrun --nproc_per_node=N train.py experiment=shapes_deepsdf` starts N processes with RANK,
WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT set; `init_from_environment` joins them (gloo on
CPUs, NCCL on GPUs). `fit` then wraps its loss computation in DistributedDataParallel, which averages
the gradients of all ranks every step (latent codes included: their gradients are dense), and writes
checkpoints, TensorBoard events and logs from rank 0 only. Every rank draws the same global batch
from the fit's seeded generator and keeps its rows `rank::world` (DistributedSampler's strided split
of one shared permutation), so N processes step exactly as one process with the same global batch.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist

from neuralsurf.errors import ConfigError


def rank_and_world() -> tuple[int, int]:
    """(rank, world size) of this process: (0, 1) without a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def is_main_process() -> bool:
    return rank_and_world()[0] == 0


def init_from_environment(device: str = "auto") -> str:
    """Join the process group that torchrun describes in the environment (no-op when WORLD_SIZE is
    absent or 1, or the group exists); returns the device this rank should use: `cuda:<LOCAL_RANK>`
    for "auto"/"cuda" when CUDA is there, else `device`."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return device
    if not dist.is_available():
        raise ConfigError("WORLD_SIZE > 1 but this PyTorch build has no torch.distributed; run one process")
    cuda = torch.cuda.is_available() and str(device) in ("auto", "cuda")
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        if cuda:
            torch.cuda.set_device(local_rank)
        dist.init_process_group("nccl" if cuda else "gloo")
    return f"cuda:{local_rank}" if cuda else device


def leave_process_group() -> None:
    """Every rank: end the process group (no-op without one); later fits are single-process."""
    if dist.is_available() and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def barrier() -> None:
    if rank_and_world()[1] > 1:
        dist.barrier()


def broadcast_object(value):
    """Rank 0's `value` on every rank (itself without a process group)."""
    if rank_and_world()[1] == 1:
        return value
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def mean_over_ranks(values: dict[str, float]) -> dict[str, float]:
    """The mean of each value over the ranks (the values themselves without a process group)."""
    world = rank_and_world()[1]
    if world == 1 or not values:
        return values
    backend_cuda = dist.get_backend() == "nccl"
    tensor = torch.tensor(list(values.values()), dtype=torch.float64,
                          device=f"cuda:{torch.cuda.current_device()}" if backend_cuda else "cpu")
    dist.all_reduce(tensor)
    return dict(zip(values, (tensor / world).tolist()))


def shard_rows(count: int, world: int, what: str) -> None:
    """Check that a global batch of `count` rows splits evenly over `world` processes."""
    if count % world:
        raise ConfigError(f"{what}: the global batch of {count} shapes does not split evenly over {world} "
                          f"processes; make it a multiple of {world} (and the collection at least that large)")
