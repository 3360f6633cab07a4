"""Steps per second of each registered environment under a random policy (one env, one process).

    MUJOCO_GL=egl python benchmarks/env_speed.py --steps 5000
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym

from sb3_gocu.envs import GOCU_ENV_IDS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ids", nargs="*", default=list(GOCU_ENV_IDS))
    args = parser.parse_args()
    print(f"command: python {' '.join(sys.argv)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, MUJOCO_GL={os.environ['MUJOCO_GL']}, seed {args.seed}")
    for env_id in args.ids:
        env = gym.make(env_id)
        env.reset(seed=args.seed)
        env.action_space.seed(args.seed)
        t0 = time.perf_counter()
        for _ in range(args.steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        rate = args.steps / (time.perf_counter() - t0)
        print(f"{env_id:28s} {rate:8.0f} steps/s")
        env.close()


if __name__ == "__main__":
    main()
