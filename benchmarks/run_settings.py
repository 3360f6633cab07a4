"""The settings of a ``sample_efficiency.py`` run: the model's keywords (the paper's PPO, or the zoo launcher's files),
the curiosity's, and the configuration a checkpoint must agree with to be resumed."""

from __future__ import annotations

import argparse
import json
import pathlib
from typing import Any

import yaml

import sb3_gocu
from sb3_gocu import PAPER_N_ENVS, PAPER_PPO_KWARGS

#: a plain SB3 algorithm on ``GoCuVecEnvWrapper(mode="sum")`` with ``GoCuCallback``
SUM_ALGOS = ("ppo_sum", "a2c_sum", "dqn_sum")
CURIOUS = ("ppo_gocu", *SUM_ALGOS)
#: where a2c / dqn read their settings: the zoo launcher's files
HYPERPARAMS = pathlib.Path(sb3_gocu.__file__).resolve().parent / "hyperparams"
#: keys of a zoo entry that are the launcher's, not the model's
ZOO_KEYS = ("n_envs", "n_timesteps", "policy", "vec_env_wrapper", "callback", "env_wrapper", "frame_stack", "normalize")
PPO_SETTINGS: dict[str, Any] = dict(PAPER_PPO_KWARGS)  # both algorithms get them explicitly
N_ENVS = PAPER_N_ENVS


def ppo_settings(args: argparse.Namespace) -> dict[str, Any]:
    return {**PPO_SETTINGS, "n_steps": args.n_steps, "batch_size": args.batch_size}


def zoo_entry(family: str, env: str) -> dict[str, Any]:
    """``env``'s entry in ``sb3_gocu/hyperparams/<family>.yml`` (the zoo launcher's file), as written.
    :param family: ``ppo``, ``ppo_gocu``, ``a2c`` or ``dqn``"""
    entries = yaml.safe_load((HYPERPARAMS / f"{family}.yml").read_text())
    if env not in entries:
        raise SystemExit(f"{family}: sb3_gocu/hyperparams/{family}.yml has no entry for {env} (it has {sorted(entries)})")
    return entries[env]


def zoo_settings(family: str, env: str) -> dict[str, Any]:
    """The model keywords of ``env``'s entry in ``sb3_gocu/hyperparams/<family>.yml``: the entry less the launcher's
    own keys, ``policy_kwargs`` left a string. :param family: ``a2c`` or ``dqn``"""
    return {k: v for k, v in zoo_entry(family, env).items() if k not in ZOO_KEYS}


def zoo_overrides(args: argparse.Namespace, algo: str, entry: dict[str, Any]) -> dict[str, Any]:
    """With --zoo: the zoo entry's settings the command changes (``--model-kwargs``; ``--curiosity-kwargs``,
    ``--goal-strategy``, ``--n-goals`` merged into a ppo_gocu entry's ``curiosity_kwargs``)."""
    out = dict(json.loads(args.model_kwargs))
    changed = curiosity_kwargs(args)
    if algo == "ppo_gocu" and changed:
        out["curiosity_kwargs"] = {**entry.get("curiosity_kwargs", {}), **changed}
    return out


def model_settings(args: argparse.Namespace, algo: str) -> dict[str, Any]:
    """The model keywords of a run: PPO's for the ppo algos, the zoo file's (and ``--model-kwargs``) for a2c / dqn."""
    family = algo.split("_")[0]
    if family == "ppo":
        return ppo_settings(args)
    return {**zoo_settings(family, args.env), **json.loads(args.model_kwargs)}


def curiosity_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    kw = dict(json.loads(args.curiosity_kwargs))
    if args.goal_strategy is not None:
        kw["goal_strategy"] = args.goal_strategy
    if args.n_goals is not None:
        kw["n_goals"] = args.n_goals
    return kw


def run_config(args: argparse.Namespace, algo: str, seed: int) -> dict[str, Any]:
    """What a checkpoint must agree with to be resumed (the step budget is not part of it: it can grow)."""
    if args.zoo:
        entry = zoo_entry(algo, args.env)
        entry = {**entry, **zoo_overrides(args, algo, entry)}
        entry.pop("n_timesteps", None)  # the budget is --timesteps
        return json.loads(json.dumps({"algo": algo, "seed": seed, "env": args.env, "zoo": entry, "window": args.window}))
    key = "ppo" if algo.startswith("ppo") else "model"
    cfg: dict[str, Any] = {"algo": algo, "seed": seed, "env": args.env, "n_envs": args.n_envs, key: model_settings(args, algo), "window": args.window}
    if algo in CURIOUS:
        cfg["curiosity_kwargs"] = curiosity_kwargs(args)
        cfg["intrinsic_coef"] = args.intrinsic_coef
        if args.constant_curiosity:
            cfg["constant_curiosity"] = True
        if algo in SUM_ALGOS and args.uncentred:
            cfg["uncentred"] = True
    return json.loads(json.dumps(cfg))
