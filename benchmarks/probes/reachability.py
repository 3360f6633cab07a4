"""Which training pairs teach the mastery predictor what r_gc asks of it? Offline, on random-policy DoorKey episodes.

    python benchmarks/probes/reachability.py --env GoCu/DoorKey-8x8-v0 --steps 100000 --adam 256 1024 2048 --threads 1 --seed 0

Plays a random policy for ``--steps`` steps (16 envs), pretrains a module's VAE on the first 10,000 frames as
``PPO_GoCu`` does, embeds every frame with it, and splits the episodes: 80% to train on, 20% (other layouts) to test
on. Each variant trains a fresh predictor (the module's network and optimiser settings) on pairs drawn from the
training episodes and is scored on pairs of the test episodes:

* ``auc_far``: gap <= 5 steps against gap >= d_max = 30, same episode;
* ``auc_goals``: gap <= 5 against goals drawn as the goal buffer draws them (episode ends and proportional steps of
  other episodes), the negatives r_gc meets when it scores.

Variants: ``eq16``, the pairs and labels an update used before (gap 1..d_max, first-visit distance, eq 15-16 soft
labels with the predictor as prior); ``gap``, hard labels with positives <= k steps, negatives >= d_max in the same
episode, nothing between; ``gap+goals``, the same plus negatives against frames of other episodes (the goal buffer's
distribution); each with pixel-identical pairs dropped where the name ends in ``-distinct``.

``--vae-update-epochs E`` adds one warm VAE update of at most E epochs after the pretraining, on a memory bank of all
the later frames (what a budget on the VAE's updates costs the predictor).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch as th

import sb3_gocu  # noqa: F401
from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.networks import MasteryPredictor, mastery_loss
from sb3_gocu.curiosity.reachability import auc
from sb3_gocu.curiosity.reward import complexity_score, mastered_probability
from sb3_gocu.curiosity.stores import observation_key

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402


def collect(env_id: str, steps: int, seed: int) -> list[np.ndarray]:
    """Episodes (raw frames s_1..s_T) of a random policy over 16 envs."""
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(env_id, n_envs=16, seed=seed)
    venv.action_space.seed(seed)
    venv.reset()
    current = [[] for _ in range(16)]
    episodes = []
    for _ in range(steps // 16):
        obs, _, dones, infos = venv.step(np.array([venv.action_space.sample() for _ in range(16)]))
        for e in range(16):
            current[e].append(infos[e]["terminal_observation"] if dones[e] else obs[e])
            if dones[e]:
                episodes.append(np.stack(current[e]))
                current[e] = []
    return episodes


def draw(episodes: list[np.ndarray], keys: list[list[bytes]], n: int, lo: int, hi: int, rng: np.random.Generator,
         distinct: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` pairs (episode, t, t + y), y uniform in [lo, hi] (hi clipped to the episode), optionally never the same view."""
    out = []
    while len(out) < n:
        e = int(rng.integers(len(episodes)))
        T = len(episodes[e])
        if T <= lo:
            continue
        y = int(rng.integers(lo, min(hi, T - 1) + 1))
        t = int(rng.integers(0, T - y))
        if distinct and keys[e][t] == keys[e][t + y]:
            continue
        out.append((e, t, t + y))
    a = np.array(out)
    return a[:, 0], a[:, 1], a[:, 2]


