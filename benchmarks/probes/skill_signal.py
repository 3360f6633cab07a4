"""Does the learned skill signal separate mastered from unmastered states? Measured on saved PPO_GoCu models.

    python benchmarks/probes/skill_signal.py <run>/model_400384.zip [more.zip ...] --env GoCu/DoorKey-8x8-v0 \\
        --episodes 64 --threads 1 [--json out.json]

For each model, plays ``--episodes`` episodes of its own policy (sampled actions, 8 envs, env seeds from
``--seed``) and reports, on what it saw:

1. **The predictor against its labels**, on pairs it never trained on: (s_t, s_{t+y}) within an episode, y uniform
   in 1..d_max, with the distance the training uses (steps to the goal's first visit after s_t), labelled p_skill by
   eq 15-16 with the predictor's own prior, as a predictor update labels them. Accuracy of m > 0.5 against
   p_skill > 0.5, the mean |m - p_skill|, and per distance band the mean m and the mean p_skill: does the predictor
   know which goals are within reach?
2. **The spread of the mastery and of r_gc over the visited states, by phase** of the episode (0: no key, 1: key
   picked up, 2: door opened): for each distinct state, h = the largest mastery over K goals drawn from the goal
   buffer as at an episode start, and r_gc (eq 13); mean, std and the 10th and 90th percentiles. A signal that
   separates mastered from unmastered regions pays the later phases, which the agent has practised least, more.
3. **What the goals cover**: the phase in which the played episodes saw each goal of the buffer (a goal seen in
   several phases counts for the earliest), and the share of goals not seen at all.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecTransposeImage

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.reward import curiosity_reward
from sb3_gocu.curiosity.stores import observation_key

BANDS = ((1, 5), (6, 10), (11, 15), (16, 20), (21, 30))


def play(model: PPO_GoCu, env_id: str, episodes: int, seed: int, n_envs: int = 8) -> list[tuple[np.ndarray, np.ndarray]]:
    """``episodes`` episodes of the model's policy: per episode the raw observations reached and their phases."""
    module = model.curiosity
    venv = VecTransposeImage(make_vec_env(env_id, n_envs=n_envs, seed=seed))  # channels first, as the model was trained
    obs = venv.reset()
    current: list[list[tuple[np.ndarray, int]]] = [[] for _ in range(n_envs)]
    done_episodes: list[tuple[np.ndarray, np.ndarray]] = []
    while len(done_episodes) < episodes:
        actions, _ = model.predict(obs, deterministic=False)
        obs, _, dones, infos = venv.step(actions)
        for i, info in enumerate(infos):
            reached = info["terminal_observation"] if dones[i] else obs[i]
            current[i].append((module.adapter.extract(reached[None])[0], int(info.get("task_phase", 0))))
            if dones[i]:
                done_episodes.append((np.stack([o for o, _ in current[i]]), np.array([p for _, p in current[i]])))
                current[i] = []
    venv.close()
    return done_episodes[:episodes]


def first_visit_distance(keys: list[bytes], t: int, y: int) -> int:
    """Steps from s_t to the first visit of s_{t+y}'s observation after t (as the trajectory store measures it)."""
    goal = keys[t + y]
    return next(k for k in range(y + 1) if keys[t + k] == goal)


@th.no_grad()
def predictor_against_labels(model: PPO_GoCu, episodes: list[tuple[np.ndarray, np.ndarray]], n_pairs: int, rng: np.random.Generator) -> dict[str, Any]:
    module, cfg = model.curiosity, model.curiosity.config
    phi_s, phi_g, dist = [], [], []
    usable = [ep for ep in episodes if len(ep[0]) > 1]
    for _ in range(n_pairs):
        obs, _ = usable[rng.integers(len(usable))]
        y = int(rng.integers(1, min(cfg.max_distance, len(obs) - 1) + 1))
        t = int(rng.integers(0, len(obs) - y))
        keys = [observation_key(o) for o in obs[t : t + y + 1]]
        d = first_visit_distance(keys, 0, y) if cfg.first_visit_distance else y
        phi_s.append(obs[t]), phi_g.append(obs[t + y]), dist.append(d)
    s, g = module.embed(np.stack(phi_s)), module.embed(np.stack(phi_g))
    dist_t = th.tensor(dist, dtype=th.float32)
    module.predictor.eval()
    labels = module.trainer.label_pairs(s, g, dist_t)
    mastery = module.predictor.mastery(s, g)
    out: dict[str, Any] = {
        "pairs": len(dist),
        "accuracy": float(((mastery > 0.5) == (labels > 0.5)).float().mean()),
        "mean_abs_error": float((mastery - labels).abs().mean()),
        "mastered_label_share": float((labels > 0.5).float().mean()),
        "bands": {},
    }
    for lo, hi in BANDS:
        sel = (dist_t >= lo) & (dist_t <= hi)
        if sel.any():
            out["bands"][f"{lo}-{hi}"] = {"pairs": int(sel.sum()), "mastery": float(mastery[sel].mean()), "label": float(labels[sel].mean())}
    return out


