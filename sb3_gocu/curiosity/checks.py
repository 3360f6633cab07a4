"""Type tests of settings, shared by the curiosity module and the adapters around it.

A bare ``isinstance`` gets two cases wrong: ``bool`` is a subclass of ``int`` (so ``True`` would pass as 1), and
numpy's scalars are not Python's (so ``np.int64(3)`` from a config or a sweep would be refused). No
Stable-Baselines3 import.
"""

from __future__ import annotations

import math
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