def goal_like(episodes: list[np.ndarray], n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Frames drawn as goals are: an episode's end, or a step drawn with weight proportional to its index."""
    e = rng.integers(len(episodes), size=n)
    t = np.array([len(episodes[i]) - 1 if rng.random() < 1 / 8 else int(rng.choice(len(episodes[i]), p=np.arange(1, len(episodes[i]) + 1) / (len(episodes[i]) * (len(episodes[i]) + 1) / 2)))
                  for i in e])
    return e, t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--steps", type=int, default=100_000)
    p.add_argument("--adam", type=int, nargs="+", default=[256, 1024, 2048], help="Adam steps (batch 128) at which to score")
    p.add_argument("--variants", nargs="+", default=["eq16", "gap", "gap+goals", "gap+goals-distinct"])
    p.add_argument("--near", type=int, default=5, help="k: positives are at most k steps apart")
    p.add_argument("--hidden", type=int, nargs="+", default=None, help="the predictor's hidden layers (default: the module's)")
    p.add_argument("--vae-update-epochs", type=int, default=None,
                   help="after the pretraining, one warm VAE update of at most this many epochs (early stopping as the module's) "
                   "on a memory bank of every later frame, as a run's first update sees it (default: none)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    th.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    episodes = collect(args.env, args.steps, args.seed)
    import gymnasium as gym

    space = gym.make(args.env).observation_space
    module = GoalCuriosityModule(space, seed=args.seed)
    cfg = module.config
    frames = np.concatenate(episodes)[: cfg.pretrain_steps]
    module.memory.add(frames, module.rng)
    module.pretrain()
    if args.vae_update_epochs is not None:
        module.memory.add(np.concatenate(episodes)[cfg.pretrain_steps :], module.rng)
        fit = module.train_vae(epochs=args.vae_update_epochs)
        print(f"VAE update: at most {args.vae_update_epochs} epochs: {fit['vae_epochs_run']:.0f} run, best {fit['vae_best_epoch']:.0f}, "
              f"{fit['vae_observations']:.0f} distinct observations, {fit['vae_time']:.1f} s")
    phi = [module.embed(ep) for ep in episodes]
    keys = [[observation_key(x) for x in ep] for ep in episodes]
    print(f"{len(episodes)} episodes, {sum(map(len, episodes))} frames, collected and VAE pretrained in {time.perf_counter() - t0:.0f} s")
    order = rng.permutation(len(episodes))
    n_test = len(episodes) // 5
    test, train = sorted(order[:n_test]), sorted(order[n_test:])
    tr_eps, tr_phi, tr_keys = [episodes[i] for i in train], [phi[i] for i in train], [keys[i] for i in train]
    te_eps, te_phi, te_keys = [episodes[i] for i in test], [phi[i] for i in test], [keys[i] for i in test]
    D = cfg.max_distance

    def emb(phis: list[th.Tensor], e: np.ndarray, t: np.ndarray) -> th.Tensor:
        return th.stack([phis[i][j] for i, j in zip(e, t)])

    # the test pairs, fixed across variants
    e, t, g = draw(te_eps, te_keys, 2000, 1, args.near, rng, distinct=False)
    near = (emb(te_phi, e, t), emb(te_phi, e, g))
    e, t, g = draw(te_eps, te_keys, 2000, D, 10**9, rng, distinct=False)
    far = (emb(te_phi, e, t), emb(te_phi, e, g))
    ge, gt = goal_like(te_eps, 2000, rng)
    goals = (near[0], emb(te_phi, ge, gt))  # the near pairs' states against goals of (mostly) other episodes

    def score(pred: MasteryPredictor) -> tuple[float, float, float, float]:
        pred.eval()
        with th.no_grad():
            m_near, m_far, m_goal = (pred.mastery(*x) for x in (near, far, goals))
        pred.train()
        return auc(m_near, m_far), auc(m_near, m_goal), float(m_near.mean()), float(m_far.mean())

    def batch_eq16(pred: MasteryPredictor, n: int) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        e, t, g = draw(tr_eps, tr_keys, n, 1, D, rng, distinct=False)
        dist = []
        for i, a, b in zip(e, t, g):  # first-visit distance
            k = next(j for j in range(a, b + 1) if tr_keys[i][j] == tr_keys[i][b])
            dist.append(k - a)
        s, gg = emb(tr_phi, e, t), emb(tr_phi, e, g)
        with th.no_grad():
            pred.eval()
            prior = 1 - pred.mastery(s, gg)
            pred.train()
        target = mastered_probability(complexity_score(prior, th.tensor(dist, dtype=th.float32), cfg.prior_weight, cfg.distance_weight),
                                      cfg.label_threshold, cfg.label_slope)
        return s, gg, target

    def batch_gap(n: int, with_goals: bool, distinct: bool) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        n_pos = n // 2
        n_goal = n // 4 if with_goals else 0
        e, t, g = draw(tr_eps, tr_keys, n_pos, 1, args.near, rng, distinct)
        s = [emb(tr_phi, e, t)]
        gg = [emb(tr_phi, e, g)]
        e, t, g = draw(tr_eps, tr_keys, n - n_pos - n_goal, D, 10**9, rng, distinct)
        s.append(emb(tr_phi, e, t)), gg.append(emb(tr_phi, e, g))
        if n_goal:
            e, t, _ = draw(tr_eps, tr_keys, n_goal, 0, 0, rng, False)
            ge, gt = goal_like(tr_eps, n_goal, rng)
            s.append(emb(tr_phi, e, t)), gg.append(emb(tr_phi, ge, gt))
        target = th.cat([th.ones(n_pos), th.zeros(n - n_pos)])
        return th.cat(s), th.cat(gg), target

    print(f"test pairs: {len(near[0])} near (<= {args.near}), {len(far[0])} far (>= {D}), {len(goals[1])} goal-like; "
          f"CPU {cpu_model()}, {args.threads} torch thread(s), seed {args.seed}")
    print("variant | Adam steps | auc_far | auc_goals | mean m near / far | seconds")
    for variant in args.variants:
        th.manual_seed(args.seed)
        pred = MasteryPredictor(cfg.embed_dim, args.hidden or cfg.predictor_hidden)
        opt = th.optim.Adam(pred.parameters(), lr=cfg.predictor_lr)
        pred.train()
        t0, done = time.perf_counter(), 0
        for target_steps in args.adam:
            while done < target_steps:
                if variant == "eq16":
                    s, g, y = batch_eq16(pred, cfg.predictor_batch_size)
                else:
                    s, g, y = batch_gap(cfg.predictor_batch_size, "goals" in variant, variant.endswith("distinct"))
                loss, _ = mastery_loss(pred(s, g), y)
                opt.zero_grad()
                loss.backward()
                opt.step()
                done += 1
            a_far, a_goal, m_near, m_far = score(pred)
            print(f"{variant} | {done} | {a_far:.3f} | {a_goal:.3f} | {m_near:.2f} / {m_far:.2f} | {time.perf_counter() - t0:.0f}", flush=True)


if __name__ == "__main__":
    main()
