"""Where computation runs: one rule for every module (device=auto|cpu|cuda[:i])."""

import warnings

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


class CompiledOnCPU:
    """`function` compiled by torch.compile (dynamic shapes) for CPU tensors: one fused loop over its
    elements instead of a pass over memory per operation. torch.compile's CPU backend needs a C++ compiler:
    where it fails, a warning (once, naming `what` runs slower) and `function` itself, eager, which gives
    the same results."""

    def __init__(self, function, what: str):
        self.function, self.what, self.compiled, self.failed = function, what, None, False

    def __call__(self, *args):
        if not self.failed:
            self.compiled = self.compiled or torch.compile(self.function, dynamic=True)
            try:
                return self.compiled(*args)
            except torch._dynamo.exc.BackendCompilerFailed as error:
                self.failed = True
                warnings.warn(
                    f"{self.what} runs eager (slower): torch.compile failed for {self.function.__name__} "
                    f"({str(error).strip().splitlines()[0]}); install a C++ compiler (Debian: apt-get install g++) "
                    f"or pass compiled=False to skip the attempt",
                    stacklevel=3,
                )
        return self.function(*args)

    def on(self, device: torch.device, compiled: bool):
        """This compiled form where `compiled` and `device` is a CPU, else the function itself (eager)."""
        return self if compiled and device.type == "cpu" else self.function
