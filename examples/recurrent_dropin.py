"""GoCu dropped into an sb3-contrib algorithm: RecurrentPPO (an LSTM policy) on MiniGrid DoorKey, no PPO_GoCu.

    python examples/recurrent_dropin.py                       # DoorKey-5x5, 300k steps
    python examples/recurrent_dropin.py --timesteps 50000 --eval-episodes 20

The algorithm is untouched: the env is wrapped in ``GoCuVecEnvWrapper(mode="sum")``, whose reward is
``r_e + 0.25 * (r_gc - its running mean)``, and ``GoCuCallback`` trains the curiosity module (pretraining the VAE
on random-policy steps before the first rollout). Any SB3 or sb3-contrib algorithm takes the two the same way
(QRDQN, TRPO, ...). The evaluation env has no wrapper: its returns are extrinsic. Saves the policy to
``recurrent_gocu_doorkey5.zip`` (the curiosity module lives in the wrapper and is not saved with it).
"""

from __future__ import annotations

import argparse
from typing import Sequence

import numpy as np
from sb3_contrib import RecurrentPPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_gocu import PAPER_N_ENVS, PAPER_PPO_KWARGS, GoCuCallback, GoCuVecEnvWrapper, PaperCNN


def main(argv: Sequence[str] | None = None) -> tuple[RecurrentPPO, np.ndarray]:
    """Train, save and evaluate; returns the model and the evaluation episodes' returns."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-5x5-v0")
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--save", default="recurrent_gocu_doorkey5")
    args = parser.parse_args(argv)

    env = GoCuVecEnvWrapper(make_vec_env(args.env, n_envs=PAPER_N_ENVS, seed=args.seed), mode="sum")
    model = RecurrentPPO(
        "CnnLstmPolicy", env, seed=args.seed, verbose=1, policy_kwargs=dict(features_extractor_class=PaperCNN), **PAPER_PPO_KWARGS
    )
    model.learn(args.timesteps, callback=GoCuCallback(), progress_bar=True)
    model.save(args.save)
    print(f"saved {args.save}.zip")

    eval_env = make_vec_env(args.env, n_envs=1, seed=args.seed + 1000)
    returns, _ = evaluate_policy(model, eval_env, n_eval_episodes=args.eval_episodes, deterministic=False, return_episode_rewards=True)
    returns = np.asarray(returns)
    print(f"evaluation over {len(returns)} episodes: success rate {np.mean(returns > 0):.2f}, mean return {returns.mean():.3f}")
    return model, returns


if __name__ == "__main__":
    main()
