"""Where each curiosity update sits against PPO's update and the next rollout, in one PPO_GoCu run.

    python benchmarks/update_timeline.py --env GoCu/DoorKey-8x8-v0 --timesteps 210000 --threads 1

With ``overlap_ppo_update`` (the default) an update due at a rollout's end runs in a thread beside PPO's update;
with ``queue_during_update`` the next rollout's env steps go on beside it, their scoring queued; the rollout's end
waits for whatever is left. This script records, for every VAE and predictor fit (the pretraining's included),
when it started and ended, and, from the same start, when PPO's update ended, when the next rollout's env stepping
reached its end (the first wait for the update), when the update was taken into use and when the next rollout
ended. So it says how much of an update the overlap hides and what the rollout still waits for.

Paper PPO settings (16 envs, n_steps 128, batch 256, 4 epochs) and the module's defaults, plus
``--curiosity-kwargs``. Prints one row per fit and a summary; ``--json`` writes the events.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PAPER_PPO_KWARGS, PPO_GoCu
from sb3_gocu.curiosity.module import GoalCuriosityModule

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from malloc_thresholds import fix_malloc_thresholds  # noqa: E402


class Events:
    """(label, start, end) of every call of the wrapped methods, in seconds from the recorder's creation."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.events: list[tuple[str, float, float]] = []

    def wrap(self, owner: Any, name: str, label: str) -> None:
        original = getattr(owner, name)

        def recorded(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter() - self.t0
            try:
                return original(*args, **kwargs)
            finally:
                self.events.append((label, start, time.perf_counter() - self.t0))

        setattr(owner, name, recorded)


def first_after(events: list[tuple[str, float, float]], label: str, t: float, key: int = 2) -> float | None:
    """The earliest start (key 1) or end (key 2) of a ``label`` event that ends after ``t``."""
    times = [e[key] for e in events if e[0] == label and e[2] > t]
    return min(times) if times else None


@dataclasses.dataclass
class FitRow:
    """One VAE or predictor fit and what followed it (times in s from the recorder's start; None: does not apply,
    as for the pretraining's fit, which runs in place before the first rollout)."""

    label: str  #: "vae" or "predictor"
    start: float
    end: float
    ppo_end: float | None = None  #: end of the PPO update the fit's job overlaps
    used: float | None = None  #: when the job's networks were taken into use
    rollout_end: float | None = None  #: end of the rollout after that PPO update
    waited: float | None = None  #: how much longer than the median rollout that rollout took (the job's last fit only)


def fit_rows(events: list[tuple[str, float, float]]) -> tuple[list[FitRow], dict[str, float], float]:
    """One :class:`FitRow` per fit, in order of start.

    A job is the fits due at one rollout's end (a predictor fit, a VAE fit, or both, run back to back): a fit
    starts a new job unless it follows the previous fit with no ``taken_into_use`` ending between them. The job's
    PPO update is the first to end after the job's start; the rollout's extra time goes to the job's last fit. The
    pretraining's fit (before the first rollout) has only its times.

    :return: the rows, the extra time by kind of fit, the median rollout's duration
    """
    rollouts = [e for e in events if e[0] == "rollout"]
    plain = float(np.median([e[2] - e[1] for e in rollouts]))
    first_rollout = min(e[1] for e in rollouts)
    used_ends = [e[2] for e in events if e[0] == "taken_into_use"]
    rows: list[FitRow] = []
    jobs: list[list[FitRow]] = []
    for label, start, end in sorted((e for e in events if e[0] in ("predictor", "vae")), key=lambda e: e[1]):
        if start < first_rollout:  # the pretraining's fit, in place before the first rollout
            rows.append(FitRow(label, start, end))
            continue
        same_job = bool(jobs) and not any(jobs[-1][-1].end < t < start for t in used_ends)
        job_start = jobs[-1][0].start if same_job else start
        ppo_end = first_after(events, "ppo_update", job_start)
        roll_end = None if ppo_end is None else first_after(events, "rollout", ppo_end)
        row = FitRow(label, start, end, ppo_end=ppo_end, rollout_end=roll_end)
        rows.append(row)
        if same_job:
            jobs[-1].append(row)
        else:
            jobs.append([row])
    total_waited = {"predictor": 0.0, "vae": 0.0}
    for job in jobs:
        used = first_after(events, "taken_into_use", max(r.end for r in job))
        for r in job:
            r.used = used
        last = max(job, key=lambda r: r.end)
        if last.ppo_end is not None and last.rollout_end is not None:
            last.waited = (last.rollout_end - last.ppo_end) - plain
            total_waited[last.label] += last.waited
    return rows, total_waited, plain


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--timesteps", type=int, default=210_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    parser.add_argument("--curiosity-kwargs", default="{}", help="JSON dict of GoalCuriosityModule keywords")
    parser.add_argument("--json", default=None, help="also write the events to this JSON file")
    args = parser.parse_args()
    curiosity_kwargs = json.loads(args.curiosity_kwargs)
    if not isinstance(curiosity_kwargs, dict):
        raise SystemExit(f"--curiosity-kwargs must be a JSON object, got {args.curiosity_kwargs!r}")
    if curiosity_kwargs.get("predictor_lead", 0):
        # a lead fit starts rollouts before it is due and pauses while they run: its wall time and its wait would
        # be given to the wrong rollout by the rows below
        raise SystemExit(f"--curiosity-kwargs: predictor_lead must be 0 for this timeline, got {curiosity_kwargs['predictor_lead']!r}")
    fix_malloc_thresholds()
    th.set_num_threads(args.threads)
    print("command: python " + " ".join(sys.argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, threads {args.threads}, seed {args.seed}")

    rec = Events()
    rec.wrap(GoalCuriosityModule, "_fit_predictor", "predictor")
    rec.wrap(GoalCuriosityModule, "_fit_vae_job", "vae")
    rec.wrap(GoalCuriosityModule, "finish_background_update", "taken_into_use")
    rec.wrap(PPO_GoCu, "train", "ppo_update")
    rec.wrap(PPO_GoCu, "collect_rollouts", "rollout")
    env = make_vec_env(args.env, n_envs=16, seed=args.seed)
    model = PPO_GoCu("CnnPolicy", env, seed=args.seed, curiosity_kwargs=curiosity_kwargs, **PAPER_PPO_KWARGS)
    t_learn = time.perf_counter()
    model.learn(args.timesteps)
    learn_s = time.perf_counter() - t_learn
    events = rec.events

    print(f"\n{args.env}, {args.timesteps} steps, 16 envs, curiosity_kwargs {curiosity_kwargs}; learn {learn_s:.1f} s")
    print("times in s from the fit's start; 'waited': how much longer than the median rollout the rollout after PPO's update took "
          "(a job's predictor and VAE fits share one: it is counted on the job's last fit)")
    rows, total_waited, plain = fit_rows(events)
    print(f"median rollout {plain:.2f} s, median PPO update {np.median([e[2] - e[1] for e in events if e[0] == 'ppo_update']):.2f} s")
    print(f"{'fit':<10} {'start':>7} {'fit':>6} {'PPO update ends':>16} {'taken into use':>15} {'next rollout ends':>18} {'waited':>7}")
    for r in rows:
        rel = lambda t: "" if t is None else f"{t - r.start:.2f}"  # noqa: E731
        print(f"{r.label:<10} {r.start:7.1f} {r.end - r.start:6.2f} {rel(r.ppo_end):>16} {rel(r.used):>15} "
              f"{rel(r.rollout_end):>18} {'' if r.waited is None else f'{r.waited:.2f}':>7}")
    fits = {k: [e[2] - e[1] for e in events if e[0] == k] for k in ("predictor", "vae")}
    print(f"\npredictor fits: {len(fits['predictor'])}, {sum(fits['predictor']):.1f} s in all; the rollouts after them ran "
          f"{total_waited['predictor']:.1f} s over a median rollout")
    print(f"VAE fits (pretraining's first): {len(fits['vae'])}, {sum(fits['vae']):.1f} s in all; the rollouts after them ran "
          f"{total_waited['vae']:.1f} s over a median rollout (the pretraining's fit has none)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": sys.argv, "learn_s": learn_s, "events": events}, f)


if __name__ == "__main__":
    main()
