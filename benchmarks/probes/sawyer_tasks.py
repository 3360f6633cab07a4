"""The Sawyer tasks' reference figures: the scripted policy's success and the final distance of it and of a random policy.

    MUJOCO_GL=egl python benchmarks/probes/sawyer_tasks.py --episodes 100

For each ``GoCu/VisualSawyer*-v1`` id, ``--episodes`` episodes of the task's scripted policy
(``task.expert_action``, from the simulator's state) and as many of a uniform random policy, seeds ``--seed`` on:
the fraction of episodes that end in success (``info["is_success"]`` at the last step), the fraction with a success
step, and the final distance (``info["distance"]`` at the last step, Table 2's measure), mean over the episodes.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import sb3_gocu.envs  # noqa: E402,F401  (registers the ids)
from sb3_gocu.envs import SAWYER_IDS  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from run_records import cpu_model  # noqa: E402


def episodes(env_id: str, policy: str, n: int, seed: int) -> dict[str, float]:
    """``n`` episodes of ``policy`` ("expert" or "random"). :return: ends in success, any success, final distance"""
    env = gym.make(env_id)
    base = env.unwrapped
    env.action_space.seed(seed)
    ends, anys, finals = [], [], []
    for episode in range(n):
        env.reset(seed=seed + episode)
        truncated, success = False, False
        while not truncated:
            action = base.task.expert_action(base).astype(np.float32) if policy == "expert" else env.action_space.sample()
            _, _, _, truncated, info = env.step(action)
            success |= info["is_success"]
        ends.append(info["is_success"])
        anys.append(success)
        finals.append(info["distance"])
    env.close()
    return {"ends": float(np.mean(ends)), "any": float(np.mean(anys)), "final": float(np.mean(finals))}


def main(argv: list[str] | None = None) -> dict[str, dict[str, dict[str, float]]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ids", nargs="*", default=list(SAWYER_IDS))
    args = parser.parse_args(argv)
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    print(f"command: python benchmarks/probes/sawyer_tasks.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"machine: {cpu_model()}; seeds {args.seed}-{args.seed + args.episodes - 1}")
    print("| task | scripted: ends in success / any success / final distance | random: ends in success / any success / final distance |")
    print("| --- | --- | --- |")
    results = {}
    for env_id in args.ids:
        results[env_id] = {policy: episodes(env_id, policy, args.episodes, args.seed) for policy in ("expert", "random")}
        cells = [f"{r['ends']:.2f} / {r['any']:.2f} / {r['final']:.3f}" for r in results[env_id].values()]
        print(f"| {env_id} | {cells[0]} | {cells[1]} |")
    return results


if __name__ == "__main__":
    main()
