"""Where computation runs: one rule for every module (device=auto|cpu|cuda[:i])."""

import torch

from neuralsurf.errors import DeviceError


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """"auto" -> CUDA when available, else CPU; "cuda" without a GPU is an error."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as error:
        raise DeviceError(f"unknown device {device!r} ({error}); use auto, cpu or cuda[:index]") from None
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(
            f"device={device!r} was requested but PyTorch sees no CUDA GPU "
            f"(torch {torch.__version__}); use device=auto or device=cpu"
        )
    return resolved
