"""Latent codes for learned shape priors (DeepSDF, Park et al. 2019).

- `LatentCodes`: one code per training shape, initialised N(0, init_std^2) (DeepSDF: 0.01).
- `AutoDecoder(decoder, codes)`: a decoder x, z -> sdf with the codes of a collection, trained
  jointly over the collection (`neuralsurf.priors.CollectionSDF`).
- `LatentConditioned(decoder, latent_dim)`: one shape's field x -> decoder(x, code) with the code a
  Parameter; reconstruction is `fit(model, observations, trainable=[model.code])` under the frozen
  decoder.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models.spec import rebuildable


@rebuildable
class LatentCodes(nn.Module):
    """`count` codes of `dim` entries: indices[...] -> codes[..., dim]."""

    def __init__(self, count: int, dim: int, init_std: float = 0.01):
        super().__init__()
        if not (isinstance(count, int) and count >= 1 and isinstance(dim, int) and dim >= 1 and init_std >= 0):
            raise ConfigError(f"LatentCodes needs count >= 1, dim >= 1 and init_std >= 0, got count={count!r}, "
                              f"dim={dim!r}, init_std={init_std!r}")
        self.weight = nn.Parameter(torch.randn(count, dim) * init_std)

    @property
    def dim(self) -> int:
        return self.weight.shape[1]

    def __len__(self) -> int:
        return self.weight.shape[0]

    def forward(self, indices: Tensor) -> Tensor:
        """Int[Tensor, "..."] -> Float[Tensor, "... dim"]."""
        if indices.dtype not in (torch.int32, torch.int64):
            raise InputError(f"latent code indices must be integers, got {indices.dtype}")
        capturing = indices.is_cuda and torch.cuda.is_current_stream_capturing()  # a CUDA graph cannot wait
        checkable = indices.numel() and not capturing
        if checkable and (int(indices.min()) < 0 or int(indices.max()) >= len(self)):
            raise InputError(f"latent code indices must lie in [0, {len(self)}), got {int(indices.min())}.."
                             f"{int(indices.max())}: the index of a shape outside the training collection")
        return self.weight[indices]


def _check_decoder(decoder: nn.Module, dim: int, owner: str) -> None:
    latent_dim = getattr(decoder, "latent_dim", None)
    if latent_dim != dim:
        raise ConfigError(f"{owner}: the decoder takes latent codes of {latent_dim} entries, the codes have {dim}; "
                          f"build the decoder with latent_dim={dim}")


@rebuildable
class AutoDecoder(nn.Module):
    """A DeepSDF auto-decoder: a conditional decoder and the latent codes of its training shapes."""

    def __init__(self, decoder: nn.Module, codes: LatentCodes):
        super().__init__()
        _check_decoder(decoder, codes.dim, "AutoDecoder")
        self.decoder = decoder
        self.codes = codes

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x[..., 3], latent[..., dim] or [dim] -> sdf[...]. Without `latent`: the mean of the training
        codes (the collection's "mean shape", for previews and logs)."""
        if latent is None:
            latent = self.codes.weight.mean(0)
        return self.decoder(x, latent)

    def shape_sdf(self, x: Tensor, shape_index: Tensor) -> Tensor:
        """x[b, s, 3], shape_index Int[b] -> sdf[b, s] of training shape `shape_index[i]` at x[i]."""
        codes = self.codes(shape_index)
        return self.decoder(x, codes[:, None, :].expand(*x.shape[:-1], codes.shape[-1]))


@rebuildable
class LatentConditioned(nn.Module):
    """One shape of a learned prior: x[..., 3] -> decoder(x, code), the code a Parameter (zeros, the
    prior's mean, unless `init_std` > 0 or set with `set_code`)."""

    def __init__(self, decoder: nn.Module, latent_dim: int, init_std: float = 0.0):
        super().__init__()
        _check_decoder(decoder, latent_dim, "LatentConditioned")
        self.decoder = decoder
        self.code = nn.Parameter(torch.randn(latent_dim) * init_std)

    @classmethod
    def from_code(cls, decoder: nn.Module, code: Tensor) -> LatentConditioned:
        """The field of `code` (Float[Tensor, "dim"]) under `decoder` (e.g. a trained shape's code)."""
        model = cls(decoder, int(code.shape[-1]))
        return model.set_code(code)

    def set_code(self, code: Tensor) -> LatentConditioned:
        with torch.no_grad():
            self.code.copy_(code.reshape(self.code.shape))
        return self

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x[..., 3] -> sdf[...]; `latent` must be None (the code is this module's own)."""
        if latent is not None:
            raise InputError("LatentConditioned holds its own code; call it without a latent "
                             "(or call its decoder with yours)")
        return self.decoder(x, self.code)
