"""How GoCu reads an observation space: which entry it embeds, and how a batch becomes a float tensor.

No Stable-Baselines3 import: this file only knows gymnasium spaces, numpy and torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

#: the longest image side GoCu keeps: larger images are averaged down (see :class:`ObservationAdapter`)
MAX_IMAGE_SIDE = 64

SUPPORTED_SPACES = (
    "Box images (H, W), (H, W, C) or (C, H, W) with C in {1, 3, 4} (uint8 or float), "
    "1-D Box vectors, or a Dict holding at least one such image or vector entry"
)


def _image_layout(box: spaces.Box) -> str | None:
    """Return "hwc", "chw", "hw" for an image-like Box, or None for a vector."""
    shape = box.shape
    if len(shape) == 2:
        return "hw"
    if len(shape) == 3:
        if shape[-1] in (1, 3, 4) or (shape[-1] <= 16 and shape[0] > 16):
            return "hwc"
        if shape[0] in (1, 3, 4) or (shape[0] <= 16 and shape[-1] > 16):
            return "chw"
    return None


@dataclass
class ObservationAdapter:
    """Turns raw observations of one space into what the VAE embeds.

    :param observation_space: the environment's observation space
    :param obs_key: for a ``Dict`` space, the entry to embed (default: the first image entry, else the
        first vector entry)
    :param image_channels: keep only the last ``image_channels`` channels of an image (the newest frame
        of a frame stack, e.g. 1 for Atari's 4 stacked grey frames); ``None`` keeps all channels

    Images whose longer side exceeds :data:`MAX_IMAGE_SIDE` pixels are averaged over f x f blocks, f the smallest
    integer that brings that side within it (rows and columns beyond a whole block are dropped), before GoCu keeps
    and embeds them: Atari's 84x84 frames become 42x42, on which the paper's VAE (whose dense layer grows with the
    image's area) trains about 4x faster; 32x32 views are kept as they are.
    """

    observation_space: spaces.Space
    obs_key: str | None = None
    image_channels: int | None = None

    def __post_init__(self) -> None:
        space = self.observation_space
        if isinstance(space, spaces.Dict):
            if self.obs_key is None:
                boxes = {k: s for k, s in space.spaces.items() if isinstance(s, spaces.Box)}
                images = [k for k, s in boxes.items() if _image_layout(s) is not None]
                vectors = [k for k, s in boxes.items() if len(s.shape) == 1]
                if images:
                    self.obs_key = images[0]
                elif vectors:
                    self.obs_key = vectors[0]
                else:
                    raise ValueError(
                        f"observation_space: GoCu cannot embed {space}: the Dict has no image or vector entry. "
                        f"Supported: {SUPPORTED_SPACES}."
                    )
            elif self.obs_key not in space.spaces:
                raise ValueError(f"obs_key={self.obs_key!r} is not an entry of the Dict space (entries: {list(space.spaces)})")
            box = space.spaces[self.obs_key]
        else:
            if self.obs_key is not None:
                raise ValueError("obs_key is only valid for a Dict observation space")
            box = space
        if not isinstance(box, spaces.Box):
            raise ValueError(f"observation_space: GoCu cannot embed {box}. Supported: {SUPPORTED_SPACES}.")
        self.box = box
        layout = _image_layout(box)
        if layout is None and len(box.shape) != 1:
            raise ValueError(f"observation_space: GoCu cannot embed a Box of shape {box.shape}. Supported: {SUPPORTED_SPACES}.")
        self.layout = layout or "vector"
        self.is_image = layout is not None
        if self.is_image:
            if layout == "hw":
                c, h, w = 1, box.shape[0], box.shape[1]
            elif layout == "hwc":
                h, w, c = box.shape
            else:
                c, h, w = box.shape
            if self.image_channels is not None:
                if not 1 <= self.image_channels <= c:
                    raise ValueError(f"image_channels must be in [1, {c}] for this space, got {self.image_channels}")
                c = self.image_channels
            #: the block side images are averaged over (1: kept as they are)
            self.image_downsample = -(-max(h, w) // MAX_IMAGE_SIDE)
            if min(h, w) < self.image_downsample:
                raise ValueError(f"observation_space: a {h}x{w} image would keep no pixel of its shorter side once averaged "
                                 f"over {self.image_downsample}x{self.image_downsample} blocks (images longer than "
                                 f"{MAX_IMAGE_SIDE} pixels are): give GoCu images at least that many pixels a side")
            h, w = h // self.image_downsample, w // self.image_downsample
            self.input_shape: tuple[int, ...] = (c, h, w)
        else:
            if self.image_channels is not None:
                raise ValueError("image_channels is only valid for image observations")
            self.image_downsample = 1
            self.input_shape = (int(box.shape[0]),)
        # The stored raw form keeps the space's dtype (uint8 images stay uint8).
        self.raw_dtype = box.dtype
        self.raw_shape = self._raw_shape()
        if box.dtype == np.uint8:
            self.scale = 255.0
        else:
            low, high = np.asarray(box.low, dtype=np.float64), np.asarray(box.high, dtype=np.float64)
            if self.is_image and not (np.isfinite(low).all() and np.isfinite(high).all() and low.min() >= 0):
                raise ValueError(
                    f"observation_space: a {box.dtype} image Box needs finite bounds with low >= 0 (GoCu divides it "
                    f"by its largest high into [0, 1], the range of the VAE's image loss), got low in [{low.min()}, "
                    f"{low.max()}] and high in [{high.min()}, {high.max()}]: give finite bounds such as Box(0, 1) or "
                    "Box(0, 255), or a uint8 space"
                )
            finite_high = high[np.isfinite(high)]
            self.scale = float(finite_high.max()) if self.is_image and finite_high.size and finite_high.max() > 1 else 1.0

    def _raw_shape(self) -> tuple[int, ...]:
        if not self.is_image:
            return tuple(self.box.shape)
        c, h, w = self.input_shape
        return {"hw": (h, w), "hwc": (h, w, c), "chw": (c, h, w)}[self.layout]

    def extract(self, obs: Any) -> np.ndarray:
        """The raw batch GoCu keeps (memory bank, goals): the embedded entry, newest channels only, downsampled
        (block means, rounded back to the space's dtype for integer images)."""
        x = obs[self.obs_key] if self.obs_key is not None else obs
        x = np.asarray(x)
        if self.is_image and self.image_channels is not None:
            x = x[..., -self.image_channels :] if self.layout == "hwc" else x[:, -self.image_channels :]
        f = self.image_downsample
        if self.is_image and f > 1:
            n = x.shape[0]
            if self.layout == "chw":
                c, h, w = self.input_shape
                x = x[:, :, : h * f, : w * f].reshape(n, c, h, f, w, f).mean(axis=(3, 5), dtype=np.float32)
            else:
                _, h, w = self.input_shape
                x = x[:, : h * f, : w * f].reshape(n, h, f, w, f, *x.shape[3:]).mean(axis=(2, 4), dtype=np.float32)
            x = np.rint(x).astype(self.raw_dtype) if np.issubdtype(self.raw_dtype, np.integer) else x.astype(self.raw_dtype)
        return x

    def to_tensor(self, raw: np.ndarray | th.Tensor, device: th.device | str = "cpu") -> th.Tensor:
        """A raw batch (as returned by :meth:`extract`) as a float tensor (n, C, H, W) or (n, D)."""
        if self.is_image and isinstance(raw, np.ndarray) and th.device(device).type == "cpu":
            # the same values to the bit as the torch path below, in numpy: one copy instead of torch's several
            y = raw[:, None] if self.layout == "hw" else raw.transpose(0, 3, 1, 2) if self.layout == "hwc" else raw
            y = np.ascontiguousarray(y, dtype=np.float32)
            if self.scale != 1.0:
                y /= np.float32(self.scale)
            return th.from_numpy(y)
        x = th.as_tensor(raw, device=device)
        if self.is_image:
            if self.layout == "hw":
                x = x.unsqueeze(1)
            elif self.layout == "hwc":
                x = x.permute(0, 3, 1, 2)
            x = x.float()
            if self.scale != 1.0:
                x = x / self.scale
            return x.contiguous()
        return x.float().reshape(x.shape[0], -1)
