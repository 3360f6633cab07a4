"""What ``split_updates`` buys: the module's VAE and predictor fits with and without it, and a short A/B run.

    python benchmarks/split_updates.py --repeats 3
    python benchmarks/split_updates.py --repeats 0 --learn-steps 110000

``split_updates`` (GoalCuriosityModule, default True) computes the large products of an update in two halves and
lets a thread that waits for the update compute the second halves. This script, with 1 torch thread and glibc's
allocator thresholds fixed (as ``throughput.py``):

* fits, outside a training run, the module's predictor on ``--pairs`` random pairs of 128-d embeddings (the
  labels' prior included, one epoch, minibatches of 128) and its VAE on ``--images`` random 32x32 RGB images for
  ``--vae-epochs`` epochs (minibatches of 128), as an update run in place: with ``split_updates=True`` the fit
  runs in a thread of its own and the calling thread helps it, as PPO_GoCu's training thread does while it waits
  for an update. Two modules of the same seed, one per setting, fit alternately ``--repeats`` times; it prints
  the seconds per fit, the speed-up, and whether the two settings gave the same weights to the bit;
* with ``--learn-steps N``, trains PPO_GoCu (paper settings, CnnPolicy, 16 envs, seed ``--seed``) for N steps
  on ``--env`` with each setting, and prints the wall time, the rollouts' waits for updates, the VAE's and the
  predictor's training time, how many halves were posted, and a hash of the policy's, VAE's and predictor's
  weights (the same hash: the same run).
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import os
import platform
import sys
import time
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_gocu.curiosity.module import GoalCuriosityModule
from sb3_gocu.curiosity.parallel import SplitWork

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from malloc_thresholds import fix_malloc_thresholds  # noqa: E402

IMAGE_SPACE = spaces.Box(0, 255, (32, 32, 3), np.uint8)


def weights(*modules: th.nn.Module) -> str:
    h = hashlib.sha256()
    for module in modules:
        for value in module.state_dict().values():
            h.update(value.detach().cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def fit_arms(pairs: int, images: int, vae_epochs: int, repeats: int, seed: int) -> list[dict[str, Any]]:
    """Time each fit with both settings, alternately; the weights after every fit must match."""
    rng = np.random.default_rng(seed)
    phi_s = th.from_numpy(rng.standard_normal((pairs, 128), dtype=np.float32)).relu_()
    phi_g = th.from_numpy(rng.standard_normal((pairs, 128), dtype=np.float32)).relu_()
    dist = th.from_numpy(rng.integers(1, 30, pairs).astype(np.float32))
    data = rng.integers(0, 256, (images, 32, 32, 3), dtype=np.uint8)
    w = np.ones(images, dtype=np.float32)
    modules = {split: GoalCuriosityModule(IMAGE_SPACE, split_updates=split, seed=seed) for split in (False, True)}
    fits = {
        "predictor": lambda m: m._fit_predictor(phi_s, phi_g, dist, threads=1),
        "vae": lambda m: m._fit_vae(data, w, vae_epochs, threads=1),
    }
    rows = []
    for name, fit in fits.items():
        times: dict[bool, list[float]] = {False: [], True: []}
        same = True
        for _ in range(repeats):
            for split, module in modules.items():
                t0 = time.perf_counter()
                module._helped(functools.partial(fit, module))
                times[split].append(time.perf_counter() - t0)
            net = "predictor" if name == "predictor" else "vae"
            same &= weights(getattr(modules[False], net)) == weights(getattr(modules[True], net))
        whole, split = float(np.mean(times[False])), float(np.mean(times[True]))
        rows.append({"fit": name, "whole_s": whole, "split_s": split, "speedup": whole / split, "same_weights": same})
    return rows


def learn_arms(env_id: str, steps: int, seed: int) -> list[dict[str, Any]]:
    from stable_baselines3.common.env_util import make_vec_env

    import sb3_gocu  # noqa: F401  (registers the GoCu ids)
    from sb3_gocu import PAPER_PPO_KWARGS, PPO_GoCu

    posted = [0]
    run2 = SplitWork.run2

    def counting(self: SplitWork, first: Any, second: Any) -> Any:
        posted[0] += bool(self.helpers)
        return run2(self, first, second)

    SplitWork.run2 = counting  # type: ignore[method-assign]
    rows = []
    try:
        for split in (False, True):
            posted[0] = 0
            venv = make_vec_env(env_id, n_envs=16, seed=seed)
            model = PPO_GoCu("CnnPolicy", venv, seed=seed, curiosity_kwargs={"split_updates": split}, **PAPER_PPO_KWARGS)
            t0 = time.perf_counter()
            model.learn(steps)
            mod = model.curiosity
            rows.append({"split_updates": split, "total_s": time.perf_counter() - t0, "update_waits_s": mod.time_update_wait,
                         "vae_training_s": mod.time_vae, "predictor_training_s": mod.time_predictor, "halves_posted": posted[0],
                         "weights": weights(model.policy, mod.vae, mod.predictor)})
    finally:
        SplitWork.run2 = run2  # type: ignore[method-assign]
    return rows


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=16384, help="predictor pairs per fit (the default predictor_pairs)")
    parser.add_argument("--images", type=int, default=2048, help="images of a VAE fit")
    parser.add_argument("--vae-epochs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3, help="fits per setting (0: none)")
    parser.add_argument("--learn-steps", type=int, default=0, help="also train PPO_GoCu this many steps with each setting")
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    malloc = "glibc mallopt trim 1 GiB, mmap 32 MiB" if fix_malloc_thresholds() else "glibc thresholds: default"
    print(f"command: python {' '.join(sys.argv)}")
    print(f"machine: {platform.machine()}, torch {th.__version__}, 1 torch thread, seed {args.seed}; {malloc}")
    out: dict[str, Any] = {"fits": [], "learn": []}
    if args.repeats > 0:
        out["fits"] = fit_arms(args.pairs, args.images, args.vae_epochs, args.repeats, args.seed)
        print(f"\nfits in place, mean of {args.repeats} (predictor: {args.pairs} pairs; VAE: {args.images} images x {args.vae_epochs} epochs)")
        print(f"{'fit':<10} {'whole (s)':>10} {'split, helped (s)':>18} {'speed-up':>9}  same weights")
        for r in out["fits"]:
            print(f"{r['fit']:<10} {r['whole_s']:>10.3f} {r['split_s']:>18.3f} {r['speedup']:>8.2f}x  {r['same_weights']}")
    if args.learn_steps > 0:
        out["learn"] = learn_arms(args.env, args.learn_steps, args.seed)
        print(f"\nPPO_GoCu on {args.env}, {args.learn_steps} steps, 16 envs, paper settings")
        print(f"{'split_updates':<14} {'total (s)':>10} {'update waits (s)':>17} {'VAE (s)':>8} {'predictor (s)':>14} {'halves posted':>14}  weights")
        for r in out["learn"]:
            print(f"{str(r['split_updates']):<14} {r['total_s']:>10.1f} {r['update_waits_s']:>17.1f} {r['vae_training_s']:>8.1f} "
                  f"{r['predictor_training_s']:>14.1f} {r['halves_posted']:>14}  {r['weights']}")
        print("same run (same weights):", len({r["weights"] for r in out["learn"]}) == 1)
    return out


if __name__ == "__main__":
    main()
