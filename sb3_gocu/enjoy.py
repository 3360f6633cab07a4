"""rl-zoo3's ``enjoy`` with ``ppo_gocu`` registered: ``python -m sb3_gocu.enjoy --algo ppo_gocu --env GoCu/DoorKey-8x8-v0 -f logs/``.

Every flag is rl-zoo3's (``python -m sb3_gocu.enjoy --help``). The model is loaded by ``PPO_GoCu.load(...,
curiosity=False)``: acting needs the policy alone, so the file's curiosity state is not read. The env is built from
the run's saved ``config.yml``, as the zoo does.
"""

from __future__ import annotations

import sys
from typing import Any

from sb3_gocu import PPO_GoCu
from sb3_gocu._extras import missing_extra

try:
    from sb3_gocu.zoo import register_zoo
except ModuleNotFoundError as e:  # rl-zoo3 and optuna come with the [zoo] extra
    raise missing_extra(e, "sb3_gocu.enjoy", "zoo") from e


class ActingPPO_GoCu(PPO_GoCu):
    """PPO_GoCu whose ``load`` leaves the curiosity state unread (what ``enjoy`` registers as ``ppo_gocu``)."""

    @classmethod
    def load(cls, *args: Any, **kwargs: Any) -> PPO_GoCu:  # type: ignore[override]
        kwargs.setdefault("curiosity", False)
        return super().load(*args, **kwargs)


def main(argv: list[str] | None = None) -> None:
    """Register ``ppo_gocu`` (loading the policy alone) and run ``rl_zoo3.enjoy.enjoy()``."""
    register_zoo(ActingPPO_GoCu)
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    from rl_zoo3.enjoy import enjoy

    enjoy()


if __name__ == "__main__":
    main()
