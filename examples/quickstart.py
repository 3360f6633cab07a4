"""Quickstart: PPO_GoCu on MiniGrid DoorKey-5x5 (32x32 RGB partial view), paper hyperparameters.

    python examples/quickstart.py                 # 300k steps, ~10 min on a 2-core CPU
    python examples/quickstart.py --timesteps 50000 --eval-episodes 20

Trains with SB3's progress bar, evaluates the success rate of the trained policy, and saves the model
(curiosity state included) to ``gocu_doorkey5.zip``.
"""

from __future__ import annotations

import argparse

import numpy as np
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_gocu import PPO_GoCu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-5x5-v0")
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--save", default="gocu_doorkey5")
    args = parser.parse_args()

    env = make_vec_env(args.env, n_envs=16, seed=args.seed)
    model = PPO_GoCu(
        "CnnPolicy",
        env,
        n_steps=128,
        batch_size=256,
        n_epochs=4,
        learning_rate=1e-4,
        ent_coef=0.01,
        gamma=0.99,
        vf_coef=0.5,
        clip_range=0.2,
        intrinsic_coef=0.25,  # sigma, eq 10
        curiosity_kwargs=dict(n_goals=50, goal_buffer_size=1500, goal_strategy="proportional", reward_scale=10.0),
        seed=args.seed,
        verbose=1,
    )
    model.learn(args.timesteps, progress_bar=True)
    model.save(args.save)
    print(f"saved {args.save}.zip")

    eval_env = make_vec_env(args.env, n_envs=1, seed=args.seed + 1000)
    returns, _ = evaluate_policy(model, eval_env, n_eval_episodes=args.eval_episodes, deterministic=False, return_episode_rewards=True)
    returns = np.asarray(returns)
    print(f"evaluation over {len(returns)} episodes: success rate {np.mean(returns > 0):.2f}, mean return {returns.mean():.3f}")


if __name__ == "__main__":
    main()
