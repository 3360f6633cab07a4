"""Type tests of settings, shared by the curiosity module and the adapters around it.

A bare ``isinstance`` gets two cases wrong: ``bool`` is a subclass of ``int`` (so ``True`` would pass as 1), and
numpy's scalars are not Python's (so ``np.int64(3)`` from a config or a sweep would be refused). No
Stable-Baselines3 import.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np


def is_integer(value: Any) -> bool:
    """Whether ``value`` is an integer (Python's or numpy's), and not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_number(value: Any) -> bool:
    """Whether ``value`` is a real number (an integer or a float, Python's or numpy's), and not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def is_flag(value: Any) -> bool:
    """Whether ``value`` is True or False (Python's or numpy's bool; not 0, 1 or a string)."""
    return isinstance(value, (bool, np.bool_))


def check(condition: bool, message: str) -> None:
    """Raise ``ValueError(message)`` unless ``condition``."""
    if not condition:
        raise ValueError(message)


#: sigma, the weight of the curiosity reward (wrappers, ``mode="sum"``) or advantage (PPO_GoCu, eq 10), by default
DEFAULT_INTRINSIC_COEF = 0.25


def check_intrinsic_coef(value: Any) -> float:
    """``value`` as sigma, the weight of the curiosity reward or advantage; a ``ValueError`` unless a finite number >= 0."""
    check(is_number(value) and math.isfinite(value) and value >= 0, f"intrinsic_coef (sigma) must be a finite number >= 0, got {value!r}")
    return float(value)


def available_memory() -> int | None:
    """Bytes of memory available now: psutil's ``virtual_memory().available`` (as SB3's replay buffers read it), else the
    available pages the OS reports; None where neither can tell."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def check_memory(stores: dict[str, tuple[str, int]], available: int | None = None) -> None:
    """Refuse settings whose stores would not fit in the memory available, before they are allocated.

    :param stores: for each store, the setting that sizes it (as ``"name=value"``) and the bytes it would take
    :param available: bytes available (default: :func:`available_memory`; no check where it cannot tell)
    :raises ValueError: naming the setting of the largest store, the bytes all the stores would need and the memory
        available
    """
    available = available_memory() if available is None else available
    total = sum(size for _, size in stores.values())
    if available is None or total <= available:
        return
    store, (setting, size) = max(stores.items(), key=lambda item: item[1][1])
    raise ValueError(f"{setting}: the curiosity module's stores would need {total / 1e9:.2f} GB ({store}: {size / 1e9:.2f} GB), "
                     f"more than the {available / 1e9:.2f} GB of memory available; lower {setting.split('=')[0]}")
