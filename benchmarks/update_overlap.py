"""A curiosity update beside PPO's update: fitted in a thread of the training process, or in the worker process.

    python benchmarks/update_overlap.py --env GoCu/DoorKey-8x8-v0 --timesteps 40960 --repeats 6

With ``overlap_ppo_update`` (the default) an update due at a rollout end runs while PPO updates the policy, and
the next rollout waits for whatever is left of it. This script trains PPO_GoCu for ``--timesteps`` steps, prepares
one predictor update and one VAE update from its state (the same jobs ``maybe_train`` would start), and times
"start the fit; ``model.train()``; take the fit's networks" ``--repeats`` times per arm, the fit in a thread
(``scoring_process=False``) or in the worker process (``scoring_process=True``), alternating the order and
restoring the policy, the networks, their optimisers and the generator before every call, so both arms run the
same work on the same machine state in one process. 1 torch thread. Prints each arm's median critical path
(what the next rollout would wait for), PPO's ``train()`` time and the fit's own time, and checks that both arms
end with the same networks, bit for bit.
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import sys
import threading
import time
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PPO_GoCu

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from throughput import PPO_SETTINGS, fix_malloc_thresholds  # noqa: E402


def fit_beside_train(model: PPO_GoCu, name: str, job: dict[str, Any], where: str) -> dict[str, float]:
    """One "fit beside PPO's update" as ``maybe_train`` and ``finish_background_update`` run it; wall seconds."""
    module = model.curiosity
    jobs = [(name, job)]
    previous = sys.getswitchinterval()
    sys.setswitchinterval(model.switch_interval)  # as PPO_GoCu.train does while an update runs beside it
    t0 = time.perf_counter()
    if where == "thread":
        fits: list = []
        worker = threading.Thread(target=lambda: fits.append(module._fit_predictor(**job) if name == "predictor" else module._fit_vae(**job)))
        worker.start()
    else:
        future = module.start_scoring_process().submit_fit(module._fit_shell(jobs), module._torch_gen.get_state(), jobs)
    t_train = time.perf_counter()
    model.train()
    t_train = time.perf_counter() - t_train
    t_wait = time.perf_counter()
    if where == "thread":
        worker.join()
        fit = fits[0]
    else:
        (_, fit), = future.result()[0]
        for key, state in future.result()[1].items():
            getattr(module, key).load_state_dict(state)
        module._torch_gen.set_state(future.result()[2])
    t_wait = time.perf_counter() - t_wait
    sys.setswitchinterval(previous)
    return {"critical_path_s": time.perf_counter() - t0, "ppo_train_s": t_train, "wait_after_train_s": t_wait, "fit_s": fit["time"]}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    p.add_argument("--timesteps", type=int, default=40960, help="training steps before the timing")
    p.add_argument("--repeats", type=int, default=6, help="timed calls per arm and update")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.timesteps < 2048 or args.repeats < 1:
        p.error(f"--timesteps must be >= 2048 (one rollout) and --repeats >= 1, got {args.timesteps} and {args.repeats}")
    th.set_num_threads(1)
    fix_malloc_thresholds()
    print("command: python benchmarks/update_overlap.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, torch threads 1, seed {args.seed}, "
          "glibc thresholds fixed as in throughput.py")
    model = PPO_GoCu("CnnPolicy", make_vec_env(args.env, n_envs=16, seed=args.seed), seed=args.seed, **PPO_SETTINGS)
    model.learn(args.timesteps)
    module = model.curiosity
    module.start_scoring_process()
    jobs = {"predictor": module._prepare_predictor(), "vae": module._prepare_vae(None)}
    nets = {"predictor": ("predictor", "predictor_optimizer"), "vae": ("vae", "vae_optimizer")}
    saved = {
        "policy": copy.deepcopy(model.policy.state_dict()), "policy_optimizer": copy.deepcopy(model.policy.optimizer.state_dict()),
        "torch_rng": module._torch_gen.get_state(),
        **{k: copy.deepcopy(getattr(module, k).state_dict()) for pair in nets.values() for k in pair},
    }
    results: dict[str, dict[str, list[dict[str, float]]]] = {}
    ends: dict[tuple[str, str], dict[str, th.Tensor]] = {}
    for name, job in jobs.items():
        results[name] = {"thread": [], "process": []}
        for rep in range(args.repeats):
            for where in ("thread", "process") if rep % 2 == 0 else ("process", "thread"):
                model.policy.load_state_dict(saved["policy"])
                model.policy.optimizer.load_state_dict(saved["policy_optimizer"])
                module._torch_gen.set_state(saved["torch_rng"])
                for k in (*nets["predictor"], *nets["vae"]):
                    getattr(module, k).load_state_dict(saved[k])
                module.vae.eval(), module.predictor.eval()
                results[name][where].append(fit_beside_train(model, name, job, where))
                ends[(name, where)] = copy.deepcopy(getattr(module, nets[name][0]).state_dict())
        same = all(th.equal(ends[(name, "thread")][k], ends[(name, "process")][k]) for k in ends[(name, "thread")])
        print(f"\n{name} update beside PPO's update, {args.repeats} calls per arm (medians, s); same networks in both arms: {same}")
        print(f"  {'':8s} {'critical path':>14s} {'PPO train()':>12s} {'wait after it':>14s} {'fit':>8s}")
        for where, runs in results[name].items():
            med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            print(f"  {where:8s} {med['critical_path_s']:14.3f} {med['ppo_train_s']:12.3f} {med['wait_after_train_s']:14.3f} {med['fit_s']:8.3f}")
        if not same:
            raise SystemExit(f"the {name} fit gave different networks in a thread and in the worker process")
    return results


if __name__ == "__main__":
    main()
