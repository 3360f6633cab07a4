"""Would a reachability network with its own encoder know near goals from far ones better than the module's predictor
on the VAE's phi, and would its r_gc follow the agent's progress? Offline, on a trained agent's own episodes.

    python benchmarks/probes/rnetwork.py <run>/model_501760.zip --episodes 128 --adam 2000 --threads 1 --seed 0

Plays ``--episodes`` episodes of the model's policy (``skill_signal.play``); 80% train, 20% (other layouts) test.
The pairs are the module's reachability pairs: near (gap 1..5, mastered), far (g first seen d_max or more steps after
s, same episode, not mastered) and s against a goal of the model's goal buffer (not mastered), half near, a quarter of
each other kind per batch. Each predictor is scored on pairs of the test episodes as the module logs an update:
``auc_far`` (near against far) and ``auc_goals`` (near against buffer goals).

* ``module``: the model's own predictor on phi, as saved;
* ``phi``: a fresh predictor of the module's shape on phi (the frozen VAE), ``--adam`` steps;
* ``r-network``: Episodic Curiosity's R-network (Savinov et al., 2019) made small: its own conv encoder of the
  pixels (:class:`RNetwork`), trained end to end with its comparator, the same steps and batches.

Then r_gc by phase (``skill_signal.phase_signal``) with the R-network's mastery in place of the module's, on the test
episodes: does it rank the least mastered phase first?
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch as th
from torch import nn

from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity.networks import MasteryPredictor
from sb3_gocu.curiosity.reachability import QUALITY_NEAR, auc
from sb3_gocu.curiosity.stores import observation_key

sys.path.insert(0, str(Path(__file__).resolve().parent))
import skill_signal  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402

Episode = tuple[np.ndarray, np.ndarray, bool]


class RNetwork(nn.Module):
    """m(s, g) from pixels: a conv encoder shared by s and g, and an MLP comparator on [e(s), e(g), e(s) * e(g)].

    :param channels: image channels
    :param size: image side in pixels
    :param embed: size of e
    :param hidden: width of the comparator's two hidden layers
    """

    def __init__(self, channels: int, size: int, embed: int = 64, hidden: int = 256) -> None:
        super().__init__()
        self.encoder = nn.Sequential(
            nn.Conv2d(channels, 32, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1, padding=1), nn.ReLU(), nn.Flatten(),
            nn.Linear(64 * (size // 4) ** 2, embed),
        )
        self.head = nn.Sequential(nn.Linear(3 * embed, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def compare(self, e_s: th.Tensor, e_g: th.Tensor) -> th.Tensor:
        """Logits of paired embeddings, (n,)."""
        return self.head(th.cat([e_s, e_g, e_s * e_g], dim=-1))[:, 0]

    def forward(self, x_s: th.Tensor, x_g: th.Tensor) -> th.Tensor:
        return self.compare(self.encoder(x_s), self.encoder(x_g))


class Pairs:
    """Draws the module's reachability pairs from episodes, as (state, goal) indices into a flat frame array.

    :param episodes: the episodes (raw frames first)
    :param far: d_max
    """

    def __init__(self, episodes: list[Episode], far: int) -> None:
        self.frames = np.concatenate([obs for obs, _, _ in episodes])
        self.starts = np.cumsum([0] + [len(obs) for obs, _, _ in episodes])
        self.keys = [[observation_key(o) for o in obs] for obs, _, _ in episodes]
        self.far = far

    def near(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        s, g = [], []
        while len(s) < n:
            e = int(rng.integers(len(self.keys)))
            length = len(self.keys[e])
            if length < 2:
                continue
            gap = int(rng.integers(1, min(QUALITY_NEAR, length - 1) + 1))
            t = int(rng.integers(0, length - gap))
            s.append(self.starts[e] + t), g.append(self.starts[e] + t + gap)
        return np.array(s), np.array(g)

    def far_pairs(self, n: int, rng: np.random.Generator, tries: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Pairs whose goal is first seen ``far`` or more steps after the state (fewer than ``n`` where they are rare)."""
        s, g = [], []
        for _ in range(n * tries):
            if len(s) == n:
                break
            e = int(rng.integers(len(self.keys)))
            keys = self.keys[e]
            if len(keys) <= self.far:
                continue
            t = int(rng.integers(0, len(keys) - self.far))
            u = int(rng.integers(t + self.far, len(keys)))
            if keys[u] not in keys[t : t + self.far]:
                s.append(self.starts[e] + t), g.append(self.starts[e] + u)
        return np.array(s, dtype=np.int64), np.array(g, dtype=np.int64)

    def states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.integers(len(self.frames), size=n)