@th.no_grad()
def spread_by_phase(model: PPO_GoCu, episodes: list[tuple[np.ndarray, np.ndarray]], rng: np.random.Generator) -> dict[str, Any]:
    module, cfg = model.curiosity, model.curiosity.config
    seen: dict[bytes, tuple[np.ndarray, int]] = {}
    for obs, phases in episodes:
        for o, p in zip(obs, phases):
            seen.setdefault(observation_key(o), (o, int(p)))
    states = np.stack([o for o, _ in seen.values()])
    phases = np.array([p for _, p in seen.values()])
    goals = module.goal_buffer.observations[module.goal_buffer.sample(1, cfg.n_goals, rng)[0]]
    mastery = module.mastery(states, goals)
    h = mastery.max(dim=1).values.numpy()
    reward = curiosity_reward(mastery, cfg.alpha, cfg.aggregation, cfg.reward_scale).numpy()
    out: dict[str, Any] = {}
    for phase in sorted(set(phases.tolist())):
        sel = phases == phase
        out[str(phase)] = {
            "states": int(sel.sum()),
            "h_mean": float(h[sel].mean()), "h_p10": float(np.percentile(h[sel], 10)), "h_p90": float(np.percentile(h[sel], 90)),
            "r_gc_mean": float(reward[sel].mean()), "r_gc_std": float(reward[sel].std()),
            "r_gc_p10": float(np.percentile(reward[sel], 10)), "r_gc_p90": float(np.percentile(reward[sel], 90)),
        }
    return out


def goal_coverage(model: PPO_GoCu, episodes: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    phase_of: dict[bytes, int] = {}
    for obs, phases in episodes:
        for o, p in zip(obs, phases):
            key = observation_key(o)
            phase_of[key] = min(phase_of.get(key, 9), int(p))
    buffer = model.curiosity.goal_buffer
    found = [phase_of.get(observation_key(g)) for g in buffer.observations[: buffer.size]]
    out = {"goals": buffer.size, "not_seen": sum(f is None for f in found) / max(1, len(found))}
    for phase in sorted({f for f in found if f is not None}):
        out[f"phase_{phase}"] = sum(f == phase for f in found) / max(1, len(found))
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--pairs", type=int, default=8192)
    p.add_argument("--seed", type=int, default=1000, help="env seeds and the draws of pairs and goals")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None)
    p.add_argument("--collect", type=int, default=0,
                   help="train each model this many env steps more (16 envs) before probing: a checkpoint taken at a VAE "
                        "update holds a predictor trained on the old embedding, until the next predictor update")
    args = p.parse_args(argv)
    th.set_num_threads(args.threads)
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), platform.processor())
    print("command: python benchmarks/probes/skill_signal.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {cpu}, torch {th.__version__}, {args.threads} thread(s); seed {args.seed}")
    results: dict[str, Any] = {}
    for path in args.models:
        model = PPO_GoCu.load(path, device="cpu")
        if args.collect:
            model.set_env(make_vec_env(args.env, n_envs=16, seed=args.seed + 1))
            model.learn(args.collect, reset_num_timesteps=False)
        rng = np.random.default_rng(args.seed)
        episodes = play(model, args.env, args.episodes, args.seed)
        res = {
            "steps": int(model.num_timesteps),
            "episodes": len(episodes),
            "success": float(np.mean([ph[-1] >= 3 for _, ph in episodes])) if episodes else float("nan"),
            "predictor": predictor_against_labels(model, episodes, args.pairs, rng),
            "phases": spread_by_phase(model, episodes, rng),
            "goals": goal_coverage(model, episodes),
        }
        results[Path(path).name if len(args.models) == 1 else path] = res
        pr = res["predictor"]
        print(f"\n{path} ({res['steps']:,} steps; {res['episodes']} episodes)")
        print(f"  predictor on {pr['pairs']} held-out pairs: accuracy {pr['accuracy']:.3f}, mean |m - p_skill| {pr['mean_abs_error']:.3f}, "
              f"labelled mastered {pr['mastered_label_share']:.3f}")
        for band, b in pr["bands"].items():
            print(f"    distance {band:>5}: {b['pairs']:5d} pairs, mean m {b['mastery']:.3f}, mean p_skill {b['label']:.3f}")
        for phase, f in res["phases"].items():
            print(f"  phase {phase}: {f['states']:5d} states, h {f['h_mean']:.3f} (p10 {f['h_p10']:.3f}, p90 {f['h_p90']:.3f}), "
                  f"r_gc {f['r_gc_mean']:.4f} +- {f['r_gc_std']:.4f} (p10 {f['r_gc_p10']:.4f}, p90 {f['r_gc_p90']:.4f})")
        print("  goals: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in res["goals"].items()))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
