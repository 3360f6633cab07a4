"""How many epochs the VAE pretraining runs with the module's early stopping (``vae_pretrain_patience``).

    python benchmarks/pretrain_epochs.py --env GoCu/DoorKey-8x8-v0 --seeds 0 1 --threads 1 \
        --curiosity-kwargs '{"vae_pretrain_patience": null}'

With the defaults (``vae_pretrain_patience=0``) the pretraining runs all ``vae_epochs`` epochs and measures no
held-out loss; ``null`` makes it follow ``vae_patience`` (1), the early stopping of the defaults until a69ce69,
which ``benchmarks/results/vae_epochs/pretrain_epochs_doorkey8.txt`` recorded.

For each seed: a PPO_GoCu with the current defaults (16 envs, n_steps 128) learns 2,048 steps, which covers the
random-policy pretraining (``pretrain_steps`` observations, then one VAE update) and one rollout; prints the
pretraining update's epochs run, best epoch, held-out loss and time (``module.stats``). Compare with
``benchmarks/vae_epochs.py --fresh ENV``, which prints the held-out loss of every one of 20 epochs.
"""

import argparse
import json
import math

import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu/ ids)
from sb3_gocu import PPO_GoCu

from sample_efficiency import N_ENVS, machine_line  # noqa: E402  (same directory)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    p.add_argument("--curiosity-kwargs", default="{}", help="JSON dict of GoalCuriosityModule keywords")
    args = p.parse_args()
    th.set_num_threads(args.threads)
    print(f"machine: {machine_line(args.threads)}")
    for seed in args.seeds:
        env = make_vec_env(args.env, n_envs=N_ENVS, seed=seed)
        model = PPO_GoCu("CnnPolicy", env, seed=seed, curiosity_kwargs=json.loads(args.curiosity_kwargs))
        model.learn(2048)
        st = model.curiosity.stats
        held_out = "not measured" if math.isnan(st["vae_val_loss"]) else f"{st['vae_val_loss']:.1f}"  # nan: patience 0
        print(f"seed {seed}: vae_pretrain_patience {model.curiosity.vae_pretrain_patience}, epochs run {st['vae_epochs_run']:.0f} "
              f"(of {model.curiosity.vae_epochs}), best epoch {st['vae_best_epoch']:.0f}, held-out loss {held_out}, "
              f"{st['vae_time']:.1f} s")


if __name__ == "__main__":
    main()
