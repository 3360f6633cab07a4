"""What a predictor update costs with each ``pair_labels``, and what scoring it on held-out pairs adds.

    python benchmarks/probes/predictor_update_cost.py <run>/checkpoints/ppo_gocu_seed0/model_200704.zip --env GoCu/DoorKey-8x8-v0 \
        --collect 20480 --repeats 5 --threads 1

Loads a PPO_GoCu checkpoint, trains it ``--collect`` steps more on 16 envs (a checkpoint taken just after a VAE
update has an empty trajectory store) and, from the state it then holds (trajectory store, goal buffer, predictor
and optimiser), runs the predictor update of each label kind in turn, alternating, ``--repeats`` times each, putting the state back
before every run. Prints the median seconds of the whole update (drawing the pairs, labelling, fitting, scoring),
of drawing the held-out pairs and of scoring them, and the AUCs each update reaches.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch as th

from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.reachability import QualityPairs

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--collect", type=int, default=20480, help="env steps to train before measuring")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    th.set_num_threads(args.threads)
    from stable_baselines3.common.env_util import make_vec_env

    model = PPO_GoCu.load(args.checkpoint, env=make_vec_env(args.env, n_envs=16, seed=1), device="cpu")
    model.learn(args.collect, reset_num_timesteps=False)
    module: GoalCuriosityModule = model.curiosity
    saved = copy.deepcopy(module.state_dict())
    times: dict[str, list[float]] = {"reachability": [], "eq16": []}
    draw, score, auc = [], [], {}
    for _ in range(args.repeats):
        for labels in times:
            module.load_state_dict(copy.deepcopy(saved))
            module.config = dataclasses.replace(module.config, pair_labels=labels)
            module.trainer.config = module.config
            t0 = time.perf_counter()
            stats = module.train_predictor()
            times[labels].append(time.perf_counter() - t0)
            auc[labels] = (stats["predictor_auc_far"], stats["predictor_auc_goals"], stats["predictor_adam_steps"])
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        pairs = QualityPairs.draw(module.trajectories, module.goal_buffer, module.config.max_distance, rng, module.predictor_holdout())
        draw.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        pairs.score(module.predictor.mastery)
        score.append(time.perf_counter() - t0)
    print(f"{args.checkpoint}: {module.n_recorded_steps} recorded steps, {len(module.trajectories)} states in the store, "
          f"{module.goal_buffer.size} goals; {args.repeats} alternating repeats, {args.threads} torch thread(s), "
          f"CPU {cpu_model()}")
    for labels, ts in times.items():
        far, goals, steps = auc[labels]
        print(f"pair_labels={labels}: update {statistics.median(ts):.3f} s (median), {steps:.0f} Adam steps, auc_far {far:.3f}, auc_goals {goals:.3f}")
    print(f"held-out pairs: drawn in {statistics.median(draw):.3f} s, scored in {statistics.median(score):.3f} s (medians)")


if __name__ == "__main__":
    main()
