"""rl-zoo3 integration: the ``ppo_gocu`` algorithm, its Optuna sampler and converter, and the launchers' help.

:func:`register_zoo` (idempotent) adds to rl-zoo3's tables, in this process:

* ``rl_zoo3.utils.ALGOS["ppo_gocu"] = PPO_GoCu``;
* ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER["ppo_gocu"]``: rl-zoo3's own PPO sampler for the PPO
  parameters, plus the GoCu ones (:func:`sample_ppo_gocu_params`);
* ``rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER["ppo_gocu"]``: turns the raw parameters of a stored trial
  back into model arguments (:func:`convert_ppo_gocu_params`, used by ``--trial-id``).

It also makes the zoo's ``ppo`` sampler keep the configured ``features_extractor_class`` (the zoo's sampler
replaces the whole ``policy_kwargs``, so the 32x32 entries of ``sb3_gocu/hyperparams/ppo.yml`` would fall back to
NatureCNN, which cannot take 32x32 images). Nothing else of the zoo is changed.

Sampled curiosity settings are merged into the configured ones: the zoo hands the sampler nothing but the
trial, and replaces the configured ``curiosity_kwargs`` / ``policy_kwargs`` by whatever the sampler returns,
so the sampler reads the configured values from the calling ``ExperimentManager`` (found on the call stack)
and returns configured + sampled. Settings that are not sampled (``image_channels`` for Atari, the MuJoCo
predictor size, a small ``pretrain_steps`` given on the command line) therefore survive tuning.

Config files: the YAML files live in ONE place, the package's ``sb3_gocu/hyperparams/`` directory
(``ppo_gocu.yml``, ``ppo.yml``, ``ppo_dropin.yml``, and for the paper's other learners ``a2c.yml``, ``a2c_dropin.yml``,
``dqn.yml``, ``dqn_dropin.yml``),
which ships in the wheel as package data, so the launchers find it however the package is installed; the
environment variable ``SB3_GOCU_HYPERPARAMS`` names another directory to use instead; see :func:`hyperparams_dir`
and :func:`default_conf_file`.

rl-zoo3 and Optuna come with the ``[zoo]`` extra (``pip install "sb3-gocu[zoo]"``); importing this module without
them raises a ``ModuleNotFoundError`` that says so.
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import sys
from pathlib import Path
from typing import Any

# headless MuJoCo rendering for GoCu/VisualReacher-v0 and GoCu/VisualPusher-v0; mujoco reads it on import,
# and nothing imported below imports mujoco
os.environ.setdefault("MUJOCO_GL", "egl")

from sb3_gocu._extras import missing_extra  # noqa: E402

try:
    import optuna
    import rl_zoo3  # noqa: F401
except ModuleNotFoundError as e:  # the [zoo] extra brings rl-zoo3 and optuna
    raise missing_extra(e, "sb3_gocu.zoo", "zoo") from e

import sb3_gocu  # noqa: E402, F401  (registers the GoCu/... env ids before the zoo checks --env)
from sb3_gocu.curiosity.goals import GOAL_STRATEGIES  # noqa: E402
from sb3_gocu.curiosity.reward import REVISIT_DECAYS  # noqa: E402
from sb3_gocu.ppo_gocu import PPO_GoCu  # noqa: E402

ALGO = "ppo_gocu"
#: environment variable naming a directory of ``{algo}.yml`` files that replaces the package's ``sb3_gocu/hyperparams/``
HYPERPARAMS_ENV_VAR = "SB3_GOCU_HYPERPARAMS"
#: algorithms for which the launchers pick our config file by default
DEFAULT_CONF_ALGOS = ("ppo_gocu", "ppo", "a2c", "dqn")

#: names of the GoCu parameters in a trial (each maps to a keyword of GoalCuriosityModule, or to
#: PPO_GoCu's ``intrinsic_coef``), each acting on the rewards under the defaults (tests/test_zoo.py). Symbols of the
#: paper: K, sigma, l, d_max.
GOCU_TRIAL_PARAMS = (
    "n_goals",  # K
    "intrinsic_coef",  # sigma (eq 10)
    "new_goals_per_episode",  # l
    "goal_strategy",
    "revisit_decay",  # what a revisit within an episode pays
    "max_distance",  # d_max: a far pair of the reachability labels is at least this many steps apart
)
#: GoCu parameters earlier versions sampled, which no longer are: lambda, a and b act only with ``pair_labels="eq16"``,
#: and delta (``reward_scale``) divides r_gc before eq 14 divides it by the std of its returns, which cancels it. A
#: stored trial that holds them still converts to the settings it ran with.
EARLIER_GOCU_TRIAL_PARAMS = ("reward_scale", "prior_weight", "label_threshold", "label_slope")
#: GoCu parameters sampled only when the configured policy takes images (a ``Cnn`` policy): the module refuses
#: ``vae_pixel_weighting > 0`` with vector observations
GOCU_IMAGE_TRIAL_PARAMS = ("vae_pixel_weighting",)
_ALL_GOCU_TRIAL_PARAMS = GOCU_TRIAL_PARAMS + GOCU_IMAGE_TRIAL_PARAMS + EARLIER_GOCU_TRIAL_PARAMS
#: policy_kwargs keys that no zoo sampler samples and that must survive tuning
_EXTRACTOR_KEYS = ("features_extractor_class", "features_extractor_kwargs", "normalize_images", "share_features_extractor")


# ---------------------------------------------------------------------------------------------- sampling
def sample_gocu_trial_params(trial: optuna.Trial, images: bool = False) -> dict[str, Any]:
    """Raw GoCu parameters of a trial (names of :data:`GOCU_TRIAL_PARAMS`, and with ``images`` those of
    :data:`GOCU_IMAGE_TRIAL_PARAMS`).

    Ranges around the paper's values (K=50, sigma=0.25, l=7, proportional) and the defaults (first-visit revisits,
    d_max=30). ``vae_pixel_weighting`` (not in the paper; the default 0.5 for images) spans its whole range [0, 1].

    :param trial: the Optuna trial
    :param images: whether the observations are images (only then is ``vae_pixel_weighting`` sampled)
    """
    params: dict[str, Any] = {
        "n_goals": trial.suggest_categorical("n_goals", [10, 25, 50, 100]),
        "intrinsic_coef": trial.suggest_float("intrinsic_coef", 0.01, 1.0, log=True),
        "new_goals_per_episode": trial.suggest_int("new_goals_per_episode", 1, 15),
        "goal_strategy": trial.suggest_categorical("goal_strategy", list(GOAL_STRATEGIES)),
        "revisit_decay": trial.suggest_categorical("revisit_decay", list(REVISIT_DECAYS)),
        "max_distance": trial.suggest_categorical("max_distance", [10, 20, 30, 50]),
    }
    if images:
        params["vae_pixel_weighting"] = trial.suggest_float("vae_pixel_weighting", 0.0, 1.0)
    return params


def convert_gocu_trial_params(params: dict[str, Any], base: dict[str, Any] | None = None) -> dict[str, Any]:
    """GoCu trial parameters -> ``intrinsic_coef`` and ``curiosity_kwargs`` (merged over ``base``'s).

    ``n_goals`` is capped at the configured ``goal_buffer_size``; a stored trial of an earlier version that sampled
    a (``label_threshold``) and no d_max gets d_max = ``ceil(2 a / beta)``, as it ran with, unless the config fixes it.
    """
    base = base or {}
    curiosity = dict(_as_dict(base.get("curiosity_kwargs")))
    sampled = {k: params[k] for k in _ALL_GOCU_TRIAL_PARAMS if k in params and k != "intrinsic_coef"}
    curiosity.update(sampled)
    if "goal_buffer_size" in curiosity and "n_goals" in curiosity:
        curiosity["n_goals"] = min(int(curiosity["n_goals"]), int(curiosity["goal_buffer_size"]))
    configured = _as_dict(base.get("curiosity_kwargs"))
    if "label_threshold" in sampled and "max_distance" not in sampled and "max_distance" not in configured:
        beta = float(curiosity.get("distance_weight", 1.0)) or 1.0
        curiosity["max_distance"] = max(1, math.ceil(2 * float(curiosity["label_threshold"]) / beta))
    out: dict[str, Any] = {"curiosity_kwargs": curiosity}
    if "intrinsic_coef" in params:
        out["intrinsic_coef"] = params["intrinsic_coef"]
    return out


def sample_ppo_gocu_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna sampler of ``ppo_gocu``: rl-zoo3's PPO sampler (``rl_zoo3.hyperparams_opt.sample_ppo_params``)
    for the PPO parameters, plus K, sigma, l, the goal strategy, ``revisit_decay``, d_max and, when
    the configured policy is a ``Cnn`` one, ``vae_pixel_weighting`` (:func:`sample_gocu_trial_params`).
    Configured ``curiosity_kwargs`` and ``policy_kwargs`` keys that are not sampled are kept (see the module
    docstring). The trial's user attribute ``worker`` is ``"host:pid"`` of the
    process that ran it."""
    from rl_zoo3.hyperparams_opt import sample_ppo_params

    base = _configured_hyperparams()
    # which process ran the trial: useful when several workers / machines share one study
    trial.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")
    hyperparams = sample_ppo_params(trial, n_actions, n_envs, additional_args)
    hyperparams["policy_kwargs"] = _merge_policy_kwargs(base.get("policy_kwargs"), hyperparams.get("policy_kwargs"), keys=None)
    hyperparams.update(convert_gocu_trial_params(sample_gocu_trial_params(trial, images=_takes_images(base)), base))
    return hyperparams


def convert_ppo_gocu_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """Raw parameters of a stored ``ppo_gocu`` trial -> model arguments (rl-zoo3's on-policy converter for
    the PPO part, :func:`convert_gocu_trial_params` for the GoCu part)."""
    from rl_zoo3.hyperparams_opt import convert_onpolicy_params

    base = _configured_hyperparams()
    ppo_params = {k: v for k, v in sampled_params.items() if k not in _ALL_GOCU_TRIAL_PARAMS}
    hyperparams = convert_onpolicy_params(ppo_params)
    hyperparams["policy_kwargs"] = _merge_policy_kwargs(base.get("policy_kwargs"), hyperparams.get("policy_kwargs"), keys=None)
    hyperparams.update(convert_gocu_trial_params(sampled_params, base))
    return hyperparams


def _takes_images(hyperparams: dict[str, Any]) -> bool:
    """Whether the configured policy is an image one (``"CnnPolicy"``, or a policy class named ``...Cnn...``)."""
    policy = hyperparams.get("policy")
    name = policy if isinstance(policy, str) else getattr(policy, "__name__", "")
    return "Cnn" in name


def _keep_extractor(sampler: Any) -> Any:
    """Wrap a zoo sampler so that the configured features extractor survives its ``policy_kwargs``."""

    def sampler_keeping_extractor(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
        hyperparams = sampler(trial, n_actions, n_envs, additional_args)
        if "policy_kwargs" in hyperparams:
            base = _configured_hyperparams().get("policy_kwargs")
            hyperparams["policy_kwargs"] = _merge_policy_kwargs(base, hyperparams["policy_kwargs"], keys=_EXTRACTOR_KEYS)
        return hyperparams

    sampler_keeping_extractor.__doc__ = sampler.__doc__
    sampler_keeping_extractor._sb3_gocu_wrapped = sampler  # type: ignore[attr-defined]
    return sampler_keeping_extractor


def _merge_policy_kwargs(base: Any, sampled: Any, keys: tuple[str, ...] | None) -> dict[str, Any]:
    """Sampled policy kwargs over the configured ones (all configured keys, or only ``keys``)."""
    base_dict = _as_dict(base)
    if keys is not None:
        base_dict = {k: v for k, v in base_dict.items() if k in keys}
    return {**base_dict, **_as_dict(sampled)}


def _as_dict(value: Any) -> dict[str, Any]:
    if value is None:
        return {}
    if isinstance(value, str):  # the zoo's "dict(...)" convention
        from rl_zoo3 import exp_manager

        value = eval(value, vars(exp_manager))  # same names as the zoo's own eval of policy_kwargs
    return dict(value)


def _configured_hyperparams() -> dict[str, Any]:
    """The hyperparameters configured for the running experiment (YAML entry + ``--hyperparams``), read from
    the ``ExperimentManager`` that called the sampler or converter; {} when there is none.

    In ``objective()`` they are ``self._hyperparams``; in ``read_hyperparameters()`` (``--trial-id``), the
    local ``hyperparams`` (the entry before the trial's values are applied).
    """
    try:
        from rl_zoo3.exp_manager import ExperimentManager
    except ImportError:  # pragma: no cover
        return {}
    frame = sys._getframe(1)
    while frame is not None:
        owner = frame.f_locals.get("self")
        if isinstance(owner, ExperimentManager):
            if owner._hyperparams:
                return owner._hyperparams
            local = frame.f_locals.get("hyperparams")
            if isinstance(local, dict):
                return local
        frame = frame.f_back  # type: ignore[assignment]
    return {}


# ---------------------------------------------------------------------------------------------- registration
def register_zoo(algorithm: type = PPO_GoCu) -> None:
    """Register ``ppo_gocu`` with rl-zoo3 (algorithm, sampler, converter) in this process. Idempotent.

    :param algorithm: the class registered (PPO_GoCu, or a subclass of it)"""
    import rl_zoo3
    import rl_zoo3.utils
    from rl_zoo3 import hyperparams_opt

    for algos in {id(rl_zoo3.utils.ALGOS): rl_zoo3.utils.ALGOS, id(rl_zoo3.ALGOS): rl_zoo3.ALGOS}.values():
        algos[ALGO] = algorithm
    hyperparams_opt.HYPERPARAMS_SAMPLER[ALGO] = sample_ppo_gocu_params
    hyperparams_opt.HYPERPARAMS_CONVERTER[ALGO] = convert_ppo_gocu_params
    ppo_sampler = hyperparams_opt.HYPERPARAMS_SAMPLER.get("ppo")
    if ppo_sampler is not None and not hasattr(ppo_sampler, "_sb3_gocu_wrapped"):
        hyperparams_opt.HYPERPARAMS_SAMPLER["ppo"] = _keep_extractor(ppo_sampler)


# ---------------------------------------------------------------------------------------------- config files
def hyperparams_dir() -> Path | None:
    """Where the launchers look for ``{algo}.yml``: ``$SB3_GOCU_HYPERPARAMS`` if set (and a directory), else the
    package's own ``hyperparams/`` (``sb3_gocu/hyperparams/``, installed with the package). None if neither exists."""
    env = os.environ.get(HYPERPARAMS_ENV_VAR)
    candidates = [Path(env).expanduser()] if env else []
    candidates.append(Path(__file__).resolve().parent / "hyperparams")
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    return None


def default_conf_file(algo: str, env_id: str | None) -> Path | None:
    """Our config file for ``algo``, or None to leave rl-zoo3's default.

    For ``ppo_gocu`` (the zoo has no file for it): ``ppo_gocu.yml`` of :func:`hyperparams_dir` whenever it exists.
    For ``ppo``, ``a2c`` and ``dqn``: its ``{algo}.yml`` only if it has an entry for ``env_id``, so ``--algo ppo`` on
    any other env keeps the zoo's own ``ppo.yml`` (with its ``atari`` fallback).
    """
    if algo not in DEFAULT_CONF_ALGOS:
        return None
    folder = hyperparams_dir()
    if folder is None:
        return None
    path = folder / f"{algo}.yml"
    if not path.is_file():
        return None
    if algo == ALGO:
        return path
    import yaml

    with open(path) as f:
        entries = yaml.safe_load(f) or {}
    return path if env_id in entries else None


def with_default_conf(argv: list[str]) -> list[str]:
    """``argv`` (without the program name) with ``--conf-file <our file>`` appended when the command line
    gives no ``-conf/--conf-file`` and :func:`default_conf_file` has one. Other flags are untouched."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--algo", default="ppo")
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("-conf", "--conf-file", default=None)
    known, _ = parser.parse_known_args(argv)
    if known.conf_file is not None:
        return list(argv)
    conf = default_conf_file(known.algo, known.env)
    if conf is None:
        return list(argv)
    return [*argv, "--conf-file", str(conf)]
