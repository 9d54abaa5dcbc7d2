"""The replay buffer of paper 4.2: whole episodes, FIFO at 400, batches of 25-step segments."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["BufferedEpisode", "ReplayBuffer"]


@dataclass(frozen=True)
class BufferedEpisode:
    """Controller inputs and expert labels of one flight, aligned per step."""

    name: str
    features: np.ndarray  # (T, F) float32
    labels: np.ndarray  # (T, 4) float32
    weights: np.ndarray | None = None
    """(T,) each step's loss weight in [0, 1] (None: all 1). A step of weight 0 still feeds the
    LSTM's state; only its label is not learnt (e.g. a learner step whose expert label the
    learner could not know: :func:`training.train.vision_episode`'s gate)."""

    def __post_init__(self) -> None:
        if self.features.ndim != 2 or self.labels.shape != (self.features.shape[0], 4):
            raise ValueError(
                f"episode {self.name}: features {self.features.shape} and labels "
                f"{self.labels.shape} do not align as (T, F) / (T, 4)"
            )
        if not (np.isfinite(self.features).all() and np.isfinite(self.labels).all()):
            raise ValueError(f"episode {self.name}: non-finite features or labels")
        w = self.weights
        if w is not None and (
            w.shape != (self.features.shape[0],) or not (np.all(w >= 0) and np.all(w <= 1))
        ):
            got = f"[{np.min(w):g}, {np.max(w):g}]" if w.size else "none"
            raise ValueError(
                f"episode {self.name}: weights: expected ({self.features.shape[0]},) in [0, 1], "
                f"got shape {w.shape}, values {got}"
            )


class ReplayBuffer:
    """Holds at most ``capacity`` episodes; the oldest go first (FIFO).

    ``sample(n)`` draws ``n`` segments of ``segment_steps`` contiguous steps: an eligible episode
    (at least ``segment_steps`` long) uniformly at random, then a uniform start offset in it —
    paper 4.2. Randomness comes only from the generator seeded at construction.
    """

    def __init__(self, capacity: int = 400, segment_steps: int = 25, seed: int = 0) -> None:
        if capacity < 1 or segment_steps < 1:
            raise ValueError(
                f"replay buffer: capacity ({capacity}) and segment_steps ({segment_steps}) "
                "must be >= 1"
            )
        self.capacity = capacity
        self.segment_steps = segment_steps
        self._episodes: deque[BufferedEpisode] = deque(maxlen=capacity)
        self._rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self._episodes)

    @property
    def episodes(self) -> list[BufferedEpisode]:
        return list(self._episodes)

    @property
    def total_steps(self) -> int:
        return sum(e.features.shape[0] for e in self._episodes)

    def add(self, episode: BufferedEpisode) -> BufferedEpisode | None:
        """Append; returns the episode pushed out (FIFO) when the buffer was full."""
        evicted = self._episodes[0] if len(self._episodes) == self.capacity else None
        self._episodes.append(episode)
        return evicted

    def sample(
        self, n_segments: int, burn_in_steps: int = 0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(features (n, B+S, F), labels (n, B+S, 4), loss mask (n, B+S))`` float32.

        Each row holds one 25-step segment (mask 1, or the episode's ``weights``) preceded by
        up to ``burn_in_steps`` of the same episode (mask 0) that only warm the LSTM state —
        R2D2's burn-in, so the network learns from the recurrent states it really has late in
        a flight, not only from a zero state. Rows whose segment starts near the episode start
        have a shorter burn-in and are padded at the end (mask 0; a causal LSTM never sees the
        padding before the segment).
        """
        eligible = [
            e
            for e in self._episodes
            if e.features.shape[0] >= self.segment_steps and (e.weights is None or e.weights.any())
        ]
        if not eligible:
            raise ValueError(
                f"replay buffer: no episode has {self.segment_steps} steps "
                f"({len(self._episodes)} episodes held)"
            )
        picks = self._rng.integers(0, len(eligible), size=n_segments)
        s, b = self.segment_steps, max(0, burn_in_steps)
        feats = np.zeros((n_segments, b + s, eligible[0].features.shape[1]), dtype=np.float32)
        labels = np.zeros((n_segments, b + s, 4), dtype=np.float32)
        mask = np.zeros((n_segments, b + s), dtype=np.float32)
        for row, k in enumerate(picks):
            ep = eligible[int(k)]
            start = int(self._rng.integers(0, ep.features.shape[0] - s + 1))
            w0 = max(0, start - b)
            n = start + s - w0
            feats[row, :n] = ep.features[w0 : start + s]
            labels[row, :n] = ep.labels[w0 : start + s]
            mask[row, start - w0 : n] = 1.0 if ep.weights is None else ep.weights[start : start + s]
        return feats, labels, mask
