"""Is the VAE's encoder alive on a run's frames? The dead-encoder check of every checkpoint of a PPO_GoCu run.

    python benchmarks/probes/encoder_alive.py <out>/checkpoints/ppo_gocu_seed0

A checkpoint holds the module's VAE as the run left it: after the pretraining (checkpoints before the first later
VAE update) or after the latest VAE update (``last update`` says at which recorded step it was made). For each
checkpoint, on up to ``--frames`` distinct frames of its memory bank (the frames the VAE trains on) and on its goals:

* ``alive``: how many of the embedding's units (the encoder's ReLU layer, phi) are positive on some frame; none is a
  dead encoder, every frame embedded to one point (the Sawyer reacher's failure, docs/results.md);
* ``spread``: std of phi over the frames, mean over units;
* ``one point``: the module's own rollback test (``Trainer.embeds_to_one_point``) on those frames;
* goals: how many the buffer holds, how many distinct embeddings they have, and their median pairwise distance.

``--init-seeds N`` adds, on the first checkpoint's frames, the same figures for N freshly initialised VAEs of the same
shape (PyTorch's initialisation, torch seeds 0 to N-1): the encoder before its pretraining.

Reads checkpoints only (no env, no training).
"""

from __future__ import annotations

import argparse
import copy
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.stores import distinct_rows
from sb3_gocu.curiosity.training import torch_threads

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # sample_efficiency (benchmarks/)
from sample_efficiency import machine_line


def fresh_units(model_path: Path, n_frames: int, seed: int, torch_seeds: int) -> list[tuple[int, float]]:
    """(alive units, spread) of freshly initialised copies of the checkpoint's VAE on its memory bank's frames."""
    mod = PPO_GoCu.load(model_path, device="cpu").curiosity
    assert mod is not None, f"{model_path} carries no curiosity module"
    bank = mod.memory.observations[: mod.memory.size]
    x = mod.adapter.to_tensor(bank[np.random.default_rng(seed).permutation(distinct_rows(bank)[0])[:n_frames]], mod.device)
    out = []
    for s in range(torch_seeds):
        th.manual_seed(s)
        vae = copy.deepcopy(mod.vae)
        for layer in vae.modules():
            if hasattr(layer, "reset_parameters"):
                layer.reset_parameters()
        with th.no_grad():
            phi = vae.eval().embed(x)
        out.append((int((phi > 0).any(0).sum()), float(phi.std(0).mean())))
    return out


def measure(model_path: Path, n_frames: int, seed: int) -> dict[str, Any]:
    """The encoder's figures on one checkpoint's memory bank and goals."""
    model = PPO_GoCu.load(model_path, device="cpu")
    mod = model.curiosity
    assert mod is not None, f"{model_path} carries no curiosity module"
    bank = mod.memory.observations[: mod.memory.size]
    first = distinct_rows(bank)[0]
    frames = bank[np.random.default_rng(seed).permutation(first)[:n_frames]]
    goals = mod.goal_buffer.observations[: mod.goal_buffer.size]
    with th.no_grad():
        phi = mod.vae.eval().embed(mod.adapter.to_tensor(frames, mod.device))
        phi_g = mod.vae.embed(mod.adapter.to_tensor(goals, mod.device)) if len(goals) else th.zeros(0, phi.shape[1])
    dists = th.pdist(phi_g) if len(phi_g) > 1 else th.zeros(1)
    return {"steps": int(model.num_timesteps), "last_update": int(mod.last_vae_update), "frames": len(frames),
            "alive": int((phi > 0).any(0).sum()), "units": phi.shape[1], "spread": float(phi.std(0).mean()),
            "one_point": mod.trainer.embeds_to_one_point(frames), "goals": len(goals),
            "goal_embeddings": len(th.unique(phi_g, dim=0)), "goal_median_dist": float(dists.median())}


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoints", type=Path, help="a run's checkpoint folder (model_<steps>.zip files)")
    p.add_argument("--frames", type=int, default=2048, help="distinct memory-bank frames measured per checkpoint")
    p.add_argument("--seed", type=int, default=0, help="which frames are drawn")
    p.add_argument("--init-seeds", type=int, default=0, help="also measure this many freshly initialised VAEs")
    args = p.parse_args(argv)
    if args.init_seeds < 0:
        p.error(f"--init-seeds must be >= 0, got {args.init_seeds}")
    if args.frames < 2:
        p.error(f"--frames must be >= 2, got {args.frames}")
    paths = sorted(args.checkpoints.glob("model_*.zip"), key=lambda q: int(re.findall(r"\d+", q.stem)[0]))
    if not paths:
        p.error(f"no model_<steps>.zip in {args.checkpoints}")
    with torch_threads(1):  # the caller's count comes back on return
        print("command: python " + " ".join([Path(sys.argv[0]).as_posix(), "<checkpoints>", *sys.argv[2:]]))
        print(f"machine: {machine_line(1)}")
        print(f"{'steps':>8} {'last update':>11} {'frames':>6} {'alive':>8} {'spread':>8} {'one point':>9} {'goals':>5} {'distinct':>8} {'median dist':>11}")
        rows = []
        for path in paths:
            r = measure(path, args.frames, args.seed)
            rows.append(r)
            alive = f"{r['alive']}/{r['units']}"
            print(f"{r['steps']:>8} {r['last_update']:>11} {r['frames']:>6} {alive:>8} {r['spread']:>8.4f} "
                  f"{r['one_point']!s:>9} {r['goals']:>5} {r['goal_embeddings']:>8} {r['goal_median_dist']:>11.3f}", flush=True)
        for s, (alive, spread) in enumerate(fresh_units(paths[0], args.frames, args.seed, args.init_seeds)):
            print(f"freshly initialised (torch seed {s}), the first checkpoint's frames: alive {alive}/{rows[0]['units']}, spread {spread:.4g}")
        return rows


if __name__ == "__main__":
    main()
