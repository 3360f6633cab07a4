"""Env stepping (or PPO's update) with the other core idle, and with it busy with matrix products (as PPO_GoCu's scoring worker keeps it).

    python benchmarks/busy_core.py --env GoCu/DoorKey-8x8-v0 --steps 16000 --repeats 4
    python benchmarks/busy_core.py --work update --steps 60 --repeats 4 --loads float32 bfloat16 predictor-process predictor-thread vae-process vae-thread

In ``benchmarks/throughput.py`` runs, PPO_GoCu's env steps (``env_s``: the DummyVecEnv's ``step_wait``, below the
GoCu wrapper) took 5-9 s longer per 100k steps than plain PPO's, with the scoring worker in a thread or in a
process alike, so not for the GIL. This script times ``--steps`` random-action steps of 16 envs in this process,
alternately with nothing else running and beside a child process that multiplies 800x512 by 512x512 float32
matrices in a loop with 1 torch thread (the shape of eq 13 for 16 envs and K = 50), ``--repeats`` times each,
and prints the two medians and their ratio.

``--work update`` times ``--steps`` of PPO's minibatch steps instead (SB3's ``PPO.train`` on a rollout of 256 of
the env's observations in one batch of 256, plain PPO's CnnPolicy with the paper's CNN, 1 torch thread), the part
of a PPO_GoCu run that took 7-30 s longer per 400k steps than plain PPO's in the same run, beside the curiosity
fits. ``--loads`` names the busy arms, one load each:
``float32`` / ``bfloat16``, the products above in that dtype in a child process (``bfloat16`` takes the
AMX/AVX512-BF16 kernels where the CPU has them); ``predictor-process`` / ``predictor-thread``, predictor minibatch
steps (the module's 5x512 MasteryPredictor, Adam, 128 pairs) in a child process or in a thread of this process, as
the module's fits run beside PPO's update (``overlap_ppo_update``), and ``vae-process`` / ``vae-thread`` the same
with VAE minibatch steps (ConvVAE, eq 8, 128 images of 32x32x3): process and thread differ only by sharing this
process (its interpreter lock and allocator). ``--switch-interval`` sets the interpreter's switch interval for the
timings (PPO_GoCu sets 0.5 ms, its ``switch_interval``, while a fit runs beside PPO's update).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import threading
import time

import numpy as np
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)

LOAD = (
    "import torch; torch.set_num_threads(1); a = torch.randn(800, 512, dtype=torch.{dtype}); w = torch.randn(512, 512, dtype=torch.{dtype})\n"
    "while True:\n    a = torch.relu(a @ w) * 0.03 + 0.1"
)


FITS = {
    "predictor": (
        "import torch; torch.set_num_threads(1)\n"
        "from sb3_gocu.curiosity.networks import MasteryPredictor, mastery_loss\n"
        "torch.manual_seed(0); p = MasteryPredictor(128); opt = torch.optim.Adam(p.parameters(), 5e-4, foreach=True)\n"
        "x, g, t = torch.randn(128, 128), torch.randn(128, 128), torch.rand(128)\n"
        "def fit_step():\n"
        "    loss = mastery_loss(p(x, g), t)[0]\n"
        "    opt.zero_grad(); loss.backward(); opt.step()\n"
    ),
    "vae": (
        "import torch; torch.set_num_threads(1)\n"
        "from sb3_gocu.curiosity.networks import ConvVAE, vae_loss\n"
        "torch.manual_seed(0); v = ConvVAE((3, 32, 32)); opt = torch.optim.Adam(v.parameters(), 1e-3, foreach=True)\n"
        "gen = torch.Generator().manual_seed(1); x, w = torch.rand(128, 3, 32, 32, generator=gen), torch.ones(128)\n"
        "def fit_step():\n"
        "    loss = vae_loss(v, x, 1.0, w, generator=gen)[0]\n"
        "    opt.zero_grad(); loss.backward(); opt.step()\n"
    ),
}
LOADS = ("float32", "bfloat16", "predictor-process", "predictor-thread", "vae-process", "vae-thread")


class Load:
    """One busy arm's load, started on entry and stopped on exit."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.child: subprocess.Popen | None = None
        self.thread: threading.Thread | None = None
        self.stop = threading.Event()

    def __enter__(self) -> "Load":
        fit, _, where = self.name.partition("-")
        if where == "thread":
            scope: dict = {}
            exec(FITS[fit], scope)  # noqa: S102 (our own constant)

            def loop() -> None:
                while not self.stop.is_set():
                    scope["fit_step"]()

            self.thread = threading.Thread(target=loop, daemon=True)
            self.thread.start()
        else:
            code = FITS[fit] + "while True:\n    fit_step()" if where == "process" else LOAD.format(dtype=self.name)
            self.child = subprocess.Popen([sys.executable, "-c", code])
            time.sleep(1.5)  # torch imported, the loop running
        return self

    def __exit__(self, *exc) -> None:
        if self.thread is not None:
            self.stop.set()
            self.thread.join()
        if self.child is not None:
            self.child.kill()
            self.child.wait()


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


