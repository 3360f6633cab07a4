"""Can the mastery predictor learn which goals are within reach, given more training or other inputs?

    python benchmarks/probes/predictor_capacity.py <run>/model_<steps>.zip --threads 1 --seed 0

Loads a PPO_GoCu checkpoint and plays its policy (``--episodes`` TRAIN VAL, other env seeds for each): pairs (s, g)
drawn from the first play train, pairs from the second validate (other layouts, as the reward meets them). Both
are labelled by eq 15-16 with the checkpoint's predictor as the prior, as an update labels them. Each variant
trains a predictor for a number of Adam steps on minibatches drawn from the training pool (no pair seen twice
until the pool is used up) and reports, on the validation pairs: the cross-entropy against the soft labels, the
accuracy against labels > 0.5, and the mean mastery per distance band. ``sep`` = mean m at distances 1-5 minus mean m
at 21-30: how well it tells near goals from far ones (the labels' own gap is about 1.0).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch as th
from torch import nn

import sb3_gocu  # noqa: F401
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.networks import MasteryPredictor, mastery_loss

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from skill_signal import first_visit_distance, play  # noqa: E402
from sb3_gocu.curiosity.stores import observation_key  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402

BANDS = ((0, 5), (6, 10), (11, 15), (16, 20), (21, 30))


class PairFeatures(nn.Module):
    """An MLP on [phi(s), phi(g), |phi(s) - phi(g)|, phi(s) * phi(g)] (a symmetric-friendly input)."""

    def __init__(self, embed_dim: int, hidden: Sequence[int]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        n_in = 4 * embed_dim
        for n_out in hidden:
            layers += [nn.Linear(n_in, n_out), nn.BatchNorm1d(n_out), nn.ReLU()]
            n_in = n_out
        self.net = nn.Sequential(*layers, nn.Linear(n_in, 2))

    def forward(self, s: th.Tensor, g: th.Tensor) -> th.Tensor:
        return self.net(th.cat([s, g, (s - g).abs(), s * g], dim=-1))


def pairs(model: PPO_GoCu, env_id: str, episodes: int, seed: int, n: int) -> dict[str, th.Tensor]:
    """``n`` pairs (s_t, s_{t+y}) from ``episodes`` episodes of the model's policy, y uniform in 1..d_max, with the
    first-visit distance the training uses; as phi (the module's embedding) and as pixels (the VAE's input)."""
    mod, cfg = model.curiosity, model.curiosity.config
    eps = [obs for obs, _ in play(model, env_id, episodes, seed) if len(obs) > 1]
    rng = np.random.default_rng(seed)
    s_raw, g_raw, dist, pair_keys, where = [], [], [], [], []
    for _ in range(n):
        e = int(rng.integers(len(eps)))
        obs = eps[e]
        y = int(rng.integers(1, min(cfg.max_distance, len(obs) - 1) + 1))
        t = int(rng.integers(0, len(obs) - y))
        keys = [observation_key(o) for o in obs[t : t + y + 1]]
        s_raw.append(obs[t]), g_raw.append(obs[t + y]), dist.append(first_visit_distance(keys, 0, y) if cfg.first_visit_distance else y)
        pair_keys.append(keys[0] + keys[-1])
        where.append((e, t, y))
    s_raw, g_raw = np.stack(s_raw), np.stack(g_raw)
    pixels = lambda raw: mod.adapter.to_tensor(raw, "cpu").flatten(1)  # noqa: E731
    return {"s": mod.embed(s_raw), "g": mod.embed(g_raw), "d": th.tensor(dist, dtype=th.float32), "s_pix": pixels(s_raw), "g_pix": pixels(g_raw),
            "steps": sum(len(o) for o in eps), "keys": pair_keys, "where": where}


def repeated_pairs(keys: list[bytes], where: list[tuple[int, int, int]], target: th.Tensor, dist: th.Tensor) -> str:
    """How noisy the labels are for a fixed pair of views: over the pairs (s, g) whose two views occur together at
    more than one place of the episodes (a place drawn twice counts once; s = g left out), the share of the label variance that the pair's identity explains (what a predictor that memorised
    every pair could explain, at most), and the mean spread of their distances."""
    groups: dict[bytes, dict[tuple[int, int, int], int]] = {}
    for i, (k, w) in enumerate(zip(keys, where)):
        if dist[i] > 0:  # s and g the same view: trivially within reach, left out
            groups.setdefault(k, {}).setdefault(w, i)
    rep = [np.array(list(places.values())) for places in groups.values() if len(places) > 1]
    idx = np.concatenate(rep)
    t, d = target.numpy(), dist.numpy()
    within = sum(((t[ix] - t[ix].mean()) ** 2).sum() for ix in rep) / len(idx)
    total = float(t[idx].var())
    d_std = float(np.mean([d[ix].std() for ix in rep]))
    n_places = sum(len(places) for places in groups.values())
    return (f"repeated view pairs: {len(rep)} pairs of views seen at more than one place ({len(idx)} of {n_places} distinct places); "
            f"their label variance {total:.4f}, within a pair of views {within:.4f} (the pair explains {1 - within / total:.2f}); "
            f"distance std within a pair of views {d_std:.2f} steps")


def evaluate(net: nn.Module, s: th.Tensor, g: th.Tensor, d: th.Tensor, target: th.Tensor) -> dict[str, float]:
    net.eval()
    with th.no_grad():
        m = th.softmax(net(s, g), -1)[:, 1].clamp(1e-6, 1 - 1e-6)
    out = {"loss": float(-(target * m.log() + (1 - target) * (1 - m).log()).mean()),
           "acc": float(((m > 0.5) == (target > 0.5)).float().mean())}
    for lo, hi in BANDS:
        sel = (d >= lo) & (d <= hi)
        out[f"m{lo}-{hi}"] = float(m[sel].mean()) if sel.any() else float("nan")
    out["sep"] = out["m0-5"] - out["m21-30"]
    return out


def train(net: nn.Module, lr: float, steps: int, batch: int, s: th.Tensor, g: th.Tensor, target: th.Tensor, seed: int,
          report: Callable[[int], None], report_at: Sequence[int]) -> None:
    opt = th.optim.Adam(net.parameters(), lr=lr)
    gen = th.Generator().manual_seed(seed)
    order, pos = th.randperm(len(s), generator=gen), 0
    for step in range(1, steps + 1):
        if pos + batch > len(s):
            order, pos = th.randperm(len(s), generator=gen), 0
        idx = order[pos : pos + batch]
        pos += batch
        net.train()
        loss, _ = mastery_loss(net(s[idx], g[idx]), target[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step in report_at:
            report(step)


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--episodes", type=int, nargs=2, default=[64, 32], help="episodes played for training and for validation pairs")
    p.add_argument("--train-pairs", type=int, default=131072)
    p.add_argument("--val-pairs", type=int, default=8192)
    p.add_argument("--steps", type=int, nargs="+", default=[128, 512, 2048])
    p.add_argument("--variants", nargs="+", default=["checkpoint", "fresh", "pair_features", "pixels"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    th.set_num_threads(args.threads)
    th.manual_seed(args.seed)
    model = PPO_GoCu.load(args.model, device="cpu")
    mod = model.curiosity
    cfg = mod.config
    tr = pairs(model, args.env, args.episodes[0], args.seed, args.train_pairs)
    va = pairs(model, args.env, args.episodes[1], args.seed + 1000, args.val_pairs)
    mod.predictor.eval()
    tr["target"], va["target"] = mod.trainer.label_pairs(tr["s"], tr["g"], tr["d"]), mod.trainer.label_pairs(va["s"], va["g"], va["d"])
    cpu = cpu_model()
    print("command: python benchmarks/probes/predictor_capacity.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {cpu}, torch {th.__version__}, {th.get_num_threads()} thread(s); checkpoint at {model.num_timesteps:,} steps; "
          f"train pairs {len(tr['d'])} from {tr['steps']} steps, validation pairs {len(va['d'])} from {va['steps']} other steps")
    lab = {f"{lo}-{hi}": float(va["target"][(va["d"] >= lo) & (va["d"] <= hi)].mean()) for lo, hi in BANDS}
    print("labels (validation) per distance band: " + ", ".join(f"{k} {v:.3f}" for k, v in lab.items())
          + f"; labelled mastered {float((va['target'] > 0.5).float().mean()):.3f}")
    print(repeated_pairs(tr["keys"], tr["where"], tr["target"], tr["d"]))
    print(f"{'variant':>14} {'steps':>6} {'loss':>7} {'acc':>6} " + " ".join(f"{f'm{lo}-{hi}':>7}" for lo, hi in BANDS) + f" {'sep':>6}")

    def build(variant: str) -> tuple[nn.Module, str]:
        if variant == "checkpoint":  # the module's predictor, trained on from where it is
            net = MasteryPredictor(cfg.embed_dim, cfg.predictor_hidden)
            net.load_state_dict(mod.predictor.state_dict())
            return net, ""
        if variant == "fresh":
            return MasteryPredictor(cfg.embed_dim, cfg.predictor_hidden), ""
        if variant == "pair_features":
            return PairFeatures(cfg.embed_dim, cfg.predictor_hidden), ""
        if variant == "pixels":  # the same MLP on the VAE's input instead of phi: is the embedding what loses the distance?
            return MasteryPredictor(tr["s_pix"].shape[1], cfg.predictor_hidden), "_pix"
        raise SystemExit(f"unknown variant {variant}")

    for variant in args.variants:
        net, suffix = build(variant)
        s, g = "s" + suffix, "g" + suffix

        def report(step: int, net: nn.Module = net, variant: str = variant, s: str = s, g: str = g) -> None:
            r = evaluate(net, va[s], va[g], va["d"], va["target"])
            t = evaluate(net, tr[s][:8192], tr[g][:8192], tr["d"][:8192], tr["target"][:8192])
            print(f"{variant:>14} {step:>6} {r['loss']:>7.4f} {r['acc']:>6.3f} " + " ".join(f"{r[f'm{lo}-{hi}']:>7.3f}" for lo, hi in BANDS)
                  + f" {r['sep']:>6.3f}   (train: loss {t['loss']:.4f}, sep {t['sep']:.3f})", flush=True)

        report(0)
        train(net, cfg.predictor_lr, max(args.steps), cfg.predictor_batch_size, tr[s], tr[g], tr["target"], args.seed, report, set(args.steps))


if __name__ == "__main__":
    main()
