"""rl-zoo3's ``record_video`` with ``ppo_gocu`` registered:
``MUJOCO_GL=egl python -m sb3_gocu.record_video --algo ppo_gocu --env GoCu/DoorKey-8x8-v0 -f logs/ -n 500``.

Every flag is rl-zoo3's (``python -m sb3_gocu.record_video --help``); the video goes to ``<run>/videos/``
unless ``-o`` is given. rl-zoo3 keeps this script's code under ``if __name__ == "__main__"``, so it is run
with :func:`runpy.run_module`.
"""

from __future__ import annotations

import runpy
import sys

from sb3_gocu._extras import missing_extra

try:
    from sb3_gocu.zoo import register_zoo
except ModuleNotFoundError as e:  # rl-zoo3 and optuna come with the [zoo] extra
    raise missing_extra(e, "sb3_gocu.record_video", "zoo") from e


def main(argv: list[str] | None = None) -> None:
    """Register ``ppo_gocu`` and run ``rl_zoo3.record_video`` as a script."""
    register_zoo()
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    runpy.run_module("rl_zoo3.record_video", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
