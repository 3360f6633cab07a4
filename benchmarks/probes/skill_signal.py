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
2. **r_gc by phase, and which phase the agent has mastered least.** Each step is put in a phase of DoorKey: 0 no
   key, 1 key held, 2 door open (the agent still on the key's side of the wall), 3 goal room (beyond the wall); a
   phase's *mastery* is the share of the episodes that reach it and go on to the next (the goal room: to the goal).
   For each step that the first-visit rule pays (its revisit cell new in its episode), h against K goals drawn from
   the goal buffer once per episode, as at an episode start, and r_gc (eq 13); per phase the mean r_gc, its std,
   and the share of steps where h saturates (above :data:`SATURATION`). The signal works when r_gc ranks the least
   mastered phase (of those reached by at least :data:`MIN_PHASE_SHARE` of the episodes) first. The same is
   reported for other h of the same mastery (:data:`AGGREGATES`, on the same goals and steps, offline: no run
   learned with them), so that a design is measured before a learning run is spent on it; and likewise for other
   sources of the K goals (:data:`GOAL_DESIGNS`: the buffer spread out in phi, or the states of recent episodes).
3. **What the goals cover**: the phase in which the played episodes saw each goal of the buffer (a goal seen in
   several phases counts for the earliest), and the share of goals not seen at all.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
from minigrid.core.world_object import Door
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecTransposeImage

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.revisits import first_visit_mask
from sb3_gocu.curiosity.stores import observation_key

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402

BANDS = ((1, 5), (6, 10), (11, 15), (16, 20), (21, 30))
#: the phases of a step (``info["task_phase"]``, with the door-open phase split at the wall)
PHASES = ("no key", "key", "door open", "goal room")
#: h above this counts as saturated: some goal of the K looks within reach
SATURATION = 0.9
#: a phase reached by fewer episodes than this share is not ranked
MIN_PHASE_SHARE = 0.1
#: where every ranked phase's mastery is at least this, no phase is the least mastered
MASTERED = 0.95
#: h of eq 13 on the (n, K) mastery: the module's own (max), and designs measured offline
AGGREGATES: dict[str, Callable[[th.Tensor], th.Tensor]] = {
    "max (the defaults)": lambda m: m.max(dim=1).values,
    "mean": lambda m: m.mean(dim=1),
    "median": lambda m: m.median(dim=1).values,
    "share of goals within reach (m > 0.5)": lambda m: (m > 0.5).float().mean(dim=1),
}

#: played episodes: per episode its raw observations, their phases and whether it reached the goal
Episodes = list[tuple[np.ndarray, np.ndarray, bool]]


def beyond_the_wall(env: Any) -> bool:
    """Whether a DoorKey env's agent stands beyond the wall (in the goal's room)."""
    base = env.unwrapped
    door = next((o for o in base.grid.grid if isinstance(o, Door)), None)
    return door is not None and door.is_open and int(base.agent_pos[0]) > int(door.cur_pos[0])


def play(model: PPO_GoCu, env_id: str, episodes: int, seed: int, n_envs: int = 8) -> Episodes:
    """``episodes`` episodes of the model's policy: per episode the raw observations reached, their phases (0-3, as
    the module docstring numbers them) and whether it reached the goal."""
    module = model.curiosity
    venv = VecTransposeImage(make_vec_env(env_id, n_envs=n_envs, seed=seed))  # channels first, as the model was trained
    obs = venv.reset()
    current: list[list[tuple[np.ndarray, int]]] = [[] for _ in range(n_envs)]
    done_episodes: Episodes = []
    while len(done_episodes) < episodes:
        actions, _ = model.predict(obs, deterministic=False)
        obs, _, dones, infos = venv.step(actions)
        for i, info in enumerate(infos):
            reached = info["terminal_observation"] if dones[i] else obs[i]
            success = bool(info.get("is_success", False))
            phase = min(int(info.get("task_phase", 0)), 2)
            if success or (phase == 2 and not dones[i] and beyond_the_wall(venv.venv.envs[i])):
                phase = 3
            current[i].append((module.adapter.extract(reached[None])[0], phase))
            if dones[i]:
                done_episodes.append((np.stack([o for o, _ in current[i]]), np.array([p for _, p in current[i]]), success))
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
        obs = usable[rng.integers(len(usable))][0]
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


def phase_mastery(episodes: Episodes) -> dict[int, dict[str, float]]:
    """Per phase: the share of episodes that reach it, and of those the share that go on (the goal room: to the goal)."""
    furthest = np.array([int(phases.max()) for _, phases, _ in episodes])
    success = np.array([s for _, _, s in episodes])
    out = {}
    for phase in range(len(PHASES)):
        reached = furthest >= phase
        if reached.any():
            on = success[reached] if phase == len(PHASES) - 1 else furthest[reached] > phase
            out[phase] = {"reached": float(reached.mean()), "mastery": float(on.mean())}
    return out


def least_mastered(mastery: dict[int, dict[str, float]]) -> int | None:
    """The phase of lowest mastery among those reached by at least :data:`MIN_PHASE_SHARE` of the episodes (ties: the
    later); None where all of them are mastered (:data:`MASTERED`)."""
    candidates = {p: m["mastery"] for p, m in mastery.items() if m["reached"] >= MIN_PHASE_SHARE}
    weakest = min(candidates, key=lambda p: (candidates[p], -p)) if candidates else None
    return None if weakest is None or candidates[weakest] >= MASTERED else weakest


#: a goal design: (model, episodes, index of the episode being paid, K, rng) -> the K raw goals of that episode
GoalDesign = Callable[[PPO_GoCu, Episodes, int, int, np.random.Generator], np.ndarray]
#: how many episodes before the paid one count as recent
RECENT = 16
#: an episode's end, for "ends of recent episodes": its last this many steps
END_STEPS = 20


def buffer_goals(model: PPO_GoCu, episodes: Episodes, i: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """K goals drawn from the goal buffer, as the module draws them at an episode start."""
    buffer = model.curiosity.goal_buffer
    return buffer.observations[buffer.sample(1, k, rng)[0]]


def distinct_goals(model: PPO_GoCu, episodes: Episodes, i: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """K goals of the buffer spread out in phi: a random first goal, then each time the goal farthest from those taken."""
    buffer = model.curiosity.goal_buffer
    e = buffer.embeddings[: buffer.size]
    taken = [int(rng.integers(buffer.size))]
    nearest = th.linalg.vector_norm(e - e[taken[0]], dim=1)
    while len(taken) < min(k, buffer.size):
        taken.append(int(nearest.argmax()))
        nearest = th.minimum(nearest, th.linalg.vector_norm(e - e[taken[-1]], dim=1))
    return buffer.observations[np.array(taken)]


def recent_goals(ends_only: bool) -> GoalDesign:
    """K goals drawn from the states of the :data:`RECENT` episodes played before the paid one (in the order they
    ended, wrapping round at the start), from all their steps or from their last :data:`END_STEPS`."""
    def goals(model: PPO_GoCu, episodes: Episodes, i: int, k: int, rng: np.random.Generator) -> np.ndarray:
        recent = [episodes[(i - j) % len(episodes)][0] for j in range(1, min(RECENT, len(episodes) - 1) + 1)] or [episodes[i][0]]
        pool = np.concatenate([obs[-END_STEPS:] if ends_only else obs for obs in recent])
        return pool[rng.choice(len(pool), size=k, replace=len(pool) < k)]
    return goals


#: where the K goals of an episode come from: the module's own (the buffer) and designs measured offline
GOAL_DESIGNS: dict[str, GoalDesign] = {
    "buffer (the defaults)": buffer_goals,
    "buffer, spread out in phi": distinct_goals,
    "recent episodes": recent_goals(ends_only=False),
    "ends of recent episodes": recent_goals(ends_only=True),
}


@th.no_grad()
def phase_signal(model: PPO_GoCu, episodes: Episodes, rng: np.random.Generator,
                 mastery_of: Callable[[np.ndarray, np.ndarray], th.Tensor] | None = None,
                 goals_of: GoalDesign = buffer_goals) -> dict[str, Any]:
    """r_gc of the steps the first-visit rule pays, per phase and per h of :data:`AGGREGATES`; see the module docstring.

    :param mastery_of: (raw states, raw goals) -> (n_states, n_goals) mastery; None: the module's own
    :param goals_of: where each episode's K goals come from (one of :data:`GOAL_DESIGNS`)"""
    module, cfg = model.curiosity, model.curiosity.config
    mastery_of = module.mastery if mastery_of is None else mastery_of
    h_by: dict[str, list[np.ndarray]] = {name: [] for name in AGGREGATES}
    phase_of: list[np.ndarray] = []
    for i, (obs, phases, _) in enumerate(episodes):
        paid = first_visit_mask(module.revisit_key(obs), np.zeros(len(obs)))
        goals = goals_of(model, episodes, i, cfg.n_goals, rng)
        mastery = mastery_of(obs[paid], goals)
        for name, aggregate in AGGREGATES.items():
            h_by[name].append(aggregate(mastery).numpy())
        phase_of.append(phases[paid])
    phases = np.concatenate(phase_of)
    mastery = phase_mastery(episodes)
    weakest = least_mastered(mastery)
    out: dict[str, Any] = {"mastery": mastery, "least_mastered": weakest, "aggregates": {}}
    for name in AGGREGATES:
        h = np.concatenate(h_by[name])
        r_gc = (cfg.alpha - h) / cfg.reward_scale
        per_phase = {}
        for phase in sorted(set(phases.tolist())):
            sel = phases == phase
            per_phase[phase] = {"steps": int(sel.sum()), "r_gc_mean": float(r_gc[sel].mean()), "r_gc_std": float(r_gc[sel].std()),
                                "saturated": float((h[sel] > SATURATION).mean())}
        ranked = [p for p in per_phase if mastery.get(p, {}).get("reached", 0.0) >= MIN_PHASE_SHARE]
        first = max(ranked, key=lambda p: per_phase[p]["r_gc_mean"]) if ranked else None
        out["aggregates"][name] = {"phases": per_phase, "ranked_first": first,
                                   "least_mastered_first": weakest is not None and first == weakest}
    return out


def goal_coverage(model: PPO_GoCu, episodes: Episodes) -> dict[str, Any]:
    phase_of: dict[bytes, int] = {}
    for obs, phases, _ in episodes:
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
    cpu = cpu_model()
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
            "success": float(np.mean([success for _, _, success in episodes])) if episodes else float("nan"),
            "predictor": predictor_against_labels(model, episodes, args.pairs, rng),
            "phases": {name: phase_signal(model, episodes, rng, goals_of=design) for name, design in GOAL_DESIGNS.items()},
            "goals": goal_coverage(model, episodes),
        }
        results[Path(path).name if len(args.models) == 1 else path] = res
        pr = res["predictor"]
        print(f"\n{path} ({res['steps']:,} steps; {res['episodes']} episodes, success {res['success']:.2f})")
        print(f"  predictor on {pr['pairs']} held-out pairs: accuracy {pr['accuracy']:.3f}, mean |m - p_skill| {pr['mean_abs_error']:.3f}, "
              f"labelled mastered {pr['mastered_label_share']:.3f}")
        for band, b in pr["bands"].items():
            print(f"    distance {band:>5}: {b['pairs']:5d} pairs, mean m {b['mastery']:.3f}, mean p_skill {b['label']:.3f}")
        ph = next(iter(res["phases"].values()))
        print("  phases (reached by / go on): " + ", ".join(f"{PHASES[p]} {m['reached']:.2f} / {m['mastery']:.2f}" for p, m in ph["mastery"].items())
              + f"; least mastered: {PHASES[ph['least_mastered']] if ph['least_mastered'] is not None else 'none (all mastered)'}")
        print("  paid steps per phase: " + ", ".join(f"{PHASES[p]} {f['steps']}" for p, f in next(iter(ph["aggregates"].values()))["phases"].items()))
        for design, ph in res["phases"].items():
            print(f"  goals from {design}: r_gc per phase (share of h saturated)")
            for name, agg in ph["aggregates"].items():
                first = PHASES[agg["ranked_first"]] if agg["ranked_first"] is not None else "none"
                verdict = "" if ph["least_mastered"] is None else " (the least mastered)" if agg["least_mastered_first"] else ""
                print(f"    h = {name:<38}" + "  ".join(f"{f['r_gc_mean']:.4f} ({f['saturated']:.2f})" for f in agg["phases"].values())
                      + f"  -> first: {first}{verdict}")
        print("  goals: " + ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in res["goals"].items()))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
