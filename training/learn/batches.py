"""Deterministic batches: the batch of step k, and its augmentation, depend only on (seed, k)."""

from __future__ import annotations

import hashlib

import torch

from ..data.dataset import ViewDataset

__all__ = ["StepBatches", "to_device"]


def _mix(*parts: int) -> int:
    return int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "big") & ((1 << 63) - 1)


class StepBatches(torch.utils.data.Dataset):
    """Item k is this process's share of the global batch of step k (so workers may prefetch)."""

    def __init__(self, data: ViewDataset, batch: int, rank: int, world: int, seed: int):
        self.data, self.batch, self.rank, self.world, self.seed = data, batch, rank, world, seed
        self._perms: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return 1 << 40

    def _index(self, g: int) -> int:
        n = len(self.data)
        epoch, pos = divmod(g, n)
        if epoch not in self._perms:
            self._perms = {epoch: torch.randperm(n, generator=torch.Generator().manual_seed(_mix(self.seed, epoch)))}
        return int(self._perms[epoch][pos])

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        first = (step * self.world + self.rank) * self.batch
        samples = [self.data.sample(self._index(g), _mix(self.seed, g, 1)) for g in range(first, first + self.batch)]
        out = {k: torch.stack([s[k] for s in samples]) for k in samples[0]}
        # two uniform numbers per sample for the stage's per-sample choices (StageModule: sph_teacher, depth_dropout)
        out["coin"] = torch.stack([torch.rand(2, generator=torch.Generator().manual_seed(_mix(self.seed, g, 2)))
                                   for g in range(first, first + self.batch)])
        return out


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """Every tensor of ``batch`` on ``device`` (shapes unchanged)."""
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}
