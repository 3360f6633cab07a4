"""rl-zoo3's ``train`` with ``ppo_gocu`` registered: ``python -m sb3_gocu.train --algo ppo_gocu --env GoCu/DoorKey-8x8-v0``.

Every flag is rl-zoo3's (``python -m sb3_gocu.train --help``). Without ``-conf/--conf-file`` the hyperparameters
come from the repository's ``hyperparams/ppo_gocu.yml`` (``--algo ppo_gocu``) or ``hyperparams/ppo.yml``
(``--algo ppo`` on an id it lists); see :func:`sb3_gocu.zoo.default_conf_file`. ``PPO_GoCu.learn`` trains with one
torch thread on a CPU whatever ``--num-threads`` says.
"""

from __future__ import annotations

import sys

from sb3_gocu.zoo import register_zoo, with_default_conf


def main(argv: list[str] | None = None) -> None:
    """Register ``ppo_gocu``, add our default config file, and run ``rl_zoo3.train.train()``."""
    register_zoo()
    sys.argv = [sys.argv[0], *with_default_conf(sys.argv[1:] if argv is None else argv)]
    from rl_zoo3.train import train

    train()


if __name__ == "__main__":
    main()