def train_and_score(logits_of: Callable[[np.ndarray, np.ndarray], th.Tensor], net: nn.Module, fresh: bool, train: Pairs,
                    goals: np.ndarray, test: dict[str, tuple[np.ndarray, np.ndarray]], args: argparse.Namespace,
                    rng: np.random.Generator) -> dict[str, float]:
    """Trains ``net`` on ``train``'s pairs (``args.adam`` Adam steps, where ``fresh``), then scores it in eval mode on
    ``test`` (batch norm with its running statistics: a test batch holds one kind of pair only).

    :param logits_of: (raw states, raw goals) -> mastery logits (n,), through ``net``"""
    started = time.perf_counter()
    if fresh:
        net.train()
        optimiser = th.optim.Adam(net.parameters(), lr=args.lr)
        half, quarter = args.batch // 2, args.batch // 4
        for _ in range(args.adam):
            s_near, g_near = train.near(half, rng)
            s_far, g_far = train.far_pairs(quarter, rng)
            s_goal = train.states(args.batch - half - len(s_far), rng)
            g_goal = goals[rng.integers(len(goals), size=len(s_goal))]
            s = train.frames[np.concatenate([s_near, s_far, s_goal])]
            g = np.concatenate([train.frames[np.concatenate([g_near, g_far])], g_goal])
            target = th.cat([th.ones(len(s_near)), th.zeros(len(s_far) + len(s_goal))])
            loss = nn.functional.binary_cross_entropy_with_logits(logits_of(s, g), target)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    seconds = time.perf_counter() - started
    net.eval()
    with th.no_grad():
        scores = {kind: logits_of(s, g).float().numpy() for kind, (s, g) in test.items()}
    return {"auc_far": auc(scores["near"], scores["far"]), "auc_goals": auc(scores["near"], scores["goals"]),
            "train_s": seconds, "adam_steps": args.adam if fresh else 0}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--episodes", type=int, default=128)
    p.add_argument("--adam", type=int, default=2000, help="Adam steps of each fresh predictor")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--test-pairs", type=int, default=1024, help="pairs of each kind that score a predictor")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    threads = th.get_num_threads()
    th.set_num_threads(args.threads)
    try:
        return run(args, argv)
    finally:
        th.set_num_threads(threads)


def run(args: argparse.Namespace, argv: Sequence[str] | None) -> dict[str, Any]:
    th.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    cpu = cpu_model()
    print("command: python benchmarks/probes/rnetwork.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {cpu}, torch {th.__version__}, {args.threads} thread(s); seed {args.seed}")
    model = PPO_GoCu.load(args.model, device="cpu")
    module, cfg = model.curiosity, model.curiosity.config
    episodes = skill_signal.play(model, args.env, args.episodes, 1000 + args.seed)
    split = max(1, int(0.8 * len(episodes)))
    train, test_pairs = Pairs(episodes[:split], cfg.max_distance), Pairs(episodes[split:], cfg.max_distance)
    goals = module.goal_buffer.observations[: module.goal_buffer.size]
    s_near, g_near = test_pairs.near(args.test_pairs, rng)
    s_far, g_far = test_pairs.far_pairs(args.test_pairs, rng)
    test = {"near": (test_pairs.frames[s_near], test_pairs.frames[g_near]), "far": (test_pairs.frames[s_far], test_pairs.frames[g_far]),
            "goals": (test_pairs.frames[s_near], goals[rng.integers(len(goals), size=len(s_near))])}
    print(f"{len(episodes)} episodes ({split} train, {len(episodes) - split} test), {len(train.frames)} + {len(test_pairs.frames)} frames; "
          f"test pairs: {len(s_near)} near, {len(s_far)} far, {len(s_near)} against goals of the buffer ({len(goals)} goals)")

    def to_x(raw: np.ndarray) -> th.Tensor:
        return module.adapter.to_tensor(raw, th.device("cpu"))

    own = module.predictor  # scored in eval mode by train_and_score, as saved
    phi_predictor = MasteryPredictor(cfg.embed_dim, cfg.predictor_hidden)

    def phi_logits(predictor: MasteryPredictor) -> Callable[[np.ndarray, np.ndarray], th.Tensor]:
        def logits(s: np.ndarray, g: np.ndarray) -> th.Tensor:
            out = predictor(module.embed(s).clone(), module.embed(g).clone())
            return out[:, 1] - out[:, 0]
        return logits

    shape = module.adapter.input_shape
    rnet = RNetwork(shape[0], shape[1])
    results: dict[str, Any] = {"episodes": len(episodes)}
    arms = [("module", phi_logits(own), own, False), ("phi", phi_logits(phi_predictor), phi_predictor, True),
            ("r-network", lambda s, g: rnet(to_x(s), to_x(g)), rnet, True)]
    for name, logits_of, net, fresh in arms:
        res = train_and_score(logits_of, net, fresh, train, goals, test, args, rng)
        results[name] = res
        print(f"  {name:>9}: auc_far {res['auc_far']:.3f}, auc_goals {res['auc_goals']:.3f} ({res['adam_steps']} Adam steps, {res['train_s']:.0f} s)")

    @th.no_grad()
    def rnet_mastery(states: np.ndarray, raw_goals: np.ndarray) -> th.Tensor:
        e_s, e_g = rnet.encoder(to_x(states)), rnet.encoder(to_x(raw_goals))
        n, k = len(e_s), len(e_g)
        pairs = rnet.compare(e_s[:, None].expand(n, k, -1).reshape(n * k, -1), e_g[None].expand(n, k, -1).reshape(n * k, -1))
        return th.sigmoid(pairs).view(n, k)

    held_out = episodes[split:]
    for name, mastery_of in (("module", None), ("r-network", rnet_mastery)):
        signal = skill_signal.phase_signal(model, held_out, np.random.default_rng(args.seed), mastery_of)
        agg = signal["aggregates"]["max (the defaults)"]
        results[name]["phases"] = signal
        weakest = signal["least_mastered"]
        print(f"  r_gc by phase on the test episodes, h = max, {name}: "
              + ", ".join(f"{skill_signal.PHASES[ph]} {f['r_gc_mean']:.4f} ({f['steps']} steps, saturated {f['saturated']:.2f})" for ph, f in agg["phases"].items())
              + f"; least mastered {skill_signal.PHASES[weakest] if weakest is not None else 'none'}, ranked first "
              + (skill_signal.PHASES[agg["ranked_first"]] if agg["ranked_first"] is not None else "none"))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    return results


if __name__ == "__main__":
    main()
