"""rl-zoo3's ``train`` with ``ppo_gocu`` registered: ``python -m sb3_gocu.train --algo ppo_gocu --env GoCu/DoorKey-8x8-v0``.

Every flag is rl-zoo3's (``python -m sb3_gocu.train --help``). Without ``-conf/--conf-file`` the hyperparameters
come from the package's ``sb3_gocu/hyperparams/ppo_gocu.yml`` (``--algo ppo_gocu``) or ``sb3_gocu/hyperparams/ppo.yml``
(``--algo ppo`` on an id it lists); see :func:`sb3_gocu.zoo.default_conf_file`. ``PPO_GoCu.learn`` trains with one
torch thread on a CPU whatever ``--num-threads`` says. Needs the ``[zoo]`` extra and that of the environment
(``[minigrid]``, ``[mujoco]`` or ``[atari]``); a missing one is named before anything trains.
"""

from __future__ import annotations

import argparse
import sys

from sb3_gocu._extras import check_env_extra, missing_extra

try:
    from sb3_gocu.zoo import register_zoo, with_default_conf
except ModuleNotFoundError as e:  # rl-zoo3 and optuna come with the [zoo] extra
    raise missing_extra(e, "sb3_gocu.train", "zoo") from e


def main(argv: list[str] | None = None) -> None:
    """Register ``ppo_gocu``, add our default config file, and run ``rl_zoo3.train.train()``."""
    register_zoo()
    sys.argv = [sys.argv[0], *with_default_conf(sys.argv[1:] if argv is None else argv)]
    check_env_extra(_env_id(sys.argv[1:]))
    from rl_zoo3.train import train

    train()


def _env_id(argv: list[str]) -> str:
    """The ``--env`` of a command line (rl-zoo3's default when absent)."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--env", default="CartPole-v1")
    return parser.parse_known_args(argv)[0].env


if __name__ == "__main__":
    main()
