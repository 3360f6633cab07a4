"""PPO's update alone, plain PPO against PPO_GoCu, in one process: is PPO_GoCu's policy update cheaper?

    python benchmarks/update_ab.py --env GoCu/DoorKey-8x8-v0 --timesteps 61440 --repeats 8

In ``benchmarks/throughput.py`` runs, plain PPO's ``train()`` took longer in total than PPO_GoCu's (95.6 s against
74.6 s per 100k steps) with the same CNN and minibatches. This script trains both agents for ``--timesteps``
steps, saves each one's policy and optimizer state, then times ``train()`` on each agent's own last rollout
``--repeats`` times, alternating the order and restoring the saved state before every call, so both updates run
on the same machine state, from a fixed starting point, in the same process. 1 torch thread.
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import sys
import time

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PaperCNN, PPO_GoCu

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from throughput import PPO_SETTINGS  # noqa: E402  (the SPEC's PPO settings, as in the throughput runs)


def time_updates(models: dict[str, PPO], repeats: int) -> dict[str, list[float]]:
    """Wall seconds of ``train()`` per model, each call from the model's state at entry, order alternating."""
    saved = {name: (copy.deepcopy(m.policy.state_dict()), copy.deepcopy(m.policy.optimizer.state_dict())) for name, m in models.items()}
    times: dict[str, list[float]] = {name: [] for name in models}
    names = list(models)
    for rep in range(repeats):
        for name in names if rep % 2 == 0 else names[::-1]:
            model = models[name]
            model.policy.load_state_dict(saved[name][0])
            model.policy.optimizer.load_state_dict(saved[name][1])
            t0 = time.perf_counter()
            model.train()
            times[name].append(time.perf_counter() - t0)
    return times


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--timesteps", type=int, default=61440, help="training steps of each agent before the timing")
    p.add_argument("--repeats", type=int, default=8, help="train() calls timed per agent")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.timesteps < 2048 or args.repeats < 1:
        p.error(f"--timesteps must be >= 2048 (one rollout) and --repeats >= 1, got {args.timesteps} and {args.repeats}")
    th.set_num_threads(1)
    print("command: python benchmarks/update_ab.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, torch threads 1, seed {args.seed}")
    ppo = PPO("CnnPolicy", make_vec_env(args.env, n_envs=16, seed=args.seed), seed=args.seed,
              policy_kwargs=dict(features_extractor_class=PaperCNN), **PPO_SETTINGS)
    gocu = PPO_GoCu("CnnPolicy", make_vec_env(args.env, n_envs=16, seed=args.seed), seed=args.seed, **PPO_SETTINGS)
    ppo.learn(args.timesteps)
    gocu.learn(args.timesteps)
    times = time_updates({"plain PPO": ppo, "PPO_GoCu": gocu}, args.repeats)
    for name, t in times.items():
        print(f"{name:10s} train(): median {np.median(t):.3f} s over {len(t)} calls ({', '.join(f'{v:.3f}' for v in t)})")
    print(f"plain PPO / PPO_GoCu (medians): {np.median(times['plain PPO']) / np.median(times['PPO_GoCu']):.3f}")
    return times


if __name__ == "__main__":
    main()
