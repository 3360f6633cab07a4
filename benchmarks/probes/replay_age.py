"""How a replay buffer's stored curiosity rewards age: the same states scored by the curiosity of two checkpoints.

    python benchmarks/probes/replay_age.py <run>/checkpoints/dqn_sum_seed0

An off-policy learner on ``GoCuVecEnvWrapper(mode="sum")`` (``dqn_sum`` of ``benchmarks/sample_efficiency.py``)
stores each transition's reward as it was paid, ``r_e + sigma * r_gc``, and learns from it for as long as the
transition stays in the buffer (DQN's 100,000 transitions: 100,000 env steps). Meanwhile the predictor, the VAE, the
goals and the normaliser of eq 14 change, and nothing relabels the stored r_gc. This probe takes a run's two
curiosity checkpoints (default: the two newest; ``--older`` / ``--newer`` choose others), scores ``--states``
observations drawn from the newer one's memory (its VAE bank, a sample of the states seen) with each, every state
against the goals one env held at that checkpoint (state i against env i mod n_envs), and prints what a stale reward
looks like: the mean normalised r_gc under each, the mean absolute change relative to the newer mean, and the
correlation of the two scorings (Pearson, and Spearman on ranks). States are scored as first visits (a revisit pays
less under ``revisit_decay``, in both). For envs whose observations GoCu keeps whole (DoorKey, the MuJoCo ids; not
Atari's stacked, downsampled frames). Returns the figures as a dict.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch as th

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import GoalCuriosityModule
from sb3_gocu.curiosity.training import torch_threads


def load_module(ckpt_dir: Path, steps: int) -> GoalCuriosityModule:
    """The curiosity module of ``curiosity_<steps>.pth``, built as the run built it (``state_<steps>.json``)."""
    config = json.loads((ckpt_dir / f"state_{steps}.json").read_text())["config"]
    space = gym.make(config["env"]).observation_space
    module = GoalCuriosityModule(space, seed=config["seed"], **config.get("curiosity_kwargs", {}))
    module.load_state_dict(th.load(ckpt_dir / f"curiosity_{steps}.pth", weights_only=True))
    return module


def ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 0..n-1 of the values (ties in order of appearance)."""
    out = np.empty(len(x))
    out[np.argsort(x, kind="stable")] = np.arange(len(x))
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt_dir", type=Path, help="a run's checkpoint folder (<out>/checkpoints/<algo>_seed<seed>)")
    parser.add_argument("--older", type=int, help="steps of the older curiosity checkpoint (default: the second newest)")
    parser.add_argument("--newer", type=int, help="steps of the newer curiosity checkpoint (default: the newest)")
    parser.add_argument("--states", type=int, default=4096, help="observations of the memory scored (drawn without repeats)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draw")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (restored on return)")
    args = parser.parse_args(argv)
    if args.states < 2:
        parser.error(f"--states must be >= 2, got {args.states}")
    saved = sorted(int(p.stem.split("_")[1]) for p in args.ckpt_dir.glob("curiosity_*.pth"))
    newer = saved[-1] if args.newer is None and saved else args.newer
    older = next((s for s in reversed(saved) if newer is not None and s < newer), None) if args.older is None else args.older
    if newer is None or older is None or older not in saved or newer not in saved or older >= newer:
        parser.error(f"need two curiosity checkpoints, older before newer, in {args.ckpt_dir}; saved: {saved}")
    with torch_threads(args.threads):
        old, new = load_module(args.ckpt_dir, older), load_module(args.ckpt_dir, newer)
        memory = new.memory
        pick = np.random.default_rng(args.seed).permutation(memory.size)[: args.states]
        states = memory.observations[np.sort(pick)]
        if new.adapter.extract(states[:1]).shape != states[:1].shape:
            raise ValueError(f"{args.ckpt_dir}: GoCu keeps these observations cut or downsampled; this probe scores whole ones")
        envs = np.arange(len(states)) % new.n_envs
        scored = {}
        for name, module in (("older", old), ("newer", new)):
            raw = module.score_states(states, env_indices=envs)
            scored[name] = module.normalizer(raw, envs, update=False)
    a, b = scored["older"].astype(np.float64), scored["newer"].astype(np.float64)
    result = {
        "older": older, "newer": newer, "states": len(states),
        "mean_older": float(a.mean()), "mean_newer": float(b.mean()),
        "mean_abs_change_rel": float(np.abs(a - b).mean() / b.mean()) if b.mean() > 0 else float("nan"),
        "pearson": float(np.corrcoef(a, b)[0, 1]), "spearman": float(np.corrcoef(ranks(a), ranks(b))[0, 1]),
    }
    print(f"{len(states)} states of the memory at {newer:,} steps, scored (normalised r_gc, eq 14, first visits) by the "
          f"curiosity at {older:,} and at {newer:,} steps:")
    print(f"  mean {result['mean_older']:.4f} against {result['mean_newer']:.4f}; mean |change| "
          f"{result['mean_abs_change_rel']:.1%} of the newer mean; correlation {result['pearson']:.3f} "
          f"(Spearman {result['spearman']:.3f})")
    return result


if __name__ == "__main__":
    main()
