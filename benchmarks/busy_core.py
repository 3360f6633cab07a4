"""Env stepping with the other core idle, and with it busy with matrix products (as PPO_GoCu's scoring worker keeps it).

    python benchmarks/busy_core.py --env GoCu/DoorKey-8x8-v0 --steps 16000 --repeats 4

In ``benchmarks/throughput.py`` runs, PPO_GoCu's env steps (``env_s``: the DummyVecEnv's ``step_wait``, below the
GoCu wrapper) took 5-9 s longer per 100k steps than plain PPO's, with the scoring worker in a thread or in a
process alike, so not for the GIL. This script times ``--steps`` random-action steps of 16 envs in this process,
alternately with nothing else running and beside a child process that multiplies 800x512 by 512x512 float32
matrices in a loop with 1 torch thread (the shape of eq 13 for 16 envs and K = 50), ``--repeats`` times each,
and prints the two medians and their ratio.
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
    "import torch; torch.set_num_threads(1); a = torch.randn(800, 512); w = torch.randn(512, 512)\n"
    "while True:\n    a = torch.relu(a @ w) * 0.03 + 0.1"
)


def step_rate(venv, steps: int, rng: np.random.Generator) -> float:
    n = venv.num_envs
    t0 = time.perf_counter()
    for _ in range(steps // n):
        venv.step(rng.integers(venv.action_space.n, size=n))
    return (steps // n) * n / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--steps", type=int, default=16000, help="env steps per timing (16 envs)")
    p.add_argument("--repeats", type=int, default=4, help="timings per arm, alternating")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.steps < 16 or args.repeats < 1:
        p.error(f"--steps must be >= 16 and --repeats >= 1, got {args.steps} and {args.repeats}")
    print("command: python benchmarks/busy_core.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, seed {args.seed}; the load: 1 torch thread in a child process")
    venv = make_vec_env(args.env, n_envs=16, seed=args.seed)
    venv.reset()
    rng = np.random.default_rng(args.seed)
    step_rate(venv, args.steps // 4, rng)  # warm-up
    rates: dict[str, list[float]] = {"idle": [], "busy": []}
    for rep in range(args.repeats):
        for arm in ("idle", "busy") if rep % 2 == 0 else ("busy", "idle"):
            load = subprocess.Popen([sys.executable, "-c", LOAD]) if arm == "busy" else None
            if load is not None:
                time.sleep(1.0)  # torch imported, the loop running
            try:
                rates[arm].append(step_rate(venv, args.steps, rng))
            finally:
                if load is not None:
                    load.kill()
                    load.wait()
    for arm, r in rates.items():
        print(f"other core {arm}: median {np.median(r):7.0f} steps/s  ({', '.join(f'{v:.0f}' for v in r)})")
    print(f"time per env step, busy / idle (medians): {np.median(rates['idle']) / np.median(rates['busy']):.3f}")
    return rates


if __name__ == "__main__":
    main()
