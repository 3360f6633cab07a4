"""How much predictor training does one update need? Validation loss per epoch for several pair budgets.

    python benchmarks/probes/predictor_epochs.py <run>/checkpoints/ppo_gocu_seed0/model_<steps>.zip \\
        --pairs 1024 2048 4096 8192 --epochs 15 --threads 1 --seed 0

Loads a PPO_GoCu checkpoint and replays the predictor update that was due next, on the trajectories the
module holds (the last P_m steps; with ``--collect STEPS``, on STEPS fresh steps of the checkpoint's own policy
instead, e.g. when a VAE update has just cleared them), once per ``--pairs`` budget, each time from the
checkpoint's predictor and optimiser state:

* training pairs: ``predictor_pairs = P`` drawn as in training (``--seed``), de-duplicated as in training;
* validation pairs: ``--val-pairs`` drawn with another generator (``--seed + 1``) from the same trajectories, labelled
  (eq 15-16) with the checkpoint's predictor as the prior, as the training pairs are;
* after each epoch: the validation cross-entropy against the soft labels, the accuracy against the labels
  thresholded at 0.5, and the mean |m - m_ref| over the validation pairs, where m_ref is the mastery predicted
  after the largest budget's last epoch (the paper-like update, the reference); and the seconds of training so far.

A budget whose curves reach the reference's loss and |m - m_ref| early costs less for the same predictor. The
validation pairs come from the same trajectories as the training pairs (different draws), so they measure
the fit to the data of this update, not generalisation to the next P_m steps.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import platform
import sys
import time
from typing import Any, Sequence

import numpy as np
import torch as th

import sb3_gocu  # noqa: F401
from sb3_gocu.curiosity.training import Trainer
from sb3_gocu import PPO_GoCu


def soft_cross_entropy(m: th.Tensor, target: th.Tensor) -> float:
    m = m.clamp(1e-7, 1 - 1e-7)
    return float(-(target * m.log() + (1 - target) * (1 - m).log()).mean())


def collect(model: PPO_GoCu, env_id: str, steps: int, n_envs: int, seed: int) -> None:
    """Play the model's stochastic policy for ``steps`` env steps; its module records the trajectories (the
    memory bank and the normaliser move too, as in training; nothing is trained)."""
    from stable_baselines3.common.env_util import make_vec_env

    model.set_env(make_vec_env(env_id, n_envs=n_envs, seed=seed))
    env = model.get_env()
    mod = model.curiosity
    mod.trajectories.clear()
    mod.recording = True
    obs = env.reset()
    for _ in range(-(-steps // n_envs)):
        actions, _ = model.predict(obs, deterministic=False)
        obs, _, _, _ = env.step(actions)
    mod.recording = False


def probe(path: str, pairs: Sequence[int], epochs: int, val_pairs: int, seed: int, env_id: str | None = None,
          collect_steps: int = 0, n_envs: int = 16) -> dict[str, Any]:
    model = PPO_GoCu.load(path, device="cpu")
    mod = model.curiosity
    assert mod is not None
    if collect_steps:
        collect(model, env_id or "GoCu/DoorKey-8x8-v0", collect_steps, n_envs, seed)
    if len(mod.trajectories) < 2:
        raise SystemExit(f"{path}: the module holds no trajectories (a VAE update clears them); use --collect STEPS")
    start = copy.deepcopy((mod.predictor.state_dict(), mod.trainer.predictor_optimizer.state_dict()))
    vs, vg, vd = mod.trajectories.sample_pairs(val_pairs, mod.max_distance, np.random.default_rng(seed + 1), first_visit=mod.first_visit_distance)
    mod.predictor.eval()
    v_target = mod.trainer.label_pairs(vs, vg, vd)
    with th.no_grad():
        m0 = mod.predictor.mastery(vs, vg)
    curves: dict[int, list[dict[str, float]]] = {}
    masteries: dict[int, list[th.Tensor]] = {}
    for budget in pairs:
        mod.predictor.load_state_dict(start[0])
        # the module's own training code, with this budget and epoch count
        config = dataclasses.replace(mod.config, predictor_pairs=budget, predictor_epochs=epochs)
        trainer = Trainer(mod.vae, mod.predictor, config, mod.adapter, mod.device, th.Generator().manual_seed(seed))
        trainer.predictor_optimizer.load_state_dict(start[1])
        pairs_drawn = mod.trajectories.sample_pairs(budget, config.max_distance, np.random.default_rng(seed), first_visit=config.first_visit_distance)
        job = trainer.predictor_job(*pairs_drawn)
        assert job is not None
        rows: list[dict[str, float]] = []
        ms: list[th.Tensor] = []
        clock = {"t": time.perf_counter(), "train": 0.0}

        def on_epoch(epoch: int) -> None:
            clock["train"] += time.perf_counter() - clock["t"]
            mod.predictor.eval()
            with th.no_grad():
                m = mod.predictor.mastery(vs, vg)
            mod.predictor.train()
            ms.append(m)
            rows.append({
                "epoch": epoch + 1,
                "train_s": clock["train"],
                "val_loss": soft_cross_entropy(m, v_target),
                "val_acc": float(((m > 0.5) == (v_target > 0.5)).float().mean()),
                "distinct_pairs": float(len(job.phi_s)),
            })
            clock["t"] = time.perf_counter()

        trainer.fit_predictor(job, on_epoch=on_epoch)
        curves[budget], masteries[budget] = rows, ms
    ref = masteries[max(pairs)][-1]  # the largest budget's last epoch: the reference
    for budget, rows in curves.items():
        for r, m in zip(rows, masteries[budget]):
            r["mean_abs_diff_ref"] = float((m - ref).abs().mean())
    return {
        "start_val_loss": soft_cross_entropy(m0, v_target),
        "start_val_acc": float(((m0 > 0.5) == (v_target > 0.5)).float().mean()),
        "labelled_mastered": float((v_target > 0.5).float().mean()),
        "curves": curves,
        "steps": int(model.num_timesteps),
    }


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", help="a PPO_GoCu model or checkpoint zip")
    p.add_argument("--pairs", type=int, nargs="+", default=[1024, 2048, 4096, 8192])
    p.add_argument("--epochs", type=int, default=15)
    p.add_argument("--val-pairs", type=int, default=8192)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    p.add_argument("--collect", type=int, default=0, metavar="STEPS",
                   help="first play the model's policy for STEPS env steps on --env and replay the update on those trajectories "
                        "(default 0: use the trajectories saved in the checkpoint)")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0", help="env id for --collect")
    p.add_argument("--n-envs", type=int, default=16, help="envs for --collect")
    args = p.parse_args(argv)
    th.set_num_threads(args.threads)
    out = probe(args.model, args.pairs, args.epochs, args.val_pairs, args.seed, args.env, args.collect, args.n_envs)
    print("command: python " + " ".join(sys.argv))
    if args.collect:
        print(f"trajectories: {args.collect} steps of the checkpoint's policy on {args.env}, {args.n_envs} envs, seed {args.seed}")
    print(f"machine: {platform.machine()}, {th.get_num_threads()} torch threads, torch {th.__version__}; checkpoint at {out['steps']} steps")
    print(f"validation pairs: {args.val_pairs}, labelled mastered {out['labelled_mastered']:.3f}; before the update: "
          f"loss {out['start_val_loss']:.4f}, accuracy {out['start_val_acc']:.3f}")
    print(f"{'pairs':>6} {'distinct':>8} {'epoch':>5} {'train s':>8} {'val loss':>9} {'val acc':>8} {'|m - m_ref|':>11}")
    for budget, rows in sorted(out["curves"].items()):
        for r in rows:
            print(f"{budget:>6} {int(r['distinct_pairs']):>8} {r['epoch']:>5} {r['train_s']:>8.2f} {r['val_loss']:>9.4f} "
                  f"{r['val_acc']:>8.3f} {r['mean_abs_diff_ref']:>11.4f}")
    return out


if __name__ == "__main__":
    main()
