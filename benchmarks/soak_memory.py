"""Soak test: does PPO_GoCu's resident memory stay bounded over a long run?

    python benchmarks/soak_memory.py --env GoCu/DoorKey-8x8-v0 --timesteps 300000 --seed 0 --threads 2

Trains PPO_GoCu with the paper's settings (16 envs, n_steps 128, batch 256, 4 epochs, lr 1e-4, ent 0.01,
sigma 0.25; GoCu defaults: K = 50, goal buffer 1500, memory bank 10,000, P_m = 20k, P_vae = 100k, VAE
pretraining on 10,000 random-policy observations) and samples the process's resident set size (psutil RSS)
at every rollout end (every ``n_envs * n_steps`` = 2048 steps). Prints the command, seed and machine, a
sample table (each line also says where the curiosity's time went since the line before: the rollout's own time in
the module, and the VAE and predictor updates), and a summary:

* start: RSS after the imports, before the model exists;
* warm: RSS at the first rollout end after ``--warmup`` steps (default 25% of the run, at least one P_vae
  so that every store, cache and optimiser state has been allocated);
* peak and end RSS, and the growth from warm to end, with the least-squares slope of RSS over the samples
  after warm-up (MB per 100k steps);
* the sizes of GoCu's bounded stores at the end, against their capacities.

The stores are preallocated at their capacities, so growth after warm-up should be near zero (allocator noise
of a few MB). ``--save-freq N`` also writes a checkpoint every N steps (``GoCuCheckpointCallback``) into a
temporary directory, to soak the save path too. ``--csv PATH`` writes the samples.

Atari (``--zoo``, the default for ``ALE/...`` ids): the agent the zoo launcher builds from
``sb3_gocu/hyperparams/ppo_gocu.yml`` (8 envs, 4 stacked 84x84 frames, the VAE on the newest frame averaged to 42x42)::

    python benchmarks/soak_memory.py --env ALE/MontezumaRevenge-v5 --timesteps 1000000 --seed 0 --save-freq 200000
"""

from __future__ import annotations

import argparse
import csv
import os
import pathlib
import platform
import sys
import tempfile
import time

import numpy as np
import psutil
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu.curiosity.config import EPISODE_MEMORY
from sb3_gocu.curiosity.scoring import PHI_MEMO_SIZE
from sb3_gocu import PAPER_PPO_KWARGS, PPO_GoCu
from sb3_gocu.checkpoints import GoCuCheckpointCallback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from run_records import cpu_model  # noqa: E402
from throughput import zoo_model  # noqa: E402

MB = 1024**2


def rss() -> int:
    return psutil.Process().memory_info().rss


class RSSSampler(BaseCallback):
    """Samples RSS (and GoCu's store sizes) at every rollout end."""

    def __init__(self, print_every: int) -> None:
        super().__init__()
        self.samples: list[tuple[int, float, int]] = []  # (timesteps, seconds, rss bytes)
        self.print_every = print_every
        self.t0 = time.perf_counter()
        self._next_print = 0
        self._timers_at_print = (0.0,) * 3  # the curiosity timers at the last printed sample

    def _timers(self) -> tuple[float, ...]:
        """Cumulative seconds: the rollout's own time in the module, VAE training, predictor training."""
        m = self.model.curiosity
        return m.time_inference, m.time_vae, m.time_predictor

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        r = rss()
        self.samples.append((self.num_timesteps, time.perf_counter() - self.t0, r))
        if self.num_timesteps >= self._next_print:
            m = self.model.curiosity
            seconds, timers = self.samples[-1][1], self._timers()
            d = [now - before for now, before in zip(timers, self._timers_at_print)]
            self._timers_at_print = timers
            print(
                f"{self.num_timesteps:>9d} steps {seconds:8.0f} s  RSS {r / MB:8.1f} MB  "
                f"goals {m.goal_buffer.size}  memory {m.memory.size}  trajectories {len(m.trajectories)}  "
                f"phi cache {len(m.scorer.phi_memo)}  |  since the last line: curiosity {d[0]:.0f} s, "
                f"VAE {d[1]:.0f} s, predictor {d[2]:.0f} s",
                flush=True,
            )
            self._next_print += self.print_every


