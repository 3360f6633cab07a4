"""The curiosity module's own time per vector step in the training thread, outside a training run.

    python benchmarks/module_step.py --steps 2048 --repeats 3

Records ``--steps`` vector steps of ``--n-envs`` DoorKey envs under random actions (terminal observations where
episodes end), pretrains a module (the defaults but ``vae_epochs``, set by ``--vae-epochs``) on the first
``--pretrain`` of them, and then hands the rest to it ``--repeats`` times as ``PPO_GoCu`` does during a rollout:
``submit`` with the scoring worker (by default a process, ``scoring_process``), and the previous step's
``collect`` after it. It prints, per repeat, the wall time and the module's time in the training thread
without the waits for the worker's scores (``time_inference - time_scoring_wait``): the part of a step that
no worker overlaps. The first repeat includes starting the scoring process. The observations of a random policy
repeat more than a trained agent's (reward memo hit rate printed), so this is a relative measure: compare two
versions of the code with it, on the same machine, one after the other.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu/ ids)
from sb3_gocu.curiosity import GoalCuriosityModule


def record(env_id: str, n_envs: int, steps: int, seed: int) -> tuple[list[np.ndarray], list[np.ndarray], object]:
    venv = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    venv.reset()
    rng = np.random.default_rng(seed)
    observations, dones = [], []
    for _ in range(steps):
        obs, _, done, infos = venv.step(rng.integers(0, venv.action_space.n, n_envs))
        obs = obs.copy()
        for i in np.flatnonzero(done):
            obs[i] = infos[i]["terminal_observation"]
        observations.append(obs)
        dones.append(done.copy())
    return observations, dones, venv.observation_space


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--n-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=2048)
    parser.add_argument("--pretrain", type=int, default=200, help="vector steps to pretrain on and to fill the goal buffer from")
    parser.add_argument("--vae-epochs", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in ("n_envs", "steps", "pretrain", "vae_epochs", "repeats", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.pretrain >= args.steps:
        parser.error(f"--pretrain must be < --steps ({args.steps}), got {args.pretrain}")
    th.set_num_threads(args.threads)
    print("command: python " + " ".join(sys.argv))
    print(f"machine: {platform.machine()}, Python {platform.python_version()}, "
          f"torch {th.__version__}, {args.threads} torch thread(s); seed {args.seed}")
    observations, dones, space = record(args.env, args.n_envs, args.steps, args.seed)
    module = GoalCuriosityModule(space, pretrain_steps=0, vae_epochs=args.vae_epochs, seed=args.seed)
    module.memory.add(np.concatenate(observations[: args.pretrain]), module.rng)
    module.pretrain()
    for obs, done in zip(observations[: args.pretrain], dones[: args.pretrain]):
        module.step(obs, done)
    module.add_finished_episode_goals()
    n = args.steps - args.pretrain
    for repeat in range(args.repeats):
        t0, own0, wait0 = time.perf_counter(), module.time_inference, module.time_scoring_wait
        previous = None
        for obs, done in zip(observations[args.pretrain :], dones[args.pretrain :]):
            ticket = module.submit(obs, done)
            if previous is not None:
                module.collect(previous)
            previous = ticket
        module.collect_all()
        wall = time.perf_counter() - t0
        own = (module.time_inference - own0) - (module.time_scoring_wait - wait0)
        print(f"repeat {repeat}: {n} vector steps, wall {wall:.2f} s, module's own time in the training thread "
              f"{own:.2f} s = {own / n * 1000:.3f} ms per vector step; reward memo hit rate so far "
              f"{module.cache_hits / module.cache_lookups:.2f}")


if __name__ == "__main__":
    main()
