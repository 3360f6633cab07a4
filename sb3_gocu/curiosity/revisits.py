"""What counts as a revisit: the cell a state falls in, chosen per env from the random-policy observations.

The first-visit rule (``revisit_decay``) pays r_gc for the first visit of a state in an episode. "The same state" is
the same *cell*, Go-Explore's coarse view of an observation, not the same bytes: Atari and robot-arm frames almost
never repeat byte for byte, so a byte key never sees a revisit there and the agent is paid for standing still.

* Images (:class:`ImageCell`): the newest frame in grey (the last channel of a grey frame stack, the last three of an
  RGB one), area-averaged to W x H pixels, quantised to L levels.
* Vectors (:class:`SimHashCell`): SimHash (#Exploration, Tang et al. 2017) of the standardised vector, the sides of
  k fixed random hyperplanes (each with a random offset, so that a cell sees a vector's size as well as its
  direction). Quantising each entry instead cannot reach the target share on 11 or more entries (Hopper 0.42,
  HalfCheetah 0.96 at its coarsest, 2 levels), where k bits can (docs/results.md).

:func:`choose_cell` picks the parameters from the random-policy episodes that pretrain the VAE: the candidate whose
*first-visit share* (the share of steps whose cell is new in its episode) lies nearest :data:`TARGET_SHARE`, the
share of DoorKey's byte key, on which the rule was measured; among equal shares the finer cell. Before the choice
(:func:`first_cell`) an image's cell is the whole frame in 16 levels. No SB3 import.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Union

import numpy as np
import torch as th

#: the first-visit share :func:`choose_cell` aims at: DoorKey-8x8's under a random policy (0.117)
TARGET_SHARE = 0.12
#: cell sizes tried for images (Go-Explore's 11 x 8 among them), each kept within the frame, and the whole frame
CELL_SIZES = ((4, 3), (6, 4), (8, 6), (11, 8), (16, 12), (22, 16), (32, 24), (45, 34), (64, 48))
#: grey levels tried for images
CELL_LEVELS = (4, 8, 16)
#: SimHash bits tried for vectors
SIMHASH_BITS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)
#: Go-Explore's cell (W, H, L), used where the random policy gave fewer than :data:`MIN_CALIBRATION_STEPS` observations
DEFAULT_CELL = (11, 8, 8)
#: SimHash bits used until then
DEFAULT_SIMHASH_BITS = 16
#: seed of SimHash's projections (fixed: a cell's key depends on its parameters alone)
SIMHASH_SEED = 0
#: fewest random-policy observations to choose from; fewer keep the default cell
MIN_CALIBRATION_STEPS = 1000
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of area averaging: output pixel j is the mean of the input over [j s, (j + 1) s), s = n_in / n_out."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    i = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, i + 1) - np.maximum(lo, i), 0.0, None)
    return (overlap / (n_in / n_out)).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class ImageCell:
    """The cell of an image: its newest frame in grey, area-averaged to ``width`` x ``height``, in ``levels`` levels.

    :param layout: the raw batch's layout, "hw", "hwc" or "chw" (:class:`~sb3_gocu.curiosity.ObservationAdapter`)
    :param scale: the value of white (255 for uint8 images)
    :param frame_size: (height, width) of the raw image
    :param width: W, cell pixels across
    :param height: H, cell pixels down
    :param levels: L, grey levels
    """

    layout: str
    scale: float
    frame_size: tuple[int, int]
    width: int
    height: int
    levels: int

    def __post_init__(self) -> None:
        h, w = self.frame_size
        if not (1 <= self.width <= w and 1 <= self.height <= h and 2 <= self.levels <= 256):
            raise ValueError(f"a cell must be 1..{w} pixels across, 1..{h} down and have 2..256 levels, got "
                             f"{self.width} x {self.height}, {self.levels} levels")
        object.__setattr__(self, "_rows", _area_weights(h, self.height))
        object.__setattr__(self, "_cols", _area_weights(w, self.width).T.copy())

    def grey(self, raw: np.ndarray) -> np.ndarray:
        """The newest frame of each raw image in grey, (n, H, W) float32 in [0, 1]."""
        x = raw[..., None] if self.layout == "hw" else np.moveaxis(raw, 1, -1) if self.layout == "chw" else raw
        c = x.shape[-1]
        g = x[..., -3:].astype(np.float32) @ _LUMA if c % 3 == 0 else x[..., -1].astype(np.float32)
        return g / np.float32(self.scale)

    def cells(self, raw: np.ndarray) -> np.ndarray:
        """The cells of a raw batch, (n, height, width) uint8."""
        small = np.nan_to_num(self._rows @ self.grey(raw) @ self._cols)
        return np.clip(np.floor(small * self.levels), 0, self.levels - 1).astype(np.uint8)

    def __call__(self, raw: np.ndarray) -> list[bytes]:
        """The key of each observation of a raw batch."""
        return [c.tobytes() for c in self.cells(raw)]

    def describe(self) -> str:
        return f"{self.width}x{self.height} pixels, {self.levels} grey levels"

    def state_dict(self) -> dict[str, Any]:
        return {"kind": "image", "width": self.width, "height": self.height, "levels": self.levels}


@dataclasses.dataclass(frozen=True, eq=False)
class SimHashCell:
    """The cell of a vector: which side of ``bits`` random hyperplanes its standardised entries lie (SimHash, with
    offsets: the sign of ``a . z + b`` for Gaussian a and b).

    :param mean: subtracted from each entry
    :param scale: each entry is divided by it (> 0)
    :param bits: k, hyperplanes (1..64): the first k columns of a fixed seeded Gaussian matrix, its last row the offsets
    """

    mean: np.ndarray
    scale: np.ndarray
    bits: int

    def __post_init__(self) -> None:
        if not 1 <= self.bits <= max(SIMHASH_BITS):
            raise ValueError(f"a SimHash cell needs 1..{max(SIMHASH_BITS)} bits, got {self.bits}")
        d = int(np.asarray(self.mean).size)
        projection = np.random.default_rng(SIMHASH_SEED).standard_normal((d + 1, max(SIMHASH_BITS)))[:, : self.bits]
        object.__setattr__(self, "_projection", projection)

    def cells(self, raw: np.ndarray) -> np.ndarray:
        """The cells of a raw batch, (n, ceil(bits / 8)) uint8 (the sign bits, packed)."""
        raw = np.asarray(raw, dtype=np.float64)
        z = np.nan_to_num((raw.reshape(len(raw), int(np.prod(raw.shape[1:]))) - self.mean) / self.scale)
        return np.packbits(z @ self._projection[:-1] + self._projection[-1] > 0, axis=1)

    def __call__(self, raw: np.ndarray) -> list[bytes]:
        return [c.tobytes() for c in self.cells(raw)]

    def describe(self) -> str:
        return f"SimHash of {self.bits} bits"

    def state_dict(self) -> dict[str, Any]:
        return {"kind": "simhash", "mean": th.as_tensor(np.asarray(self.mean, dtype=np.float64)),
                "scale": th.as_tensor(np.asarray(self.scale, dtype=np.float64)), "bits": self.bits}


Cell = Union[ImageCell, SimHashCell]


def first_visit_mask(keys: list[bytes], episode_ids: np.ndarray) -> np.ndarray:
    """Whether each step's key is new in its episode (the steps where the first-visit rule pays).

    :param keys: the key of each step, in step order within each episode
    :param episode_ids: the episode of each step (steps of several envs may interleave)"""
    seen: dict[int, set] = {}
    new = np.zeros(len(keys), dtype=bool)
    for i, (key, episode) in enumerate(zip(keys, np.asarray(episode_ids).tolist())):
        visited = seen.setdefault(episode, set())
        if key not in visited:
            visited.add(key)
            new[i] = True
    return new


def first_visit_share(keys: list[bytes], episode_ids: np.ndarray) -> float:
    """The share of steps whose key is new in its episode; see :func:`first_visit_mask`."""
    return float(first_visit_mask(keys, episode_ids).mean()) if len(keys) else float("nan")


def default_cell(layout: str, scale: float, raw_shape: tuple[int, ...], low: np.ndarray | None = None,
                 high: np.ndarray | None = None) -> Cell:
    """The cell used before one is chosen: Go-Explore's 11 x 8 pixels and 8 levels (within the frame) for images;
    for vectors SimHash of 16 bits, each entry standardised by the middle and half-width of ``low`` and ``high`` (where
    either is not finite, by 0 and 1)."""
    if layout == "vector":
        low = np.broadcast_to(np.asarray(-1.0 if low is None else low, dtype=np.float64), raw_shape).ravel()
        high = np.broadcast_to(np.asarray(1.0 if high is None else high, dtype=np.float64), raw_shape).ravel()
        finite = np.isfinite(low) & np.isfinite(high) & (high > low)
        return SimHashCell(np.where(finite, (low + high) / 2, 0.0), np.where(finite, (high - low) / 2, 1.0), DEFAULT_SIMHASH_BITS)
    h, w = _frame_size(layout, raw_shape)
    width, height, levels = DEFAULT_CELL
    return ImageCell(layout, scale, (h, w), min(width, w), min(height, h), levels)


def first_cell(layout: str, scale: float, raw_shape: tuple[int, ...], low: np.ndarray | None = None,
               high: np.ndarray | None = None) -> Cell:
    """The cell the rule counts with before one is chosen (the pretraining's random steps): for images the finest
    candidate, the whole frame in 16 levels, which on DoorKey tells apart exactly what the bytes do; for vectors the
    default cell."""
    if layout == "vector":
        return default_cell(layout, scale, raw_shape, low, high)
    return candidates(layout, scale, raw_shape)[-1]


def _frame_size(layout: str, raw_shape: tuple[int, ...]) -> tuple[int, int]:
    return (raw_shape[0], raw_shape[1]) if layout in ("hw", "hwc") else (raw_shape[1], raw_shape[2])


def candidates(layout: str, scale: float, raw_shape: tuple[int, ...], mean: np.ndarray | None = None,
               std: np.ndarray | None = None) -> list[Cell]:
    """The cells :func:`choose_cell` tries, coarsest first (vectors: standardised by ``mean`` and ``std``)."""
    if layout == "vector":
        assert mean is not None and std is not None
        return [SimHashCell(mean, np.where(std > 0, std, 1.0), bits) for bits in SIMHASH_BITS]
    h, w = _frame_size(layout, raw_shape)
    sizes = sorted({(min(cw, w), min(ch, h)) for cw, ch in CELL_SIZES} | {(w, h)}, key=lambda s: s[0] * s[1])
    return [ImageCell(layout, scale, (h, w), cw, ch, levels) for cw, ch in sizes for levels in CELL_LEVELS]


def choose_cell(raw: np.ndarray, episode_ids: np.ndarray, layout: str, scale: float) -> tuple[Cell, dict[str, float]]:
    """The cell whose first-visit share on ``raw`` lies nearest :data:`TARGET_SHARE` (by ratio); among equal shares,
    the finer. With fewer than :data:`MIN_CALIBRATION_STEPS` observations, the default cell.

    :param raw: random-policy observations, as the module keeps them
    :param episode_ids: the episode of each
    :param layout: "hw", "hwc", "chw" or "vector"
    :param scale: the value of white, for images
    :return: the cell, and what it measured: ``revisit_share`` (its first-visit share on ``raw``) and
        ``revisit_calibration_steps``
    """
    raw_shape = tuple(raw.shape[1:])
    if len(raw) < MIN_CALIBRATION_STEPS:
        cell = default_cell(layout, scale, raw_shape)
        return cell, {"revisit_share": first_visit_share(cell(raw), episode_ids), "revisit_calibration_steps": float(len(raw))}
    mean = std = None
    if layout == "vector":
        flat = np.asarray(raw, dtype=np.float64).reshape(len(raw), int(np.prod(raw_shape)))
        mean, std = flat.mean(axis=0), flat.std(axis=0)
    best, best_rank, best_share = None, None, 0.0
    for fineness, cell in enumerate(candidates(layout, scale, raw_shape, mean, std)):
        share = first_visit_share(cell(raw), episode_ids)
        rank = (round(abs(math.log(max(share, 1e-9) / TARGET_SHARE)), 6), -fineness)
        if best_rank is None or rank < best_rank:
            best, best_rank, best_share = cell, rank, share
    assert best is not None
    return best, {"revisit_share": best_share, "revisit_calibration_steps": float(len(raw))}


def cell_from_state(state: dict[str, Any], layout: str, scale: float, raw_shape: tuple[int, ...]) -> Cell:
    """The cell a :meth:`ImageCell.state_dict` or :meth:`SimHashCell.state_dict` describes."""
    if state["kind"] == "simhash":
        return SimHashCell(state["mean"].numpy(), state["scale"].numpy(), int(state["bits"]))
    return ImageCell(layout, scale, _frame_size(layout, raw_shape), int(state["width"]), int(state["height"]), int(state["levels"]))


class Calibration:
    """The random-policy observations of the pretraining, with their episodes, that :func:`choose_cell` chooses from.

    :param capacity: the most observations kept (the pretraining's ``pretrain_steps``)
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.observations: list[np.ndarray] = []
        self.episode_ids: list[np.ndarray] = []
        self.size = 0

    def add(self, raw: np.ndarray, episode_ids: np.ndarray) -> None:
        take = min(len(raw), self.capacity - self.size)
        if take > 0:
            self.observations.append(raw[:take].copy())
            self.episode_ids.append(np.asarray(episode_ids[:take]).copy())
            self.size += take

    def choose(self, layout: str, scale: float, raw_shape: tuple[int, ...]) -> tuple[Cell, dict[str, float]]:
        """:func:`choose_cell` on what was kept; empties the store."""
        raw = np.concatenate(self.observations) if self.observations else np.zeros((0, *raw_shape))
        ids = np.concatenate(self.episode_ids) if self.episode_ids else np.zeros(0, dtype=np.int64)
        self.observations, self.episode_ids, self.size = [], [], 0
        return choose_cell(raw, ids, layout, scale)
