"""Which keypoint groups join each training batch (the bundle loss needs whole groups).

Groups are visited in a fresh random order every epoch, `groups_per_batch` at a time; from a group
with more than `obs_per_group` observations a random subset is drawn each time, which bounds the
n^2 pairs per group while every observation still gets its turn. Groups seen from a single buffer
view carry no multi-view constraint and are left out.
"""

from __future__ import annotations

import numpy as np


class GroupSampler:
    def __init__(self, kp_id: np.ndarray, kp_view: np.ndarray, groups_per_batch: int, obs_per_group: int,
                 rng: np.random.Generator) -> None:
        if len(kp_id) and np.any(np.diff(kp_id) < 0):
            raise ValueError("keypoint observations must be sorted by keypoint id")
        ids, starts, counts = np.unique(kp_id, return_index=True, return_counts=True)
        views_per_group = np.array([len(np.unique(kp_view[s:s + c])) for s, c in zip(starts, counts)], dtype=np.int64)
        multi = views_per_group >= 2
        self.starts, self.counts, self.ids = starts[multi], counts[multi], ids[multi]
        if len(self.starts) == 0:
            raise ValueError("no keypoint is observed in two or more buffer views: nothing for the bundle loss")
        self.groups_per_batch = min(groups_per_batch, len(self.starts))
        self.obs_per_group = obs_per_group
        self.rng = rng
        self.order = rng.permutation(len(self.starts))
        self.cursor = 0
        self.epochs = 0

    @property
    def num_groups(self) -> int:
        return len(self.starts)

    def next(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, mask), both (groups_per_batch, obs_per_group): each line one group's observation
        rows, padded with its first row where the group has fewer (mask False there), so that
        every step has the same shape."""
        if self.cursor + self.groups_per_batch > len(self.order):
            self.order, self.cursor, self.epochs = self.rng.permutation(len(self.starts)), 0, self.epochs + 1
        groups = self.order[self.cursor:self.cursor + self.groups_per_batch]
        self.cursor += self.groups_per_batch
        rows = np.empty((len(groups), self.obs_per_group), dtype=np.int64)
        mask = np.zeros((len(groups), self.obs_per_group), dtype=bool)
        for line, g in enumerate(groups):
            start, count = self.starts[g], self.counts[g]
            if count > self.obs_per_group:
                pick = np.sort(self.rng.choice(count, self.obs_per_group, replace=False))
            else:
                pick = np.arange(count)
            rows[line] = start + pick[0]
            rows[line, :len(pick)] = start + pick
            mask[line, :len(pick)] = True
        return rows, mask
