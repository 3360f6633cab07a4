"""What does a trained agent do on a Sawyer task? Does it move the object, and toward the goal?

    MUJOCO_GL=egl python benchmarks/probes/sawyer_behaviour.py <checkpoints>/ppo_seed0/model_501760.zip --algo ppo \\
        --env GoCu/VisualSawyerPusher-v1 --episodes 60

Loads a PPO or PPO_GoCu model (``sample_efficiency.py``'s checkpoints) and plays ``--episodes`` episodes (seeds 1000
on, goals the training never drew with those seeds), with its stochastic and its deterministic policy. Per episode:
how far the objects moved (each puck's or the ball's centre, metres; the door's angle, radians: the largest over the
objects), the progress (distance at the start minus the final distance, ``info["distance"]``), whether the task ends
solved, and where the hand ends. An agent that moves the object but makes no progress pushes it the same way whatever
the goal: its hand ends at one place (a small spread of the hand's end over the episodes).
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402

from sb3_gocu import PPO_GoCu  # noqa: E402


def object_state(base) -> np.ndarray:
    """The objects' positions (each free joint's but the hand's) and the door's angle, as one vector."""
    parts = [base.data.joint(name).qpos[:3] for name in ("puck", "puck2", "ball") if _has_joint(base, name)]
    if _has_joint(base, "hinge"):
        parts.append(base.data.joint("hinge").qpos[:1])
    return np.concatenate(parts)


def _has_joint(base, name: str) -> bool:
    try:
        base.model.joint(name)
    except KeyError:
        return False
    return True


def play(model, env_id: str, episodes: int, deterministic: bool) -> dict[str, float]:
    """:return: mean object move, mean progress, success rate, the hand's end (mean and spread over the episodes)"""
    env = gym.make(env_id)
    base = env.unwrapped
    moves, progress, solved, hands = [], [], [], []
    for episode in range(episodes):
        obs, info = env.reset(seed=1000 + episode)
        start, start_distance, truncated = object_state(base), info["distance"], False
        while not truncated:
            action, _ = model.predict(obs.transpose(2, 0, 1)[None], deterministic=deterministic)
            obs, _, _, truncated, info = env.step(np.clip(action[0], -1, 1).astype(np.float32))
        delta = object_state(base) - start
        moves.append(np.abs(delta).max() if len(delta) <= 1 else max(np.linalg.norm(delta[i:i + 3]) for i in range(0, len(delta) - 2, 3)))
        progress.append(start_distance - info["distance"])
        solved.append(info["is_success"])
        hands.append(base.hand)
    env.close()
    hands = np.array(hands)
    return {"move": float(np.mean(moves)), "moved": float(np.mean(np.array(moves) > 0.02)), "progress": float(np.mean(progress)),
            "solved": float(np.mean(solved)), "hand_mean": hands.mean(0).round(3).tolist(), "hand_spread": float(hands.std(0).sum())}


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a PPO or PPO_GoCu .zip")
    parser.add_argument("--algo", required=True, choices=["ppo", "ppo_gocu"], help="the model's class")
    parser.add_argument("--env", required=True, help="a GoCu/VisualSawyer*-v1 id")
    parser.add_argument("--episodes", type=int, default=60)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {args.episodes}")
    th.set_num_threads(1)
    model = (PPO_GoCu if args.algo == "ppo_gocu" else PPO).load(args.model, device="cpu")
    print(f"command: python benchmarks/probes/sawyer_behaviour.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    results = {}
    for deterministic in (False, True):
        r = results["deterministic" if deterministic else "stochastic"] = play(model, args.env, args.episodes, deterministic)
        print(f"{'deterministic' if deterministic else 'stochastic'}: object moved > 2 cm in {r['moved']:.2f} of the episodes "
              f"(mean move {r['move']:.3f}), progress to the goal {r['progress']:+.3f}, solved at the end {r['solved']:.2f}, "
              f"hand ends at {r['hand_mean']} (spread {r['hand_spread']:.3f})")
    return results


if __name__ == "__main__":
    main()
