"""Env stepping (or PPO's update) with the other core idle, and with it busy with matrix products (as PPO_GoCu's scoring worker keeps it).

    python benchmarks/busy_core.py --env GoCu/DoorKey-8x8-v0 --steps 16000 --repeats 4
    python benchmarks/busy_core.py --work update --steps 60 --repeats 4 --load-dtypes float32 bfloat16

In ``benchmarks/throughput.py`` runs, PPO_GoCu's env steps (``env_s``: the DummyVecEnv's ``step_wait``, below the
GoCu wrapper) took 5-9 s longer per 100k steps than plain PPO's, with the scoring worker in a thread or in a
process alike, so not for the GIL. This script times ``--steps`` random-action steps of 16 envs in this process,
alternately with nothing else running and beside a child process that multiplies 800x512 by 512x512 float32
matrices in a loop with 1 torch thread (the shape of eq 13 for 16 envs and K = 50), ``--repeats`` times each,
and prints the two medians and their ratio.

``--work update`` times ``--steps`` of PPO's minibatch steps instead (plain PPO's CnnPolicy with the paper's CNN,
256 observations of the env, loss, backward and Adam step, 1 torch thread), the part of a PPO_GoCu run that ran
14-30 s slower per 400k steps beside the curiosity fits. ``--load-dtypes`` runs one busy arm per dtype of the
load's products (``bfloat16`` takes the AMX/AVX512-BF16 kernels where the CPU has them).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time

import numpy as np
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)

LOAD = (
    "import torch; torch.set_num_threads(1); a = torch.randn(800, 512, dtype=torch.{dtype}); w = torch.randn(512, 512, dtype=torch.{dtype})\n"
    "while True:\n    a = torch.relu(a @ w) * 0.03 + 0.1"
)


def step_rate(venv, steps: int, rng: np.random.Generator) -> float:
    n = venv.num_envs
    t0 = time.perf_counter()
    for _ in range(steps // n):
        venv.step(rng.integers(venv.action_space.n, size=n))
    return (steps // n) * n / (time.perf_counter() - t0)


def update_rate(step, steps: int) -> float:
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return steps / (time.perf_counter() - t0)


def ppo_update_step(venv, seed: int):
    """One of PPO's minibatch steps (clipped loss, value loss, entropy, backward, Adam) on 256 of the env's
    observations, with plain PPO's CnnPolicy and the paper's CNN."""
    import torch as th
    from stable_baselines3 import PPO

    from sb3_gocu import PAPER_PPO_KWARGS, PaperCNN

    model = PPO("CnnPolicy", venv, seed=seed, policy_kwargs=dict(features_extractor_class=PaperCNN), **PAPER_PPO_KWARGS)
    policy = model.policy
    obs = np.concatenate([venv.step(np.random.default_rng(seed).integers(venv.action_space.n, size=venv.num_envs))[0] for _ in range(16)])
    obs_t, _ = policy.obs_to_tensor(obs)
    actions = th.as_tensor(np.random.default_rng(seed).integers(venv.action_space.n, size=len(obs)))
    adv, returns, old_logp = th.randn(len(obs)), th.randn(len(obs)), th.full((len(obs),), -1.9)

    def step() -> None:
        values, logp, entropy = policy.evaluate_actions(obs_t, actions)
        ratio = th.exp(logp - old_logp)
        loss = -th.min(adv * ratio, adv * th.clamp(ratio, 0.8, 1.2)).mean() + 0.5 * ((returns - values.flatten()) ** 2).mean() - 0.01 * entropy.mean()
        policy.optimizer.zero_grad()
        loss.backward()
        th.nn.utils.clip_grad_norm_(policy.parameters(), 0.5)
        policy.optimizer.step()

    return step


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--work", choices=("env", "update"), default="env", help="what is timed: env steps or PPO's minibatch steps")
    p.add_argument("--steps", type=int, default=16000, help="env steps (16 envs) or minibatch steps per timing")
    p.add_argument("--load-dtypes", nargs="+", choices=("float32", "bfloat16"), default=["float32"], help="one busy arm per dtype of the load's products")
    p.add_argument("--repeats", type=int, default=4, help="timings per arm, alternating")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.steps < (16 if args.work == "env" else 1) or args.repeats < 1:
        p.error(f"--steps must be >= 16 (env) or >= 1 (update) and --repeats >= 1, got {args.steps} and {args.repeats}")
    print("command: python benchmarks/busy_core.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, seed {args.seed}; the load: 1 torch thread in a child process")
    venv = make_vec_env(args.env, n_envs=16, seed=args.seed)
    venv.reset()
    rng = np.random.default_rng(args.seed)
    if args.work == "env":
        def timed() -> float:
            return step_rate(venv, args.steps, rng)
        unit = "env steps/s"
        step_rate(venv, args.steps // 4, rng)  # warm-up
    else:
        import torch as th

        th.set_num_threads(1)
        step = ppo_update_step(venv, args.seed)
        def timed() -> float:
            return update_rate(step, args.steps)
        unit = "minibatch steps/s"
        update_rate(step, max(1, args.steps // 4))  # warm-up
    arms = ["idle"] + [f"busy {d}" for d in args.load_dtypes]
    rates: dict[str, list[float]] = {arm: [] for arm in arms}
    for rep in range(args.repeats):
        for arm in arms if rep % 2 == 0 else arms[::-1]:
            load = subprocess.Popen([sys.executable, "-c", LOAD.format(dtype=arm.split()[1])]) if arm != "idle" else None
            if load is not None:
                time.sleep(1.0)  # torch imported, the loop running
            try:
                rates[arm].append(timed())
            finally:
                if load is not None:
                    load.kill()
                    load.wait()
    for arm, r in rates.items():
        print(f"other core {arm}: median {np.median(r):9.1f} {unit}  ({', '.join(f'{v:.1f}' for v in r)})")
    for arm in arms[1:]:
        print(f"time per {args.work} step, {arm} / idle (medians): {np.median(rates['idle']) / np.median(rates[arm]):.3f}")
    return rates


if __name__ == "__main__":
    main()
