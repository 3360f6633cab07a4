"""One minibatch step of each curiosity network's training, with 1 and with 2 torch threads in a worker thread.

    python benchmarks/update_threads.py --steps 40 --repeats 2

``update_threads`` (GoalCuriosityModule, opt-in) runs the VAE and predictor updates with more torch threads than
the caller's. This script times what a second thread buys per step on this machine, outside a training run:
a VAE step (eq 8, Adam) on ``--vae-batch`` 32x32 RGB images and a predictor step (the 5x512 MLP, Adam) on
``--predictor-batch`` pairs of 128-d embeddings, each in a fresh Python thread (as the module's update thread)
with 1 and with 2 torch threads while the main thread keeps 1, ``--repeats`` times alternately, after 3 warm-up
steps. It prints the mean milliseconds per step, the speed-up, and whether the two counts gave the same weights
to the bit after ``--steps`` steps (some matrix products split their sums by thread, so they may not).

The third arm is the module's own VAE step with ``vae_shards=2`` (opt-in; the default is 1): the two halves, 1 torch
thread each, one after the other (1 thread: ``update_threads=1``) or in parallel (2 threads: ``update_threads=2``),
their gradients added in a fixed order, so the weights must be the same with both counts.
"""

from __future__ import annotations

import argparse
import platform
import sys
import threading
import time
from typing import Callable

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_gocu.curiosity.module import GoalCuriosityModule
from sb3_gocu.curiosity.networks import ConvVAE, MasteryPredictor, mastery_loss, vae_loss


def vae_trainer(batch: int) -> tuple[th.nn.Module, Callable[[], None]]:
    th.manual_seed(0)
    vae = ConvVAE((3, 32, 32))
    opt = th.optim.Adam(vae.parameters(), 1e-3)
    gen = th.Generator().manual_seed(1)
    x, w = th.rand(batch, 3, 32, 32, generator=gen), th.ones(batch)
    vae.train()

    def step() -> None:
        loss, _, _ = vae_loss(vae, x, 1.0, w, generator=gen)
        opt.zero_grad()
        loss.backward()
        opt.step()

    return vae, step


def sharded_vae_trainer(batch: int, threads: int) -> tuple[th.nn.Module, Callable[[], None]]:
    """The module's VAE step (``vae_shards=2``) with ``threads`` shard threads, on 32x32 RGB images."""
    module = GoalCuriosityModule(spaces.Box(0, 255, (32, 32, 3), np.uint8), vae_batch_size=batch, vae_shards=2,
                                 update_threads=threads, seed=0)
    gen = th.Generator().manual_seed(1)
    x, w = th.rand(batch, 3, 32, 32, generator=gen), th.ones(batch)
    module.vae.train()

    def step() -> None:
        stepped, _ = module._vae_step(x, w)
        assert stepped

    return module.vae, step


def predictor_trainer(batch: int) -> tuple[th.nn.Module, Callable[[], None]]:
    th.manual_seed(0)
    predictor = MasteryPredictor(128)
    opt = th.optim.Adam(predictor.parameters(), 5e-4)
    gen = th.Generator().manual_seed(1)
    a, b, y = th.randn(batch, 128, generator=gen), th.randn(batch, 128, generator=gen), th.rand(batch, generator=gen)
    predictor.train()

    def step() -> None:
        loss = mastery_loss(predictor(a, b), y)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()

    return predictor, step


def timed(make: Callable[[int], tuple[th.nn.Module, Callable[[], None]]], threads: int, steps: int) -> tuple[float, th.Tensor]:
    """ms per step and the final weights, trained in a fresh thread with ``threads`` torch threads."""
    out: dict[str, object] = {}

    def work() -> None:
        th.set_num_threads(threads)
        net, step = make(threads)
        for _ in range(3):
            step()
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        out["ms"] = (time.perf_counter() - t0) / steps * 1000
        out["weights"] = th.cat([p.detach().flatten() for p in net.parameters()])

    worker = threading.Thread(target=work)
    worker.start()
    worker.join()
    return out["ms"], out["weights"]  # type: ignore[return-value]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--vae-batch", type=int, default=128)
    parser.add_argument("--predictor-batch", type=int, default=128)
    args = parser.parse_args()
    for name, value in (("steps", args.steps), ("repeats", args.repeats), ("vae-batch", args.vae_batch), ("predictor-batch", args.predictor_batch)):
        if value < 1:
            parser.error(f"--{name} must be >= 1, got {value}")
    th.set_num_threads(1)
    th.get_num_threads()  # fixes the main thread's count before a worker changes torch's default for new threads
    print("Command: python " + " ".join(sys.argv))
    print(f"machine: {platform.machine()}, torch {th.__version__}, main thread 1 torch thread")
    arms = {
        "VAE": lambda threads: vae_trainer(args.vae_batch),
        "predictor": lambda threads: predictor_trainer(args.predictor_batch),
        "VAE 2 parts": lambda threads: sharded_vae_trainer(args.vae_batch, threads),
    }
    for name, make in arms.items():
        ms: dict[int, list[float]] = {1: [], 2: []}
        weights: dict[int, th.Tensor] = {}
        for _ in range(args.repeats):
            for threads in (1, 2):
                t, weights[threads] = timed(make, threads, args.steps)
                ms[threads].append(t)
        one, two = sum(ms[1]) / len(ms[1]), sum(ms[2]) / len(ms[2])
        same = th.equal(weights[1], weights[2])
        print(f"{name:11s} 1 thread {one:7.1f} ms/step   2 threads {two:7.1f} ms/step   speed-up {one / two:.2f}x   "
              f"same weights after {args.steps} steps: {same}"
              + ("" if same else f" (largest difference {float((weights[1] - weights[2]).abs().max()):.2e})"))
        assert th.get_num_threads() == 1, "the main thread's count is its own"


if __name__ == "__main__":
    main()