def machine() -> str:
    mem = psutil.virtual_memory().total / 1024**3
    return (
        f"{platform.platform()}, {cpu_model()}, {os.cpu_count()} CPUs, {mem:.1f} GiB RAM; "
        f"python {platform.python_version()}, torch {th.__version__} ({th.get_num_threads()} threads), "
        f"numpy {np.__version__}, sb3-gocu {sb3_gocu.__version__}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--timesteps", type=int, default=300_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-envs", type=int, default=16)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--warmup", type=int, default=None, help="steps before the 'warm' sample (default: max(25%% of the run, 100k) if the run is long enough, else 25%%)")
    parser.add_argument("--print-every", type=int, default=20_480, help="steps between printed samples")
    parser.add_argument("--save-freq", type=int, default=0, help="checkpoint every N steps (0: no checkpoints)")
    parser.add_argument("--zoo", action=argparse.BooleanOptionalAction, default=None,
                        help="build the agent as the zoo launcher does, from hyperparams/ppo_gocu.yml (default: for ALE/... ids; "
                        "--n-envs then comes from the file)")
    parser.add_argument("--csv", default=None, help="write the samples (timesteps, seconds, rss_mb) to this file")
    args = parser.parse_args()

    th.set_num_threads(args.threads)
    start = rss()
    print("command:", " ".join([os.path.basename(sys.executable), *sys.argv]))
    print(f"seed: {args.seed}")
    print("machine:", machine())
    print(f"RSS at start: {start / MB:.1f} MB", flush=True)

    if args.env.startswith("ALE/") if args.zoo is None else args.zoo:
        model = zoo_model("ppo_gocu", args.env, args.seed)
    else:
        env = make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed)
        model = PPO_GoCu("CnnPolicy", env, intrinsic_coef=0.25, seed=args.seed, **PAPER_PPO_KWARGS)
    sampler = RSSSampler(args.print_every)
    callbacks: list[BaseCallback] = [sampler]
    tmp = None
    if args.save_freq > 0:
        tmp = tempfile.TemporaryDirectory(prefix="gocu_soak_")
        callbacks.append(GoCuCheckpointCallback(max(1, args.save_freq // model.n_envs), tmp.name))  # save_freq counts calls
    t0 = time.perf_counter()
    model.learn(args.timesteps, callback=callbacks)
    wall = time.perf_counter() - t0

    samples = sampler.samples
    steps = np.array([s[0] for s in samples], dtype=np.float64)
    mem = np.array([s[2] for s in samples], dtype=np.float64) / MB
    warmup = args.warmup
    if warmup is None:
        warmup = max(args.timesteps // 4, 100_000) if args.timesteps >= 400_000 else args.timesteps // 4
    warm_i = int(np.searchsorted(steps, warmup))
    warm_i = min(warm_i, len(samples) - 1)
    after = slice(warm_i, None)
    slope = float(np.polyfit(steps[after], mem[after], 1)[0] * 100_000) if len(steps[after]) >= 3 else float("nan")
    peak = max(float(mem.max()), start / MB)
    m = model.curiosity
    print()
    print(f"steps: {model.num_timesteps} in {wall:.0f} s ({model.num_timesteps / wall:.0f} steps/s)")
    print(f"RSS start {start / MB:.1f} MB | warm ({int(steps[warm_i])} steps) {mem[warm_i]:.1f} MB | peak {peak:.1f} MB | end {mem[-1]:.1f} MB")
    print(f"growth after warm-up: {mem[-1] - mem[warm_i]:+.1f} MB; slope {slope:+.2f} MB per 100k steps")
    print(
        f"stores at the end: goal buffer {m.goal_buffer.size}/{m.goal_buffer.capacity}, memory bank {m.memory.size}/"
        f"{m.memory.capacity}, trajectory store {len(m.trajectories)}/{m.trajectories.capacity * m.trajectories.n_envs}, "
        f"embedding memo {len(m.scorer.phi_memo)}/{PHI_MEMO_SIZE}, "
        f"reward memos {sum(len(c) for c in m.episodes.rewards)} (<= {EPISODE_MEMORY} per env), "
        f"finished episodes queued {len(m.episodes.finished)}"
    )
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["timesteps", "seconds", "rss_mb"])
            w.writerows((int(s), round(t, 2), round(r / MB, 2)) for s, t, r in samples)
        print(f"samples written to {args.csv}")
    if tmp is not None:
        for path in sorted(pathlib.Path(tmp.name).rglob("*")):
            if path.is_file():
                print(f"checkpoint file {path.name}: {path.stat().st_size / MB:.1f} MB")
        tmp.cleanup()


if __name__ == "__main__":
    main()
