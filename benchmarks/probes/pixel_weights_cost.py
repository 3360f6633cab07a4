"""What ``vae_pixel_weighting`` costs: fitting the colour weights at a VAE update, and a VAE step with them.

    python benchmarks/probes/pixel_weights_cost.py --model <run>/model_800768.zip --steps 20 --repeats 3 --threads 1

From a saved PPO_GoCu model's memory bank (the observations a VAE update trains on; without ``--model``, 10,000
observations of DoorKey-8x8 under random actions), this times

* ``fit``: :meth:`PixelWeights.fit_observations` on the whole bank (de-duplicated and weighted by multiplicity, as the module's
  VAE update does; once per VAE update, i.e. every ``vae_train_freq`` steps);
* ``step``: one VAE optimiser step (eq 8, Adam) on a minibatch of ``--batch`` observations of the bank, with and
  without the weights, the two arms alternating ``--repeats`` times after 3 warm-up steps each, ``--steps`` steps
  per arm and repeat; it prints the mean milliseconds per step of each arm and their ratio (same run).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu/ ids)
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity import ConvVAE, PixelWeights, vae_loss
from sb3_gocu.curiosity.stores import distinct_rows

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402


def random_bank(n: int, seed: int) -> np.ndarray:
    """``n`` DoorKey-8x8 observations (C, H, W) under random actions."""
    env = make_vec_env("GoCu/DoorKey-8x8-v0", n_envs=16, seed=seed)
    rng = np.random.default_rng(seed)
    obs, out = env.reset(), []
    while sum(len(o) for o in out) < n:
        obs, _, _, _ = env.step(rng.integers(0, env.action_space.n, env.num_envs))
        out.append(obs.transpose(0, 3, 1, 2))
    return np.concatenate(out)[:n]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default=None, help="a saved PPO_GoCu model (its memory bank); default: random DoorKey-8x8 views")
    p.add_argument("--exponent", type=float, default=0.5, help="vae_pixel_weighting")
    p.add_argument("--batch", type=int, default=128, help="VAE minibatch (the module's vae_batch_size)")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    th.set_num_threads(args.threads)
    print("command: python " + " ".join(sys.argv))
    print(f"machine: {platform.machine()}, {cpu_model()}, {args.threads} torch threads, torch {th.__version__}")

    if args.model is not None:
        module = PPO_GoCu.load(args.model, device="cpu").curiosity
        bank = module.memory.observations[: module.memory.size]
        to_tensor = module.adapter.to_tensor
    else:
        bank = random_bank(10_000, args.seed)
        to_tensor = lambda raw: th.from_numpy(raw.astype(np.float32) / 255)  # noqa: E731
    first, inverse = distinct_rows(bank)
    data = bank[first]
    counts = np.bincount(inverse, minlength=len(first)).astype(np.float32)
    print(f"bank: {len(bank)} observations, {len(data)} distinct, shape {data.shape[1:]}")

    t0 = time.perf_counter()
    weights = PixelWeights.fit_observations(data, counts, to_tensor, args.exponent)
    fit_s = time.perf_counter() - t0
    used = weights.table[th.unique(PixelWeights.colour_ids(to_tensor(data[: min(len(data), 4096)])))]
    print(f"fit: {fit_s * 1000:.0f} ms; weights of the colours in view {float(used.min()):.3f} .. {float(used.max()):.1f}")

    rng = np.random.default_rng(args.seed)
    th.manual_seed(args.seed)
    vae = ConvVAE(tuple(data.shape[1:])).train()
    opt = th.optim.Adam(vae.parameters(), 1e-3)
    gen = th.Generator().manual_seed(args.seed)

    def step(pw: PixelWeights | None) -> None:
        idx = rng.integers(0, len(data), args.batch)
        x, w = to_tensor(data[idx]), th.from_numpy(counts[idx])
        loss, _, _ = vae_loss(vae, x, 1.0, w, generator=gen, pixel_weights=pw)
        opt.zero_grad()
        loss.backward()
        opt.step()

    times: dict[str, list[float]] = {"unweighted": [], "weighted": []}
    for _ in range(3):
        step(None), step(weights)
    for _ in range(args.repeats):
        for name, pw in (("unweighted", None), ("weighted", weights)):
            t0 = time.perf_counter()
            for _ in range(args.steps):
                step(pw)
            times[name].append((time.perf_counter() - t0) / args.steps)
    plain, weighted = np.mean(times["unweighted"]), np.mean(times["weighted"])
    print(f"VAE step, batch {args.batch}: unweighted {plain * 1000:.1f} ms, weighted {weighted * 1000:.1f} ms, "
          f"ratio {weighted / plain:.3f} ({args.repeats} repeats x {args.steps} steps, alternating)")
    return {"bank": len(bank), "distinct": len(data), "fit_s": fit_s, "weight_min": float(used.min()), "weight_max": float(used.max()),
            "step_s": {"unweighted": float(plain), "weighted": float(weighted)}, "ratio": float(weighted / plain)}


if __name__ == "__main__":
    main()
