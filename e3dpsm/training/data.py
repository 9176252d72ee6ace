"""Training windows over a prepared folder: N consecutive frames of one sequence.

Sampling is a pure function of (seed, epoch, rank, world size), so a resumed run draws the
same windows it would have drawn without the interruption, and the ranks of a distributed
run draw disjoint shares of each epoch without a DistributedSampler.
"""
from __future__ import annotations

from typing import Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate

from e3dpsm.data.prepared import PreparedSequence
from e3dpsm.errors import DataError

class WindowDataset(Dataset):
    """Item i = the window of `seq_len` frames starting at the i-th valid start; returns
    float32 tensors lnes [N, 2, H, W], j3d_mm [N, J, 3], j2d_px [N, J, 2], visible [N, J]."""

    def __init__(self, sequences: Sequence[PreparedSequence], seq_len: int) -> None:
        if seq_len < 2:
            raise DataError(f"--seq-len must be at least 2 (the delta loss needs two frames), got {seq_len}")
        usable = [s for s in sequences if s.frames >= seq_len]
        if not usable:
            longest = max((s.frames for s in sequences), default=0)
            raise DataError(f"no sequence has {seq_len} frames for a training window (longest: {longest}); "
                            "lower --seq-len or prepare longer sequences")
        self.sequences = usable
        self.seq_len = seq_len
        counts = np.array([s.frames - seq_len + 1 for s in usable])
        self._offsets = np.concatenate([[0], np.cumsum(counts)])

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def index_of(self, seq_index: int, start: int) -> int:
        """(sequence index, first frame) -> window index; the inverse of `locate`."""
        return int(self._offsets[seq_index]) + start

    def locate(self, index: int) -> tuple[int, int]:
        """Window index -> (sequence index, first frame)."""
        seq = int(np.searchsorted(self._offsets, index, side="right") - 1)
        return seq, int(index - self._offsets[seq])

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        seq_index, start = self.locate(index)
        seq = self.sequences[seq_index]
        window = slice(start, start + self.seq_len)
        return {
            "lnes": torch.from_numpy(np.asarray(seq.lnes[window], dtype=np.float32)),
            "j3d_mm": torch.from_numpy(np.asarray(seq.j3d_mm[window], dtype=np.float32)),
            "j2d_px": torch.from_numpy(np.asarray(seq.j2d_px[window], dtype=np.float32)),
            "visible": torch.from_numpy(np.asarray(seq.visible[window], dtype=np.float32)),
        }

    def frames_total(self) -> int:
        return int(sum(s.frames for s in self.sequences))


class SeededWindowSampler(Sampler[int]):
    """Random window starts for one epoch and one rank.

    An epoch draws `samples_per_epoch` starts (without replacement while they last) from
    a generator seeded by (seed, epoch); rank r of W takes every W-th of them. `skip`
    drops the first batches of the epoch a resumed run has already trained on.
    """

    def __init__(self, num_windows: int, samples_per_epoch: int, seed: int, epoch: int,
                 rank: int = 0, world_size: int = 1, skip: int = 0) -> None:
        self.num_windows, self.samples_per_epoch = num_windows, samples_per_epoch
        self.seed, self.epoch, self.rank, self.world_size, self.skip = seed, epoch, rank, world_size, skip

    def _indices(self) -> np.ndarray:
        rng = np.random.default_rng([self.seed, self.epoch])
        rounds = -(-self.samples_per_epoch // self.num_windows)
        drawn = np.concatenate([rng.permutation(self.num_windows) for _ in range(rounds)])
        return drawn[: self.samples_per_epoch][self.rank :: self.world_size][self.skip :]

    def __iter__(self) -> Iterator[int]:
        return iter(self._indices().tolist())

    def __len__(self) -> int:
        return len(self._indices())


def epoch_size(dataset: WindowDataset, batch_size: int, world_size: int = 1) -> tuple[int, int]:
    """(optimizer steps per epoch, windows per epoch). An epoch covers every frame once in
    expectation; rounded so every rank does the same number of steps."""
    per_step = batch_size * world_size
    steps = max(1, -(-(dataset.frames_total() // dataset.seq_len) // per_step))
    return steps, steps * per_step


def seeded_batches(dataset: WindowDataset, batch_size: int, seed: int, start_step: int = 0, *,
                   rank: int = 0, world_size: int = 1, num_workers: int = 0) -> Iterator[tuple[int, dict[str, torch.Tensor]]]:
    """Yield (step, batch) from `start_step` on, epoch after epoch, endlessly; the windows of
    a step depend only on (seed, step, rank, world size), so a resumed run draws what an
    uninterrupted one would have drawn."""
    epoch_steps, epoch_windows = epoch_size(dataset, batch_size, world_size)
    step = start_step
    while True:
        epoch, done = divmod(step, epoch_steps)
        sampler = SeededWindowSampler(len(dataset), epoch_windows, seed, epoch, rank, world_size,
                                      skip=done * batch_size)
        loader = DataLoader(dataset, batch_size=batch_size, sampler=sampler, drop_last=True,
                            num_workers=num_workers)
        for batch in loader:
            yield step, batch
            step += 1


def stream_batches(dataset: WindowDataset, batch_size: int, seed: int, windows_per_stream: int
                   ) -> Iterator[tuple[int, dict[str, torch.Tensor], torch.Tensor]]:
    """Yield (step, batch, fresh) endlessly, for truncated backpropagation through a stream:
    lane b of a batch continues one recording with its next `seq_len` frames for
    `windows_per_stream` steps, then starts another at a random place; `fresh[b]` is True
    where lane b starts a stream (its states start from the initial ones), False where it
    continues the previous step's (its states carry over). The lanes' first streams are
    staggered, so they restart at different steps. Depends only on (seed, step)."""
    if windows_per_stream < 1:
        raise DataError(f"windows per stream must be at least 1, got {windows_per_stream}")
    length = dataset.seq_len * windows_per_stream
    starts = np.array([max(0, s.frames - length + 1) for s in dataset.sequences])
    if not starts.any():
        longest = max(s.frames for s in dataset.sequences)
        raise DataError(f"no sequence has {length} frames for a stream of {windows_per_stream} windows of "
                        f"{dataset.seq_len} (longest: {longest}); lower --stream-windows or --seq-len")
    rng = np.random.default_rng([seed, 7717])

    def restart(windows: int) -> list[int]:
        """[sequence, next frame, windows left] of a new stream of `windows` windows."""
        seq = int(rng.choice(len(starts), p=starts / starts.sum()))
        first = int(rng.integers(0, dataset.sequences[seq].frames - windows * dataset.seq_len + 1))
        return [seq, first, windows]

    lanes = [restart(windows_per_stream - (lane * windows_per_stream) // batch_size) for lane in range(batch_size)]
    fresh = [True] * batch_size
    step = 0
    while True:
        items = []
        for lane in lanes:
            items.append(dataset[dataset.index_of(lane[0], lane[1])])
            lane[1] += dataset.seq_len
            lane[2] -= 1
        yield step, default_collate(items), torch.tensor(fresh)
        fresh = [lane[2] == 0 for lane in lanes]
        lanes = [restart(windows_per_stream) if lane[2] == 0 else lane for lane in lanes]
        step += 1


def mean_pose_mm(sequences: Sequence[PreparedSequence]) -> np.ndarray:
    """Mean ground-truth pose [J, 3] over every frame (the direct head's prior)."""
    total = sum(np.asarray(s.j3d_mm, np.float64).sum(axis=0) for s in sequences)
    return (total / sum(s.frames for s in sequences)).astype(np.float32)
