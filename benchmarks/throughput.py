"""Throughput of PPO_GoCu against plain PPO, measured in one run, and where PPO_GoCu's time goes.

    python benchmarks/throughput.py --env GoCu/DoorKey-8x8-v0 --timesteps 400000 --threads 1

Prints, for the same env, step count and PPO settings (the paper's: 16 envs, n_steps 128, batch 256, 4 epochs):
raw env steps/s with random actions (the ceiling), plain PPO steps/s, PPO_GoCu steps/s (the library's defaults:
K = 50, P_m = 20k, P_vae = 100k, the VAE's pretraining on 10k random-policy observations and every update
included), their ratio, and PPO_GoCu's time split into env stepping, policy forward and rollout
bookkeeping, PPO update, curiosity inference, VAE training (pretraining included) and predictor training.
With ``--zoo`` (the default for ``ALE/...`` ids) both agents are built as the zoo launcher builds them, from
``sb3_gocu/hyperparams/ppo.yml`` and ``ppo_gocu.yml`` (env wrappers, frame stack, n_envs, schedules; curiosity
settings given here are merged into the YAML's), e.g.

    python benchmarks/throughput.py --env ALE/MontezumaRevenge-v5 --timesteps 20000

The last line (``summary:``) is the figure the README quotes: PPO_GoCu's time per step over plain PPO's over the
whole run, and past ``--past`` steps (default 100,000: after the pretraining and the first VAE update's wait). With
``--gocu-model`` PPO_GoCu continues a trained agent (its goal buffer full, its policy moving: few states seen twice)::

    python benchmarks/throughput.py --env GoCu/DoorKey-8x8-v0 --timesteps 40000 --past 0 --gocu-model <run>/model_600000.zip

``--order`` picks which agent runs first. glibc's allocator makes the first training run of a process slower
(it keeps returning memory and faulting it in again until its dynamic thresholds have grown), so by default
(``--malloc fixed``) the thresholds are fixed at the start and the order no longer matters.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PAPER_PPO_KWARGS, GoCuVecEnvWrapper, PaperCNN, PPO_GoCu
from sb3_gocu.callbacks import GoCuCallback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from malloc_thresholds import fix_malloc_thresholds  # noqa: E402
from run_records import cpu_model, machine_line  # noqa: E402

PPO_SETTINGS: dict[str, Any] = dict(PAPER_PPO_KWARGS)  # both algorithms get them explicitly


class Timer:
    """Accumulates the wall time spent in wrapped methods."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}

    def wrap(self, obj: Any, name: str, label: str) -> None:
        original = getattr(obj, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.totals[label] = self.totals.get(label, 0.0) + time.perf_counter() - t0

        setattr(obj, name, timed)


#: the random-policy pretraining phase (env steps, VAE pretraining, first goals), over all runs
pretrain_timer = Timer()
pretrain_timer.wrap(GoCuCallback, "_pretrain", "pretrain")


class RolloutClock(BaseCallback):
    """Records (num_timesteps, wall time) at each rollout's start: the steps done and everything before them (PPO's
    and the curiosity's updates included)."""

    def __init__(self) -> None:
        super().__init__()
        self.marks: list[tuple[int, float]] = []

    def _on_rollout_start(self) -> None:
        self.marks.append((self.num_timesteps, time.perf_counter()))

    def _on_step(self) -> bool:
        return True


def innermost(venv: Any) -> Any:
    while hasattr(venv, "venv"):
        venv = venv.venv
    return venv


def zoo_manager(algo: str, env_id: str, seed: int, hyperparams: dict[str, Any] | None = None) -> Any:
    """rl-zoo3's ExperimentManager for ``algo`` on ``env_id`` with our YAML file (logs in a temporary folder)."""
    import atexit
    import shutil
    import tempfile

    from rl_zoo3.exp_manager import ExperimentManager

    from sb3_gocu.zoo import hyperparams_dir, register_zoo

    register_zoo()
    logs = tempfile.mkdtemp(prefix="throughput_")
    atexit.register(shutil.rmtree, logs, True)
    return ExperimentManager(
        argparse.Namespace(), algo, env_id, logs, eval_freq=-1, verbose=0, seed=seed,
        config=str(hyperparams_dir() / f"{algo}.yml"), hyperparams=hyperparams or {},
    )


def zoo_model(algo: str, env_id: str, seed: int, curiosity_overrides: dict[str, Any] | None = None) -> Any:
    """The model the zoo launcher builds for ``algo`` (``ppo`` or ``ppo_gocu``); curiosity overrides merged into the
    YAML's ``curiosity_kwargs``."""
    import contextlib
    import io

    hyperparams: dict[str, Any] = {}
    if curiosity_overrides:
        with contextlib.redirect_stdout(io.StringIO()):
            configured = zoo_manager(algo, env_id, seed).read_hyperparameters()[0].get("curiosity_kwargs", {})
        hyperparams["curiosity_kwargs"] = {**configured, **curiosity_overrides}
    with contextlib.redirect_stdout(io.StringIO()):
        model, _ = zoo_manager(algo, env_id, seed, hyperparams).setup_experiment()
    return model


def raw_env_rate(env_id: str, n_envs: int, steps: int, seed: int, zoo: bool = False) -> float:
    venv = zoo_model("ppo", env_id, seed).get_env() if zoo else make_vec_env(env_id, n_envs=n_envs, seed=seed)
    n_envs = venv.num_envs
    venv.reset()
    rng = np.random.default_rng(seed)
    n = venv.action_space.n
    t0 = time.perf_counter()
    for _ in range(steps // n_envs):
        venv.step(rng.integers(n, size=n_envs))
    return (steps // n_envs) * n_envs / (time.perf_counter() - t0)


def run(algo: str, env_id: str, timesteps: int, seed: int, curiosity_kwargs: dict[str, Any], gocu_model: str | None = None,
        overrides: dict[str, Any] | None = None, model_attrs: dict[str, Any] | None = None, zoo: bool = False,
        past: int = 0) -> dict[str, float]:
    """One arm: ``algo`` for ``timesteps`` steps; ``overrides``: curiosity settings that replace those of
    ``curiosity_kwargs`` (a fresh agent; refused with ``gocu_model``, whose settings were fixed at its construction);
    ``zoo``: the agent the zoo launcher builds from our YAML files; ``past``: also time the steps from the first
    rollout that starts at or after this step to the end (``past_steps_per_s``)."""
    overrides = overrides or {}
    timer = Timer()
    if zoo:
        if gocu_model is not None:
            raise ValueError("--gocu-model and --zoo do not go together")
        model = zoo_model(algo, env_id, seed, {**curiosity_kwargs, **overrides} if algo == "ppo_gocu" else None)
        venv = model.get_env()
    else:
        venv = make_vec_env(env_id, n_envs=16, seed=seed)
    timer.wrap(innermost(venv), "step_wait", "env")
    if zoo:
        pass
    elif algo == "ppo":
        model = PPO("CnnPolicy", venv, seed=seed, policy_kwargs=dict(features_extractor_class=PaperCNN), **PPO_SETTINGS)
    elif algo == "ppo_sum":  # the drop-in pipeline: plain PPO on the sum-mode wrapper, with GoCuCallback
        venv = GoCuVecEnvWrapper(venv, mode="sum", curiosity_kwargs={**curiosity_kwargs, **overrides})
        model = PPO("CnnPolicy", venv, seed=seed, policy_kwargs=dict(features_extractor_class=PaperCNN), **PPO_SETTINGS)
    elif gocu_model is not None:
        # a trained agent: its policy moves (fewer repeated states, more scoring), its goal buffer is full
        model = PPO_GoCu.load(gocu_model, env=venv, device="cpu")
        if overrides:
            raise ValueError("--gocu-model: a loaded model keeps its curiosity settings (they are fixed at construction)")
    else:
        curiosity_kwargs = {**curiosity_kwargs, **overrides}
        model = PPO_GoCu("CnnPolicy", venv, seed=seed, curiosity_kwargs=curiosity_kwargs, **PPO_SETTINGS)
    for name, value in (model_attrs or {}).items():  # PPO_GoCu attributes (e.g. n_epochs)
        if not hasattr(model, name):
            raise ValueError(f"--also-model-kwargs: PPO_GoCu has no attribute {name!r}")
        setattr(model, name, value)
    timer.wrap(model, "train", "ppo_update")
    mod = model.curiosity if algo == "ppo_gocu" else venv.module if algo == "ppo_sum" else None
    if mod is not None:
        # wall time of the curiosity updates, run at each rollout's end
        timer.wrap(mod, "maybe_train", "curiosity_updates")
    timer.wrap(model, "collect_rollouts", "rollout")
    pretrain_before = pretrain_timer.totals.get("pretrain", 0.0)
    clock = RolloutClock()
    t0 = time.perf_counter()
    model.learn(timesteps, callback=[clock, GoCuCallback()] if algo == "ppo_sum" else clock)
    t_end = time.perf_counter()
    total = t_end - t0
    out = {"total_s": total, "steps": float(model.num_timesteps), "steps_per_s": model.num_timesteps / total, "n_envs": float(venv.num_envs)}
    after = [(s, t) for s, t in clock.marks if s >= past]
    if past > 0 and after and after[0][0] < model.num_timesteps:
        out["past_from_step"] = float(after[0][0])
        out["past_steps_per_s"] = (model.num_timesteps - after[0][0]) / (t_end - after[0][1])
    out.update({f"{k}_s": v for k, v in timer.totals.items()})
    if mod is not None:
        out["curiosity_inference_s"] = mod.time_inference
        out["vae_training_s"] = mod.time_vae
        out["predictor_training_s"] = mod.time_predictor
        out["cache_hit_rate"] = mod.scorer.cache_hits / max(1, mod.scorer.cache_lookups)
        out["pretrain_s"] = pretrain_timer.totals.get("pretrain", 0.0) - pretrain_before
    out["policy_and_bookkeeping_s"] = (
        out["rollout_s"] - out["env_s"] - out.get("curiosity_inference_s", 0.0) - out.get("curiosity_updates_s", 0.0)
    )
    out["other_s"] = total - out["rollout_s"] - out["ppo_update_s"] - out.get("pretrain_s", 0.0)
    out["weights_sha256"] = weights_hash(model)
    return out


def summary_line(args: argparse.Namespace, ppo: dict[str, float], gocu: dict[str, float]) -> str:
    """The figure the README quotes: PPO_GoCu's time per step over plain PPO's, over the whole run and past ``--past``."""
    what = (f"PPO_GoCu a trained agent ({os.path.basename(args.gocu_model)}) continued, plain PPO from scratch" if args.gocu_model
            else "from scratch, the pretraining and every update included")
    line = f"summary: a PPO_GoCu step costs {ppo['steps_per_s'] / gocu['steps_per_s']:.2f}x plain PPO's time ({args.timesteps:,} steps, {what}"
    if "past_steps_per_s" in ppo and "past_steps_per_s" in gocu:
        line += f"; {ppo['past_steps_per_s'] / gocu['past_steps_per_s']:.2f}x past step {int(gocu['past_from_step']):,}"
    return line + f"); {args.env}, {gocu['n_envs']:.0f} envs, {args.threads} torch thread(s), seed {args.seed}, CPU {cpu_model()}"


def weights_hash(model: Any) -> str:
    """First 16 hex digits of the SHA-256 of the policy's weights (and the VAE's and the predictor's): arms that
    must train the same networks (options that change only the wall time) show the same digits."""
    nets = [model.policy] + ([model.curiosity.vae, model.curiosity.predictor] if getattr(model, "curiosity", None) is not None else [])
    h = hashlib.sha256()
    for net in nets:
        for value in net.state_dict().values():
            h.update(value.detach().cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--timesteps", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (both agents; every recorded run gives it)")
    parser.add_argument("--past", type=int, default=100_000,
                        help="also give the time per step past this step (from the first rollout that starts there; 0: not)")
    parser.add_argument("--order", choices=["ppo-first", "gocu-first"], default="ppo-first")
    parser.add_argument("--zoo", action=argparse.BooleanOptionalAction, default=None,
                        help="build the agents from the zoo's YAML files (default: for ALE/... ids only)")
    parser.add_argument("--malloc", choices=["fixed", "default"], default="fixed",
                        help="fixed: glibc trim/mmap thresholds set once for the process, so no run pays for being first; "
                        "default: glibc's own dynamic thresholds")
    parser.add_argument("--curiosity-kwargs", default="{}", help="JSON dict of GoalCuriosityModule keywords")
    parser.add_argument("--model-kwargs", default="{}", help="JSON dict of PPO_GoCu attributes set in every PPO_GoCu arm")
    parser.add_argument("--reverse", action="store_true", help="run the arms in reverse order (the --also-* arms first, plain PPO last)")
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    parser.add_argument("--gocu-model", default=None, help="PPO_GoCu continues this trained model instead of starting afresh "
                        "(with its own curiosity settings: curiosity settings of --also-* arms are refused; "
                        "no pretraining); plain PPO still starts afresh")
    parser.add_argument("--also-model-kwargs", action="append", default=None, metavar="JSON",
                        help="also run PPO_GoCu with these PPO_GoCu attributes set, e.g. '{\"n_epochs\": 2}' "
                        "(another run each time the option is given)")
    parser.add_argument("--also-curiosity-kwargs", action="append", default=None, metavar="JSON",
                        help="also run PPO_GoCu with these GoalCuriosityModule keywords on top of --curiosity-kwargs, "
                        "e.g. '{\"vae_update_epochs\": 20}' (another run each time the option is given)")
    parser.add_argument("--also-sum", action="store_true",
                        help="also run the drop-in pipeline: plain PPO on GoCuVecEnvWrapper(mode='sum') with GoCuCallback "
                        "(one value head; --curiosity-kwargs apply)")
    parser.add_argument("--also-arm", action="append", default=None, metavar="JSON",
                        help="also run PPO_GoCu with both kinds of setting, e.g. '{\"curiosity\": {\"scoring_dtype\": \"bfloat16\"}, "
                        "\"model\": {\"n_epochs\": 2}}' (another run each time the option is given)")
    args = parser.parse_args(argv)
    arms = [json.loads(a) for a in args.also_arm or []]
    for arm in arms:
        if not isinstance(arm, dict) or not set(arm) <= {"curiosity", "model"}:
            parser.error(f"--also-arm must be a JSON object with the keys 'curiosity' and/or 'model', got {arm!r}")
    th.set_num_threads(args.threads)
    zoo = args.env.startswith("ALE/") if args.zoo is None else args.zoo
    curiosity_kwargs = json.loads(args.curiosity_kwargs)
    malloc = "glibc default (dynamic thresholds)"
    if args.malloc == "fixed":
        malloc = "glibc mallopt trim 1 GiB, mmap 32 MiB" if fix_malloc_thresholds() else "could not fix the glibc thresholds: default"

    command = [os.path.basename(sys.executable)] + (sys.argv if argv is None else [__file__, *argv])
    print(f"command: {' '.join(command)}")
    print(f"machine: {machine_line(args.threads)}; seed {args.seed}; order {args.order}; malloc: {malloc}")
    raw = raw_env_rate(args.env, 16, min(args.timesteps, 32_000), args.seed, zoo)
    results = {}
    labels_extra: dict[str, str] = {}
    base_model = json.loads(args.model_kwargs)
    thunks = []
    order = ["ppo", "ppo_gocu"] if args.order == "ppo-first" else ["ppo_gocu", "ppo"]
    for algo in order:
        thunks.append((algo, lambda algo=algo: run(algo, args.env, args.timesteps, args.seed, curiosity_kwargs, args.gocu_model,
                                                   model_attrs=base_model if algo == "ppo_gocu" else None, zoo=zoo,
                                                   past=args.past)))
    for i, extra in enumerate(args.also_model_kwargs or []):
        thunks.append((f"ppo_gocu_model_{i}", lambda extra=extra: run("ppo_gocu", args.env, args.timesteps, args.seed, curiosity_kwargs,
                                                                       args.gocu_model, model_attrs={**base_model, **json.loads(extra)}, zoo=zoo,
                                                                       past=args.past)))
        labels_extra[f"ppo_gocu_model_{i}"] = extra
    for i, extra in enumerate(args.also_curiosity_kwargs or []):
        thunks.append((f"ppo_gocu_curiosity_{i}", lambda extra=extra: run("ppo_gocu", args.env, args.timesteps, args.seed, curiosity_kwargs,
                                                                           args.gocu_model, overrides=json.loads(extra), model_attrs=base_model, zoo=zoo,
                                                                           past=args.past)))
        labels_extra[f"ppo_gocu_curiosity_{i}"] = extra
    for i, (text, arm) in enumerate(zip(args.also_arm or [], arms)):
        thunks.append((f"ppo_gocu_arm_{i}", lambda arm=arm: run("ppo_gocu", args.env, args.timesteps, args.seed, curiosity_kwargs, args.gocu_model,
                                                                 overrides=arm.get("curiosity"), model_attrs={**base_model, **arm.get("model", {})}, zoo=zoo,
                                                                 past=args.past)))
        labels_extra[f"ppo_gocu_arm_{i}"] = text
    if args.also_sum:
        if zoo:
            parser.error("--also-sum builds the agents itself: not with --zoo")
        thunks.append(("ppo_sum", lambda: run("ppo_sum", args.env, args.timesteps, args.seed, curiosity_kwargs, past=args.past)))
        labels_extra["ppo_sum"] = "PPO + wrapper (sum)"
    for name, thunk in (reversed(thunks) if args.reverse else thunks):
        results[name] = thunk()
        print(f"{name}: {results[name]['steps_per_s']:.0f} steps/s", flush=True)
    ppo, gocu = results["ppo"], results["ppo_gocu"]
    print(f"\n{args.env}, {args.timesteps} steps, {results['ppo']['n_envs']:.0f} envs" + (" (the zoo's YAML settings)" if zoo else ""))
    print(f"raw env (random actions)      {raw:8.0f} steps/s")
    print(f"plain PPO                     {ppo['steps_per_s']:8.0f} steps/s")
    print(f"PPO_GoCu                      {gocu['steps_per_s']:8.0f} steps/s")
    print(f"time per step, GoCu / PPO     {ppo['steps_per_s'] / gocu['steps_per_s']:8.2f}x")
    if "past_steps_per_s" in ppo and "past_steps_per_s" in gocu:
        print(f"past step {int(gocu['past_from_step']):,}: plain PPO {ppo['past_steps_per_s']:.0f} steps/s, PPO_GoCu "
              f"{gocu['past_steps_per_s']:.0f} steps/s, {ppo['past_steps_per_s'] / gocu['past_steps_per_s']:.2f}x")
    extras = list(labels_extra)
    labels = labels_extra
    for k in extras:
        r = results[k]
        print(f"PPO_GoCu, {labels[k]:20s}{r['steps_per_s']:8.0f} steps/s  ({ppo['steps_per_s'] / r['steps_per_s']:.2f}x PPO's time per step)")
    if args.gocu_model:
        print(f"(PPO_GoCu continued {args.gocu_model})")
    print("\nwhere the time goes (s)          PPO   PPO_GoCu" + "".join(f"  {labels[k]:>20s}" for k in extras))
    for key in ("env_s", "policy_and_bookkeeping_s", "ppo_update_s", "curiosity_inference_s", "curiosity_updates_s", "vae_training_s", "predictor_training_s", "pretrain_s",
                "other_s", "total_s"):
        extra = "".join(f"  {results[k].get(key, 0.0):20.1f}" for k in extras)
        print(f"  {key:28s} {ppo.get(key, 0.0):7.1f}  {gocu.get(key, 0.0):9.1f}{extra}")
    print(f"  {'weights_sha256':28s} {ppo['weights_sha256']:>7s}  {gocu['weights_sha256']:>9s}" + "".join(f"  {results[k]['weights_sha256']:>20s}" for k in extras))
    print("  (curiosity_inference_s: the rollout's time in the module: hashing, memos, embedding and scoring the new states)")
    print("  (other_s: the rest of learn, outside the rollouts, PPO's updates and pretraining)")
    print("  (curiosity_updates_s: the VAE/predictor updates at the rollouts' ends; vae/predictor_training_s: the "
          "updates' own time, pretraining's VAE epochs included)")
    print(f"  (pretrain_s is the whole random-policy pretraining phase (measured, not a remainder); "
          f"reward cache hit rate {gocu['cache_hit_rate']:.2f})")
    print("\n" + summary_line(args, ppo, gocu))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": command[1:], "order": args.order, "malloc": malloc, "raw_env_steps_per_s": raw, **results}, f, indent=2)
    return results


if __name__ == "__main__":
    main()
