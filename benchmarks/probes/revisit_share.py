"""Where does the first-visit rule fire? The first-visit share of each revisit key, per env, and what the key costs.

    python benchmarks/probes/revisit_share.py --envs GoCu/DoorKey-8x8-v0 ALE/MontezumaRevenge-v5 --steps 4000 --seed 0 \\
        [--model ALE/MontezumaRevenge-v5=<run>/checkpoints/ppo_gocu_seed0/model_1000448.zip]

The first-visit share is the share of steps whose key is new in its episode: the steps where ``revisit_decay=
"first_visit"`` pays r_gc. For each env, built as the zoo builds it (Atari: ``AtariWrapper``, 4 stacked frames, the
module keeping the newest), the probe

1. plays the random policy for ``--calibration-steps`` steps in the zoo's number of envs (the pretraining's random
   episodes, 10,000 steps by default as ``pretrain_steps``) and chooses the cell as the module does
   (:func:`sb3_gocu.curiosity.revisits.choose_cell`);
2. plays ``--steps`` steps of the random policy in one env (another seed) and, where ``--model ENV=PATH`` gives one, of
   a trained agent's stochastic policy, and prints the first-visit share of three keys on them: the observation's
   bytes (the key before), the chosen cell, and Go-Explore's fixed cell (11 x 8 pixels, 8 levels);
3. times the chosen key on one vector step's observations against the env's own vector step (a lower bound of a
   training step, so the share printed is an upper bound of the key's cost).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu/ ids)
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.observations import ObservationAdapter
from sb3_gocu.curiosity.revisits import ImageCell, choose_cell, default_cell, first_visit_share
from sb3_gocu.curiosity.training import torch_threads

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # sample_efficiency (benchmarks/)
from sample_efficiency import machine_line

#: the envs of the issue's table: DoorKey, two Atari games and the five Sawyer tasks
DEFAULT_ENVS = ["GoCu/DoorKey-8x8-v0", "ALE/MontezumaRevenge-v5", "ALE/Pitfall-v5", "ALE/PrivateEye-v5",
                *(f"GoCu/VisualSawyer{task}-v1" for task in ("Reacher", "DoorHook", "Pusher", "MultiObjectPusher", "PickAndPlace"))]


def make_env(env_id: str, n_envs: int, seed: int) -> tuple[Any, ObservationAdapter]:
    """The env as the zoo builds it, and how the curiosity module reads its observations."""
    if env_id.startswith("ALE/"):
        import ale_py
        from stable_baselines3.common.env_util import make_atari_env
        from stable_baselines3.common.vec_env import VecFrameStack, VecTransposeImage

        gym.register_envs(ale_py)
        venv = make_atari_env(env_id, n_envs=n_envs, seed=seed, env_kwargs={"frameskip": 1, "repeat_action_probability": 0.0})
        venv = VecTransposeImage(VecFrameStack(venv, 4))
        return venv, ObservationAdapter(venv.observation_space, image_channels=1)
    venv = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    return venv, ObservationAdapter(venv.observation_space)


def rollout(venv: Any, adapter: ObservationAdapter, steps: int, model: Any = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """``steps`` vector steps of the random policy (or ``model``'s): the raw observations reached (the terminal one
    where an episode ended), their episode ids, and the seconds the env's steps took. An episode is the curiosity's: it
    ends where the Monitor beneath the wrappers ends one (a whole game on Atari, not a life)."""
    venv.action_space.seed(seed)
    n = venv.num_envs
    obs = venv.reset()
    ids = np.arange(n)
    next_id = n
    frames, episodes, env_time = [], [], 0.0
    for _ in range(steps):
        if model is None:
            actions = np.array([venv.action_space.sample() for _ in range(n)])
        else:
            actions = model.predict(obs, deterministic=False)[0]
        t0 = time.perf_counter()
        obs, _, dones, infos = venv.step(actions)
        env_time += time.perf_counter() - t0
        reached = np.array(obs)
        for e in np.flatnonzero(dones):
            reached[e] = infos[e]["terminal_observation"]
        frames.append(adapter.extract(reached))
        episodes.append(ids.copy())
        ends = dones & np.array(["episode" in info for info in infos])
        ids[ends] = next_id + np.arange(int(ends.sum()))
        next_id += int(ends.sum())
    return np.concatenate(frames), np.concatenate(episodes), env_time / steps


def probe(env_id: str, steps: int, calibration_steps: int, seed: int, model_path: str | None) -> dict[str, Any]:
    n_envs = 8 if env_id.startswith("ALE/") else 16
    venv, adapter = make_env(env_id, n_envs, seed)
    raw, ids, step_time = rollout(venv, adapter, -(-calibration_steps // n_envs), seed=seed)
    venv.close()
    cell, chosen = choose_cell(raw, ids, adapter.layout, adapter.scale)
    keys = {"bytes": lambda x: [r.tobytes() for r in x], "cell": cell}
    if adapter.is_image:
        fixed = default_cell(adapter.layout, adapter.scale, adapter.raw_shape)
        keys["go-explore 11x8x8"] = fixed if isinstance(fixed, ImageCell) else None
    batch = raw[:n_envs]
    t0 = time.perf_counter()
    for _ in range(200):
        cell(batch)
    key_time = (time.perf_counter() - t0) / 200
    out: dict[str, Any] = {"cell": cell.describe(), "calibration_share": chosen["revisit_share"], "key_ms": key_time * 1e3,
                           "env_step_ms": step_time * 1e3}
    policies: list[tuple[str, Any]] = [("random", None)]
    if model_path is not None:
        policies.append(("agent", PPO_GoCu.load(model_path, device="cpu")))
    for name, model in policies:
        venv, _ = make_env(env_id, 1, seed + 1)
        frames, episodes, _ = rollout(venv, adapter, steps, model, seed + 1)
        venv.close()
        out[name] = {k: first_visit_share(key(frames), episodes) for k, key in keys.items() if key is not None}
        out[name]["episodes"] = int(len(np.unique(episodes)))
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=DEFAULT_ENVS)
    p.add_argument("--steps", type=int, default=4000, help="steps of each policy in one env, where the shares are measured")
    p.add_argument("--calibration-steps", type=int, default=10_000, help="random-policy steps the cell is chosen from (pretrain_steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--model", action="append", default=[], metavar="ENV=PATH", help="a trained PPO_GoCu model of an env")
    args = p.parse_args(argv)
    for name in ("steps", "calibration_steps"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    models = dict(m.split("=", 1) for m in args.model)
    unknown = sorted(set(models) - set(args.envs))
    if unknown:
        p.error(f"--model names envs not in --envs: {unknown}")
    results = {}
    with torch_threads(1):  # the caller's count comes back on return
        print("command: python benchmarks/probes/revisit_share.py " + " ".join(sys.argv[1:] if argv is None else argv))
        print(f"machine: {machine_line(1)}")
        for env_id in args.envs:
            r = results[env_id] = probe(env_id, args.steps, args.calibration_steps, args.seed, models.get(env_id))
            print(f"{env_id}: cell {r['cell']} (share {r['calibration_share']:.3f} on {args.calibration_steps} calibration steps); "
                  f"key {r['key_ms']:.3f} ms a vector step, {100 * r['key_ms'] / r['env_step_ms']:.2f}% of the env's step ({r['env_step_ms']:.2f} ms)")
            for name in ("random", "agent"):
                if name in r:
                    shares = ", ".join(f"{k} {v:.3f}" for k, v in r[name].items() if k != "episodes")
                    print(f"  {name:>6} ({args.steps} steps, {r[name]['episodes']} episodes): first-visit share {shares}", flush=True)
    return results


if __name__ == "__main__":
    main()