def one_batch_ppo(venv, seed: int):
    """A PPO model whose ``train()`` makes one of PPO's minibatch steps, SB3's own ``PPO.train`` (clipped loss,
    value loss, entropy, backward, gradient clipping, Adam, its logging): plain PPO's CnnPolicy with the paper's CNN
    and the SPEC's settings but for the rollout's size, 16 steps of the 16 envs, so that one epoch over one batch of 256 is one minibatch step.
    The rollout is collected once, by ``learn`` (the policy's own actions); every step trains on it again.

    :return: the model; its ``train`` is the step"""
    from stable_baselines3 import PPO

    from sb3_gocu import PAPER_PPO_KWARGS, PaperCNN

    settings = {**PAPER_PPO_KWARGS, "n_steps": 256 // venv.num_envs, "batch_size": 256, "n_epochs": 1}
    model = PPO("CnnPolicy", venv, seed=seed, policy_kwargs=dict(features_extractor_class=PaperCNN), **settings)
    model.learn(total_timesteps=256)  # collects the rollout (and trains on it once)
    return model


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--work", choices=("env", "update"), default="env", help="what is timed: env steps or PPO's minibatch steps")
    p.add_argument("--steps", type=int, default=16000, help="env steps (16 envs) or minibatch steps per timing")
    p.add_argument("--switch-interval", type=float, default=None, help="sys.setswitchinterval for the timings (s; default: the interpreter's, 5 ms)")
    p.add_argument("--loads", nargs="+", choices=LOADS, default=["float32"], help="one busy arm per load (see above)")
    p.add_argument("--repeats", type=int, default=4, help="timings per arm, alternating")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.steps < (16 if args.work == "env" else 1) or args.repeats < 1:
        p.error(f"--steps must be >= 16 (env) or >= 1 (update) and --repeats >= 1, got {args.steps} and {args.repeats}")
    if args.switch_interval is not None and not 0 < args.switch_interval <= 1:
        p.error(f"--switch-interval must be in (0, 1] seconds, got {args.switch_interval}")
    before = sys.getswitchinterval()
    try:
        if args.switch_interval is not None:
            sys.setswitchinterval(args.switch_interval)
        return _run(args, argv)
    finally:
        sys.setswitchinterval(before)


def _run(args: argparse.Namespace, argv: list[str] | None) -> dict[str, list[float]]:
    print("command: python benchmarks/busy_core.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, seed {args.seed}; each load runs 1 torch thread; "
          f"switch interval {sys.getswitchinterval() * 1e3:g} ms")
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
        step = one_batch_ppo(venv, args.seed).train
        def timed() -> float:
            return update_rate(step, args.steps)
        unit = "minibatch steps/s"
        update_rate(step, max(1, args.steps // 4))  # warm-up
    arms = ["idle"] + [f"busy {d}" for d in args.loads]
    rates: dict[str, list[float]] = {arm: [] for arm in arms}
    for rep in range(args.repeats):
        for arm in arms if rep % 2 == 0 else arms[::-1]:
            if arm == "idle":
                rates[arm].append(timed())
                continue
            with Load(arm.split()[1]):
                rates[arm].append(timed())
    for arm, r in rates.items():
        print(f"other core {arm}: median {np.median(r):9.1f} {unit}  ({', '.join(f'{v:.1f}' for v in r)})")
    for arm in arms[1:]:
        print(f"time per {args.work} step, {arm} / idle (medians): {np.median(rates['idle']) / np.median(rates[arm]):.3f}")
    return rates


if __name__ == "__main__":
    main()
