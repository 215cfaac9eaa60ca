"""Data order and per-sample randomness that a checkpoint restores exactly (docs/design.md).

Every random choice of the data side is a pure function of numbers a checkpoint holds:

* the order of an epoch is a permutation drawn from ``(seed, epoch)`` (`EpochSampler`);
  with lengths given, the same permutation regrouped so that each batch holds clips of
  similar length (`group_by_length`), again a function of ``(seed, epoch)`` only;
* a sample's random crop or window is drawn from ``(seed, epoch, index)`` (`sample_rng`),
  where ``index`` is the sample's position in its dataset. The sampler hands the epoch to
  the dataset inside the key it yields, ``(index, epoch)``, so the draw does not depend on
  which DataLoader worker loads the sample, nor on how many workers there are.

`ResumableDataLoader` counts the batches it has handed out in the current epoch; Lightning
saves its `state_dict` in every checkpoint and, on ``--ckpt_path``, passes it back, so a
resumed run continues the interrupted epoch at the next batch with the same order and
crops as an uninterrupted run. Under DDP each rank reads its share of the same
permutation (padded to a multiple of the world size, as `DistributedSampler` does).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler


def sample_rng(seed: int, epoch: int, index: int) -> np.random.Generator:
    """The random generator of sample ``index`` in ``epoch``: a pure function of the three."""
    return np.random.default_rng((seed, epoch, index))


def split_key(key: Any, epoch: int) -> tuple[int, int]:
    """A dataset key → (index, epoch): ``(index, epoch)`` from `EpochSampler`, or a plain
    index, which uses the dataset's own ``epoch`` (set with ``set_epoch``)."""
    if isinstance(key, tuple):
        index, epoch = key
        return int(index), int(epoch)
    return int(key), epoch


# Batches of similar length are formed within pools of this many batches.
POOL_BATCHES = 50


def group_by_length(order: np.ndarray, lengths: np.ndarray, block: int, rng: np.random.Generator
                    ) -> np.ndarray:
    """`order` regrouped so that each run of `block` consecutive indices holds clips of
    similar length: within pools of POOL_BATCHES blocks of the shuffled order, indices are
    sorted by length (longest first), cut into blocks, and the blocks are shuffled. A
    batch then pads to its own longest clip, not to the epoch's, while every clip still
    comes once per epoch and the order of the batches stays random.

    The `len(order) % block` indices that cannot fill a block (the last ones of the
    shuffled `order`, so a random choice) are set aside before ranking and go last, where
    `drop_last` drops them: the clips an epoch leaves out are random, as with plain
    shuffling, not the shortest of the last pool. With `len(order)` a multiple of
    `block` nothing is set aside."""
    keep = len(order) - len(order) % block
    pool = block * POOL_BATCHES
    ranked = np.concatenate([chunk[np.argsort(-lengths[chunk], kind="stable")]
                             for chunk in np.split(order[:keep], range(pool, keep, pool))])
    blocks = np.split(ranked, range(block, keep, block))
    return np.concatenate([blocks[i] for i in rng.permutation(len(blocks))] + [order[keep:]])


def _world() -> tuple[int, int]:
    """(world size, rank) of the initialised process group, else (1, 0)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_world_size(), torch.distributed.get_rank()
    return 1, 0


# A DistributedSampler subclass so that Lightning, which wraps any other sampler in its own
# distributed sampler under DDP, uses this one as it is.
class EpochSampler(DistributedSampler):
    """This rank's keys ``(index, epoch)`` of one epoch; the order is a function of
    ``(seed, epoch)`` (shuffled) or the dataset order (``shuffle=False``).

    ``skip`` keys of the next epoch to be iterated are left out (a resumed epoch);
    `set_epoch` to another epoch clears it. ``len()`` is the whole epoch's share.

    ``lengths`` (one per sample) and ``batch_size``: batches of similar length
    (`group_by_length`, blocks of ``batch_size`` × world size, so that every rank's batch
    is one block's share).
    """

    def __init__(self, dataset: Dataset, seed: int = 0, shuffle: bool = True,
                 num_replicas: int | None = None, rank: int | None = None,
                 lengths: np.ndarray | None = None, batch_size: int | None = None) -> None:
        world, own = _world()
        super().__init__(dataset, num_replicas=world if num_replicas is None else num_replicas,
                         rank=own if rank is None else rank, shuffle=shuffle, seed=seed)
        if lengths is not None and (batch_size is None or len(lengths) != len(dataset)):
            raise ValueError(f"EpochSampler: lengths needs batch_size and one length per sample "
                             f"({len(lengths)} for {len(dataset)})")
        self.lengths = None if lengths is None else np.asarray(lengths)
        self.batch_size = batch_size
        self.skip = 0

    def set_epoch(self, epoch: int) -> None:
        if epoch != self.epoch:
            self.skip = 0
        self.epoch = epoch

    def order(self) -> np.ndarray:
        """(num_samples,) dataset indices of this rank in this epoch."""
        n = len(self.dataset)
        rng = np.random.default_rng((self.seed, self.epoch))
        order = rng.permutation(n) if self.shuffle else np.arange(n)
        if self.lengths is not None and self.shuffle:
            order = group_by_length(order, self.lengths, self.batch_size * self.num_replicas, rng)
        order = np.resize(order, self.total_size)  # pads by repeating from the start
        return order[self.rank:self.total_size:self.num_replicas]

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch, skip = self.epoch, self.skip
        self.skip = 0
        return iter([(int(i), epoch) for i in self.order()[skip:]])


class ResumableDataLoader(DataLoader):
    """A DataLoader over an `EpochSampler` whose position in the epoch is checkpointed.

    ``state_dict()`` is ``{"epoch", "batches"}``: the epoch and the number of batches of it
    handed out so far (counted where they leave the loader, so batches that workers have
    prefetched do not count). ``load_state_dict`` makes the next iteration start at the
    batch after those. A pass that runs to the end moves the sampler to the next epoch.
    """

    def __init__(self, dataset: Dataset, *, sampler: EpochSampler, **kwargs: Any) -> None:
        super().__init__(dataset, sampler=sampler, **kwargs)
        self._batches = 0

    def __iter__(self) -> Iterator[Any]:
        sampler: EpochSampler = self.sampler
        epoch, self._batches = sampler.epoch, sampler.skip // self.batch_size
        for batch in super().__iter__():
            self._batches += 1
            yield batch
        # A plain loop (a notebook, a tool) gets the next epoch's order on its next pass.
        # Lightning never gets here (it stops at len()) and sets the epoch itself.
        if sampler.epoch == epoch:
            sampler.set_epoch(epoch + 1)

    def state_dict(self) -> dict[str, int]:
        return {"epoch": self.sampler.epoch, "batches": self._batches}

    def load_state_dict(self, state: dict[str, int]) -> None:
        if state["batches"] >= len(self):
            return  # the epoch was over; the next one starts from its beginning
        self.sampler.epoch = state["epoch"]
        self.sampler.skip = state["batches"] * self.batch_size
