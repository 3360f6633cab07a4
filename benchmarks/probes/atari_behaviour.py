"""What does a trained Atari agent do? Where it goes, how often it dies, which actions it takes, against a random policy.

    python benchmarks/probes/atari_behaviour.py <out>/checkpoints/ppo_gocu_seed0/model_1000448.zip \\
        --env ALE/MontezumaRevenge-v5 --steps 4000 --seed 100

Plays ``--steps`` agent steps in one env built as the zoo's Atari entry builds it (``AtariWrapper``: 4 frames a step,
a lost life ends the agent's episode; 4 stacked frames), with the model's stochastic policy and then with a uniformly
random one (the same env seed), and prints for each: the distinct newest frames (what the module's first-visit
rule told apart before it keyed on cells), the distinct cells (Go-Explore's fixed key: the newest frame averaged down
to 11x8 pixels, 8 grey levels), the distinct player positions (RAM bytes 42 and 43, x and y, in Montezuma's Revenge;
other games: the distinct console RAM states, a coarse measure), the rooms (RAM byte 3 in Montezuma's Revenge), the
lives lost, the game's episodes ended, the score, and the action histogram. For a PPO_GoCu model, also what its own
curiosity module sees on both policies' steps (its episode is the game, as in training: a lost life does not end it):
the distinct cells of its revisit key, the share of steps whose cell is new in their life and in their game (what the
first-visit rule paid before and after a lost life stopped ending the curiosity's episode), and (Montezuma's Revenge)
the mean raw r_gc it pays a step where the player stood still against a step where the player moved; and, on the
agent's steps, its curiosity head's value V_gc where a game begins, where a life begins after a lost one and elsewhere
(the curiosity stream runs across episode ends: a V_gc higher where a game begins says that ending the game pays).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import ale_py
import cv2
import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_atari_env
from stable_baselines3.common.vec_env import VecFrameStack, VecTransposeImage

from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.revisits import first_visit_share
from sb3_gocu.curiosity.training import torch_threads

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # sample_efficiency (benchmarks/)
from sample_efficiency import machine_line

gym.register_envs(ale_py)  # the ALE/ ids


def play(env_id: str, model: Any, steps: int, seed: int, curiosity: Any = None) -> dict[str, Any]:
    """``steps`` agent steps of ``model`` (None: uniformly random actions) in one fresh env; with ``curiosity`` (a
    PPO_GoCu model's module), the raw r_gc it pays each step (first-visit rule included) and its revisit cells."""
    venv = make_atari_env(env_id, n_envs=1, seed=seed, env_kwargs={"frameskip": 1, "repeat_action_probability": 0.0})
    env = VecTransposeImage(VecFrameStack(venv, 4))  # make_atari_env wraps each env in Monitor and AtariWrapper
    ale = env.venv.venv.envs[0].unwrapped.ale
    montezuma = "Montezuma" in env_id
    rng = np.random.default_rng(seed)
    obs = env.reset()
    places, rooms, frames, cells, actions = set(), set(), set(), set(), Counter()
    lives_lost = games = 0
    score = best = 0.0
    lives = ale.lives()
    paid: dict[str, list[float]] = {"still": [], "moving": []}  # raw r_gc of the steps where the player stood / moved
    keys: list[bytes] = []  # the revisit cell of each step, with the life and the game it was met in
    life_ids: list[int] = []
    game_ids: list[int] = []
    life = game = 0
    previous = None
    # the curiosity head's value V_gc where a game begins, where a life begins after a lost one, and elsewhere
    values: dict[str, list[float]] = {"game": [], "life": [], "on": []}
    starting = "game"
    if curiosity is not None:
        curiosity.begin_episodes(np.arange(1))
    for _ in range(steps):
        if curiosity is not None and model is not None:
            with th.no_grad():
                values[starting].append(float(model.policy.predict_values(model.policy.obs_to_tensor(obs)[0])[0, 1]))
        action = model.predict(obs, deterministic=False)[0] if model is not None else np.array([rng.integers(env.action_space.n)])
        actions[int(action[0])] += 1
        obs, _, dones, infos = env.step(action)
        reached = infos[0]["terminal_observation"][None] if dones[0] else obs
        frames.add(obs[0, -1].tobytes())  # the newest frame, which GoCu's module sees
        cells.add((cv2.resize(obs[0, -1], (11, 8), interpolation=cv2.INTER_AREA) // 32).tobytes())
        ram = ale.getRAM()
        place = (int(ram[3]), int(ram[42]), int(ram[43])) if montezuma else ram.tobytes()
        places.add(place)
        game_over = "episode" in infos[0]  # Monitor: the end of a whole game
        if curiosity is not None:
            r_gc = float(curiosity.step(reached, dones & game_over)[0][0])
            keys.append(curiosity.revisit_key(curiosity.adapter.extract(reached))[0])
            life_ids.append(life)
            game_ids.append(game)
            life += int(dones[0])  # a lost life (AtariWrapper's episode) or the game's end
            game += int(game_over)
            if montezuma and previous is not None:
                paid["still" if place == previous else "moving"].append(r_gc)
        previous = None if dones[0] else place
        if montezuma:
            rooms.add(int(ram[3]))
        lives_lost += ale.lives() < lives
        lives = ale.lives()
        starting = "game" if game_over else "life" if dones[0] else "on"
        if game_over:
            games += 1
            best = max(best, float(infos[0]["episode"]["r"]))
            score += float(infos[0]["episode"]["r"])
    env.close()
    out = {"places": len(places), "frames": len(frames), "cells": len(cells), "rooms": sorted(rooms), "lives_lost": lives_lost, "games": games,
           "score": score, "best": best, "actions": actions}
    if curiosity is not None:
        out["module_cells"] = len(set(keys))
        out["first_visit_share_life"] = first_visit_share(keys, np.array(life_ids))
        out["first_visit_share_game"] = first_visit_share(keys, np.array(game_ids))
        for how, rewards in paid.items():
            out[f"r_gc_{how}"] = (float(np.mean(rewards)) if rewards else float("nan"), len(rewards))
        if model is not None:
            out["v_gc"] = {at: (float(np.mean(v)) if v else float("nan"), len(v)) for at, v in values.items()}
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", type=Path, help="a PPO or PPO_GoCu model zip (a checkpoint of sample_efficiency.py)")
    p.add_argument("--env", default="ALE/MontezumaRevenge-v5")
    p.add_argument("--steps", type=int, default=4000, help="agent steps played by each policy")
    p.add_argument("--seed", type=int, default=100)
    args = p.parse_args(argv)
    if args.steps < 1:
        p.error(f"--steps must be >= 1, got {args.steps}")
    with torch_threads(1):  # the caller's count comes back on return
        cls = PPO_GoCu if "ppo_gocu" in args.model.as_posix() else PPO
        model = cls.load(args.model, device="cpu")
        print("command: python " + " ".join([Path(sys.argv[0]).as_posix(), f"<checkpoints>/{args.model.parent.name}/{args.model.name}", *sys.argv[2:]]))
        print(f"machine: {machine_line(1)}; {cls.__name__} at {model.num_timesteps} steps")
        out = {}
        curiosity = getattr(model, "curiosity", None)
        for name, policy in (("agent", model), ("random", None)):
            r = play(args.env, policy, args.steps, args.seed, curiosity)
            out[name] = r
            hist = " ".join(f"{a}:{n}" for a, n in sorted(r["actions"].items()))
            print(f"{name:>6}: {r['places']} distinct places, {r['frames']} distinct frames, {r['cells']} cells, rooms {r['rooms']}, {r['lives_lost']} lives lost, {r['games']} games ended "
                  f"(score {r['score']:g}, best {r['best']:g}) in {args.steps} steps; actions {hist}", flush=True)
            if curiosity is not None:
                paid = "; ".join(f"raw r_gc {r[f'r_gc_{how}'][0]:.4f} a step over the {r[f'r_gc_{how}'][1]} steps the player {word}"
                                 for how, word in (("still", "stood still"), ("moving", "moved")) if r[f"r_gc_{how}"][1])
                print(f"{'':>8}the agent's curiosity: {r['module_cells']} revisit cells ({curiosity.revisit_key.describe()}), new in their life on "
                      f"{r['first_visit_share_life']:.3f} of the steps, in their game on {r['first_visit_share_game']:.3f}"
                      + (f"; {paid}" if paid else ""), flush=True)
                if "v_gc" in r:
                    print(f"{'':>8}its curiosity head's value V_gc: " + ", ".join(
                        f"{v:.3f} over the {n} steps {where}" for (v, n), where in zip(r["v_gc"].values(),
                        ("a game began", "a life began after a lost one", "the life went on")) if n), flush=True)
        return out


if __name__ == "__main__":
    main()
