"""What does a trained DoorKey agent do, and what is its curiosity paying for? Agent against a random policy.

    python benchmarks/probes/behaviour.py <run>/checkpoints/ppo_gocu_seed0/model_251904.zip \\
        --env GoCu/DoorKey-8x8-v0 --episodes 6 --seed 100

Plays ``--episodes`` episodes (layouts ``env.reset(seed=--seed + i)``) with the model's stochastic policy and
the same layouts with a uniformly random policy (``numpy`` generator seeded with ``--seed``), and prints for each:

* the action histogram (MiniGrid: 0 left, 1 right, 2 forward, 3 pickup, 4 drop, 5 toggle, 6 done);
* distinct cells visited per episode and the furthest task phase (``info["task_phase"]``: 0 start, 1 key,
  2 door open, 3 goal);
* for a PPO_GoCu model, the mean raw r_gc (eq 13) of the states each policy visits, scored by the model's own
  curiosity module against K goals drawn from its buffer at each episode start (as in training).

An agent whose states pay more r_gc than the random policy's while it visits fewer cells has found a place
where its curiosity stays high without exploring: the diagnosis of the first DoorKey-8x8 runs
(docs/results.md, "The first attempt: paid for standing still").
Prints one block per policy and returns the figures as a dict.
"""

from __future__ import annotations

import argparse
from collections import Counter
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch as th

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PPO_GoCu

ACTIONS = ("left", "right", "forward", "pickup", "drop", "toggle", "done")


def play(model: Any, env_id: str, policy: str, episodes: int, seed: int) -> dict[str, Any]:
    """Play ``episodes`` episodes with ``policy`` (``"agent"`` or ``"random"``) and collect the figures."""
    module = getattr(model, "curiosity", None)
    rng = np.random.default_rng(seed)
    actions: Counter = Counter()
    cells, phases, rewards, returns = [], [], [], []
    env = gym.make(env_id)
    for i in range(episodes):
        obs, info = env.reset(seed=seed + i)
        base = env.unwrapped
        if module is not None:
            env_index = 0
            module.ensure_envs(1)
            module.sample_goals(np.array([env_index]))
        seen: set = {tuple(base.agent_pos)}
        done, ret = False, 0.0
        while not done:
            if policy == "agent":
                action = int(model.predict(obs, deterministic=False)[0])
            else:
                action = int(rng.integers(env.action_space.n))
            actions[action] += 1
            obs, reward, terminated, truncated, info = env.step(action)
            ret += float(reward)
            done = terminated or truncated
            seen.add(tuple(base.agent_pos))
            if module is not None:
                # the module sees observations as the model's env gave them (channel-first after VecTransposeImage)
                x = obs if module.observation_space.shape == obs.shape else np.transpose(obs, (2, 0, 1))
                rewards.append(float(module.score_states(x[None], np.array([env_index]))[0]))
        cells.append(len(seen))
        phases.append(int(info.get("task_phase", -1)))
        returns.append(ret)
    env.close()
    total = sum(actions.values())
    return {
        "policy": policy,
        "action_share": {ACTIONS[a] if a < len(ACTIONS) else str(a): actions[a] / total for a in sorted(actions)},
        "cells_per_episode": cells,
        "phases": phases,
        "returns": returns,
        "mean_raw_r_gc": float(np.mean(rewards)) if rewards else float("nan"),
    }


def report(result: dict[str, Any]) -> str:
    shares = "  ".join(f"{k} {v:.2f}" for k, v in result["action_share"].items())
    return (
        f"{result['policy']:>6}: actions  {shares}\n"
        f"        cells/episode {result['cells_per_episode']} (mean {np.mean(result['cells_per_episode']):.1f})  "
        f"phase per episode {result['phases']}  return {np.mean(result['returns']):.3f}  "
        f"mean raw r_gc {result['mean_raw_r_gc']:.4f}"
    )


def main(argv: Sequence[str] | None = None) -> dict[str, dict[str, Any]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="a PPO_GoCu (or PPO) model zip")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--episodes", type=int, default=6)
    p.add_argument("--seed", type=int, default=100)
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    args = p.parse_args(argv)
    if args.episodes < 1:
        p.error(f"--episodes must be >= 1, got {args.episodes}")
    th.set_num_threads(args.threads)
    try:
        model = PPO_GoCu.load(args.model, device="cpu")
    except (KeyError, ValueError):
        from stable_baselines3 import PPO

        model = PPO.load(args.model, device="cpu")
    print(f"python benchmarks/probes/behaviour.py {args.model} --env {args.env} --episodes {args.episodes} --seed {args.seed}")
    out = {}
    for policy in ("agent", "random"):
        out[policy] = play(model, args.env, policy, args.episodes, args.seed)
        print(report(out[policy]), flush=True)
    return out


if __name__ == "__main__":
    main()
