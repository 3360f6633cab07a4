"""How much VAE training does one update need? Validation loss and embedding drift per epoch.

    # the first update (pretraining on random-policy observations, from fresh weights)
    python benchmarks/probes/vae_epochs.py --fresh GoCu/DoorKey-8x8-v0 --epochs 20 --threads 1 --seed 0
    # a later update: the checkpoint's VAE, on observations of the checkpoint's own policy
    python benchmarks/probes/vae_epochs.py <run>/checkpoints/ppo_gocu_seed0/model_<steps>.zip --collect 100000 --epochs 20

Replays one VAE update (eq 8) with the module's own training code (``Trainer.fit_vae``: de-duplicated memory bank,
multiplicities as weights, Adam state of the checkpoint) and measures after every epoch:

* ``val loss``: the negative ELBO (reconstruction + beta KL, eval mode) on held-out observations: ``--val-frac``
  of the distinct observations of the memory bank, left out of training;
* ``phi drift``: mean ||phi_e(x) - phi_ref(x)|| / mean ||phi_ref(x) - phi_0(x)|| over the held-out observations,
  where phi_0 is the embedding before the update and phi_ref after the last epoch: 1 = as far from the final
  embedding as before the update, 0 = the final embedding;
* ``nn agree``: fraction of held-out observations whose nearest neighbour among the goal buffer's observations
  (``--fresh``: among the training observations) is the same under phi_e as under phi_ref (the embedding's
  geometry is what the goal buffer and the predictor see);
* ``alive``: fraction of the embedding's units positive on some held-out observation (0: every observation embeds
  to one point, a dead encoder; the module rolls such an update back, docs/reliability.md);
* ``spread``: std of phi over the held-out observations, mean over units;
* the seconds of training so far (with ``--threads`` torch threads).

Sources of the memory bank: ``--fresh ENV`` builds a module with the default settings on ENV and fills it with
``pretrain_steps`` random-policy observations, as ``GoCuCallback`` does before the first rollout; a checkpoint
brings its own bank, and ``--collect STEPS`` replaces it by STEPS fresh steps of the checkpoint's policy (the
bank keeps a random subset of ``memory_size``), i.e. the data of the next update.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch as th

import sb3_gocu  # noqa: F401
from sb3_gocu.curiosity.training import VaeJob
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.training import EarlyStopping
from sb3_gocu.curiosity.networks import vae_loss

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]  # predictor_epochs (this folder), sample_efficiency (benchmarks/)
from predictor_epochs import collect  # noqa: E402
from sample_efficiency import machine_line  # noqa: E402


def fresh_module(env_id: str, n_envs: int, seed: int) -> GoalCuriosityModule:
    """A default module on ``env_id`` with its memory bank filled by random-policy steps (as before training)."""
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    mod = GoalCuriosityModule(env.observation_space, seed=seed)
    mod.recording = True
    env.action_space.seed(seed)
    obs = env.reset()
    mod.step(obs, np.zeros(n_envs, dtype=bool))
    for _ in range(-(-mod.pretrain_steps // n_envs)):
        obs, _, dones, infos = env.step(np.array([env.action_space.sample() for _ in range(n_envs)]))
        mod.step(obs, dones)
    env.close()
    return mod


def probe(mod: GoalCuriosityModule, epochs: int, val_frac: float, seed: int, references: np.ndarray | None) -> dict[str, Any]:
    job = mod.vae_job(epochs, patience=0)  # the probe holds out its own observations and runs every epoch
    if job is None:
        raise SystemExit("the module's memory bank is empty")
    data, weights = job.data, job.weights
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(data))
    n_val = max(1, int(round(val_frac * len(data))))
    val, train = order[:n_val], order[n_val:]
    x_val = mod.adapter.to_tensor(data[val], mod.device)
    w_val = th.from_numpy(weights[val])
    train_data, train_w = data[train], weights[train]
    train_w = (train_w * len(train_w) / train_w.sum()).astype(np.float32)
    refs = mod.adapter.to_tensor(train_data[: 2000] if references is None else references, mod.device)

    def measure() -> dict[str, Any]:
        mod.vae.eval()
        with th.no_grad():
            loss, recon, kl = vae_loss(mod.vae, x_val, mod.vae_beta, w_val)
            phi = mod.vae.embed(x_val)
            nn_idx = th.cdist(phi, mod.vae.embed(refs)).argmin(1)
        return {"val_loss": float(loss), "val_recon": float(recon), "val_kl": float(kl), "phi": phi, "nn": nn_idx,
                "alive": float((phi > 0).any(0).float().mean()), "spread": float(phi.std(0).mean())}

    start = measure()
    rows: list[dict[str, Any]] = []
    clock = {"t": time.perf_counter(), "train": 0.0}

    def on_epoch(epoch: int) -> None:
        clock["train"] += time.perf_counter() - clock["t"]
        m = measure()
        mod.vae.train()
        m.update(epoch=epoch + 1, train_s=clock["train"])
        rows.append(m)
        clock["t"] = time.perf_counter()

    mod.trainer.generator.manual_seed(seed)
    fit = mod.trainer.fit_vae(VaeJob(train_data, train_w, epochs, pixel_weights=job.pixel_weights), on_epoch=on_epoch)
    ref = rows[-1]
    base = float((ref["phi"] - start["phi"]).norm(dim=1).mean())
    for r in rows:
        r["phi_drift"] = float((r["phi"] - ref["phi"]).norm(dim=1).mean()) / max(base, 1e-12)
        r["nn_agree"] = float((r["nn"] == ref["nn"]).float().mean())
    start["nn_agree"] = float((start["nn"] == ref["nn"]).float().mean())
    stops = {}
    for patience in (1, 2, 3):  # the module's own rule, replayed on this probe's held-out losses
        stopping = EarlyStopping(start["val_loss"], patience)
        for r in rows:
            stopping.update(r["epoch"], r["val_loss"])
            if stopping.stop:
                break
        stops[patience] = (r["epoch"], stopping.best_epoch)
    return {"stops": stops, "collapsed": fit.collapsed, "start": start, "rows": rows, "distinct": len(data), "train": len(train), "val": n_val, "bank": mod.memory.size}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", nargs="?", help="a PPO_GoCu model or checkpoint zip (or use --fresh)")
    p.add_argument("--fresh", metavar="ENV", help="probe the pretraining update of a default module on ENV instead")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--val-frac", type=float, default=0.1, help="fraction of the distinct observations held out")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    p.add_argument("--collect", type=int, default=0, metavar="STEPS", help="with a checkpoint: refill the bank with STEPS steps of its policy")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0", help="env id for --collect")
    p.add_argument("--n-envs", type=int, default=16)
    args = p.parse_args(argv)
    if (args.model is None) == (args.fresh is None):
        p.error("give either a model path or --fresh ENV")
    if not 0 < args.val_frac < 1:
        p.error(f"--val-frac must be in (0, 1), got {args.val_frac}")
    th.set_num_threads(args.threads)
    if args.fresh:
        mod = fresh_module(args.fresh, args.n_envs, args.seed)
        refs, source, steps = None, f"fresh module on {args.fresh}, {mod.memory.size} random-policy observations", 0
    else:
        model = PPO_GoCu.load(args.model, device="cpu")
        mod = model.curiosity
        assert mod is not None
        if args.collect:
            mod.memory.size = 0
            collect(model, args.env, args.collect, args.n_envs, args.seed)
        refs = mod.goal_buffer.observations[: mod.goal_buffer.size]
        source = f"checkpoint {args.model} at {model.num_timesteps} steps" + (
            f", bank refilled by {args.collect} steps of its policy on {args.env}" if args.collect else ", its own bank")
        steps = int(model.num_timesteps)
    out = probe(mod, args.epochs, args.val_frac, args.seed, refs)
    out["steps"] = steps
    print("command: python " + " ".join(sys.argv))
    print(f"source: {source}")
    print(f"machine: {machine_line(th.get_num_threads())}; seed {args.seed}")
    print(f"memory bank {out['bank']}, distinct {out['distinct']}: train {out['train']}, held out {out['val']}; "
          f"vae_batch_size {mod.vae_batch_size}, beta {mod.vae_beta}")
    s = out["start"]
    print(f"before the update: val loss {s['val_loss']:.2f} (recon {s['val_recon']:.2f}, kl {s['val_kl']:.2f}), nn agree {s['nn_agree']:.3f}, "
          f"alive {s['alive']:.3f}, spread {s['spread']:.4g}")
    print(f"{'epoch':>5} {'train s':>8} {'val loss':>9} {'recon':>8} {'kl':>6} {'phi drift':>9} {'nn agree':>8} {'alive':>6} {'spread':>9}")
    for r in out["rows"]:
        print(f"{r['epoch']:>5} {r['train_s']:>8.2f} {r['val_loss']:>9.2f} {r['val_recon']:>8.2f} {r['val_kl']:>6.2f} "
              f"{r['phi_drift']:>9.3f} {r['nn_agree']:>8.3f} {r['alive']:>6.3f} {r['spread']:>9.4g}")
    if out["collapsed"]:
        print("the update embedded every observation to one point: the module rolls it back")
    for patience, (stop, best) in out["stops"].items():
        print(f"vae_patience {patience} would stop after epoch {stop} and keep epoch {best} (0: the weights before the update)")
    return out


if __name__ == "__main__":
    main()
