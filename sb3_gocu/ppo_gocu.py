"""PPO_GoCu: PPO learning from two reward streams, extrinsic and goal-based curiosity (paper Alg. 1).

Read top to bottom, one iteration is:

1. rollout (:meth:`PPO_GoCu.collect_rollouts`): the env stack carries a GoCu wrapper in ``"separate"``
   mode, so the reward is extrinsic and r_gc arrives in ``infos["gocu_reward"]``; the critic has two heads
   and both streams are stored; on a time-limit truncation the extrinsic head bootstraps from the terminal
   state, and the curiosity head too when its stream is episodic (``intrinsic_episodic=True``; by default it
   runs across episode ends) (Alg. 1 lines 10-15);
2. GAE per stream, A = A_e + sigma * A_gc (:class:`~sb3_gocu.buffers.GoCuRolloutBuffer`, eq 10, lines 16-18);
3. SB3's PPO update, unchanged, on A and on both value targets (line 19);
4. the curiosity module learns at the rollout end: new goals, VAE every P_vae, predictor every P_m
   (:class:`~sb3_gocu.GoCuCallback`, added to ``learn()`` automatically, lines 20-21).

The module is ``model.curiosity``; ``save()`` stores its whole state beside the policy and ``load()``
restores it, so training continues where it stopped.
"""

from __future__ import annotations

import inspect
import io
import json
import pathlib
import pickle
import warnings
import zipfile
from types import MappingProxyType
from typing import Any, ClassVar, Iterable, Mapping, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv

from sb3_gocu.buffers import GoCuDictRolloutBuffer, GoCuRolloutBuffer
from sb3_gocu.callbacks import GoCuCallback
from sb3_gocu.checkpoints import GlobalRNGState, check_model_file, read_env_state, save_model, without_members
from sb3_gocu.curiosity import CuriosityConfig, GoalCuriosityModule
from sb3_gocu.curiosity.checks import DEFAULT_INTRINSIC_COEF, check_intrinsic_coef, is_flag
from sb3_gocu.policies import GoCuActorCriticCnnPolicy, GoCuActorCriticPolicy, GoCuMultiInputActorCriticPolicy
from sb3_gocu.wrappers import GoCuVecEnvWrapper, find_gocu_module, find_gocu_wrappers

SelfPPOGoCu = TypeVar("SelfPPOGoCu", bound="PPO_GoCu")

#: The paper's PPO settings for MiniGrid: PPO_GoCu's defaults for PPO's own arguments, in
#: place of SB3's (n_steps 2048, batch 64, 10 epochs, lr 3e-4, ent 0). The paper trains on ``PAPER_N_ENVS`` envs,
#: which the caller makes: ``make_vec_env(env_id, n_envs=PAPER_N_ENVS)``.
PAPER_PPO_KWARGS: Mapping[str, Any] = MappingProxyType(
    dict(n_steps=128, batch_size=256, n_epochs=4, learning_rate=1e-4, ent_coef=0.01, gamma=0.99, vf_coef=0.5, clip_range=0.2)
)
PAPER_N_ENVS = 16


class PPO_GoCu(PPO):
    """Proximal Policy Optimization with goal-based curiosity (GoCu).

    Takes every argument of SB3's :class:`~stable_baselines3.PPO` (``learning_rate``, ``n_steps``,
    ``batch_size``, ``n_epochs``, ``gamma``, ``gae_lambda``, ``clip_range``, ``ent_coef``, ``vf_coef``, ...); those
    of :data:`PAPER_PPO_KWARGS` default to the paper's values (n_steps 128, batch 256, 4 epochs, lr 1e-4, ent 0.01,
    gamma 0.99, vf 0.5, clip 0.2) instead of SB3's, the others to SB3's. The paper runs 16 envs
    (:data:`PAPER_N_ENVS`): pass ``make_vec_env(env_id, n_envs=16)``; an env id alone gives SB3's single env. Plus:

    :param policy: "MlpPolicy", "CnnPolicy", "MultiInputPolicy" or a two-headed policy class
    :param env: an env id, an env, or a VecEnv; without a GoCu wrapper it is wrapped in a
        :class:`~sb3_gocu.GoCuVecEnvWrapper` (``mode="separate"``) holding a new module on the model's device
    :param intrinsic_coef: sigma of eq 10, weight of the curiosity advantage A_gc (>= 0)
    :param intrinsic_episodic: whether the curiosity stream stops at episode ends (True) or runs across them,
        RND-style (False: r_gc is positive almost everywhere, so an episodic stream pays for not finishing)
    :param curiosity_kwargs: settings of :class:`~sb3_gocu.GoalCuriosityModule` (``n_goals``, ``goal_strategy``, ...;
        :data:`~sb3_gocu.PAPER_CURIOSITY_KWARGS` for the paper's); its ``intrinsic_gamma`` discounts the curiosity stream
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": GoCuActorCriticPolicy,
        "CnnPolicy": GoCuActorCriticCnnPolicy,
        "MultiInputPolicy": GoCuMultiInputActorCriticPolicy,
    }
    rollout_buffer: GoCuRolloutBuffer | GoCuDictRolloutBuffer  # type: ignore[assignment]

    def __init__(
        self,
        policy: str | type[GoCuActorCriticPolicy],
        env: GymEnv | str,
        *args: Any,
        intrinsic_coef: float = DEFAULT_INTRINSIC_COEF,
        intrinsic_episodic: bool = False,
        curiosity_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        self.intrinsic_coef = check_intrinsic_coef(intrinsic_coef)
        if not is_flag(intrinsic_episodic):
            raise ValueError(f"intrinsic_episodic must be True or False, got {intrinsic_episodic!r}")
        self.intrinsic_episodic = bool(intrinsic_episodic)
        if curiosity_kwargs is not None and not isinstance(curiosity_kwargs, Mapping):
            raise TypeError(
                f"curiosity_kwargs must be a dict of GoalCuriosityModule keywords, got {type(curiosity_kwargs).__name__} "
                f"{curiosity_kwargs!r} (in an rl-zoo3 YAML file write it as a mapping, not a 'dict(...)' string)"
            )
        self.curiosity_kwargs = dict(curiosity_kwargs or {})
        self.curiosity: GoalCuriosityModule | None = None
        self.global_rng = GlobalRNGState()
        positional = list(inspect.signature(PPO.__init__).parameters)[3 : 3 + len(args)]  # after self, policy, env
        defaults = {k: v for k, v in PAPER_PPO_KWARGS.items() if k not in positional}
        super().__init__(policy, env, *args, **{**defaults, **kwargs})

    # ------------------------------------------------------------------ set-up
    def _attach_curiosity(self) -> None:
        """Find or make the curiosity module and make sure the training env carries it (separate mode)."""
        found = find_gocu_module(self.env) if self.env is not None else None
        if found is not None:
            module, mode = found
            if mode != "separate":
                raise ValueError(
                    "PPO_GoCu needs its GoCu wrapper in mode='separate' (it adds the curiosity advantage itself); "
                    "the env's wrapper is in mode='sum'"
                )
            if self.curiosity is None:
                self.curiosity = module
            elif module is not self.curiosity:
                # a loaded model brings its own module: the env's wrappers use it from now on
                for wrapper in find_gocu_wrappers(self.env):  # type: ignore[arg-type]
                    wrapper.module = self.curiosity
                self.curiosity.ensure_envs(self.env.num_envs)  # type: ignore[union-attr]
            return
        if self.curiosity is None:
            given = self.curiosity_kwargs.get("device")
            if given is not None and th.device(given) != th.device(self.device):
                raise ValueError(f"curiosity_kwargs['device']={given!r} differs from the model's device {self.device}: "
                                 "the curiosity module follows the model's device (give device= to PPO_GoCu)")
            kwargs = {"seed": self.seed, **self.curiosity_kwargs, "device": self.device}
            self.curiosity = GoalCuriosityModule(self.observation_space, **kwargs)
        if self.env is not None:
            self.env = GoCuVecEnvWrapper(self.env, module=self.curiosity, mode="separate")

    def _setup_model(self) -> None:
        if not self._acting_only:
            self._attach_curiosity()
        intrinsic_gamma = self.curiosity_kwargs.get("intrinsic_gamma", CuriosityConfig.intrinsic_gamma) if self.curiosity is None else self.curiosity.intrinsic_gamma
        if self.rollout_buffer_class is None or not issubclass(self.rollout_buffer_class, (GoCuRolloutBuffer, GoCuDictRolloutBuffer)):
            self.rollout_buffer_class = GoCuDictRolloutBuffer if isinstance(self.observation_space, spaces.Dict) else GoCuRolloutBuffer
        self.rollout_buffer_kwargs = {
            **(self.rollout_buffer_kwargs or {}),
            "intrinsic_gamma": intrinsic_gamma,
            "intrinsic_coef": self.intrinsic_coef,
            "intrinsic_episodic": self.intrinsic_episodic,
        }
        super()._setup_model()

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        super().set_env(env, force_reset)
        if not self._acting_only:
            self._attach_curiosity()
        if force_reset:
            self._last_obs = None

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        """Add a :class:`GoCuCallback` for ``model.curiosity`` unless the user gave one."""

        def has_gocu(cb: Any) -> bool:
            if isinstance(cb, GoCuCallback):
                return True
            if isinstance(cb, CallbackList):
                return any(has_gocu(c) for c in cb.callbacks)
            if isinstance(cb, list):
                return any(has_gocu(c) for c in cb)
            return False

        callbacks: list[BaseCallback] = list(callback) if isinstance(callback, list) else ([] if callback is None else [callback])  # type: ignore[list-item]
        if not has_gocu(callbacks):
            callbacks.append(GoCuCallback(self.curiosity, verbose=self.verbose))
        return super()._init_callback(callbacks, progress_bar)

    # ------------------------------------------------------------------ persistence
    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "curiosity"]

    #: objects of the file besides SB3's: the curiosity module's state and the global RNG states
    GOCU_OBJECTS = ("curiosity", "global_rng")
    #: True for a model loaded with ``load(..., curiosity=False)``: it acts, and has no curiosity module to train
    _acting_only = False

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        omitted = set(getattr(self, "_omitted_objects", ())) | ({"curiosity"} if self.curiosity is None else set())
        return [*state_dicts, *(name for name in self.GOCU_OBJECTS if name not in omitted)], variables

    def save(
        self, path: str | pathlib.Path | io.BufferedIOBase, exclude: Iterable[str] | None = None, include: Iterable[str] | None = None, save_env: bool = False
    ) -> None:
        """SB3's ``save``, atomic: the zip is written to a temporary file beside ``path`` and renamed onto it, so
        a crash never leaves a half-written model file. The file carries the curiosity module's whole state and
        the global RNG states, unless ``exclude`` names them: ``save(path, exclude=["curiosity"])`` writes a file to
        act with (the policy alone); loading it gives a fresh curiosity module.

        :param save_env: also pickle the training env stack into the file, for an exact resumption with
            ``load(path, restore_env=True)`` (in-process envs only; see :mod:`sb3_gocu.checkpoints`)
        """
        exclude = list(exclude) if exclude else None
        self._omitted_objects = set(exclude or ()) & set(self.GOCU_OBJECTS)
        try:
            save_model(self, path, exclude=exclude, include=list(include) if include else None, save_env=save_env)
        finally:
            self._omitted_objects = set()

    def set_parameters(self, load_path_or_dict: str | dict[str, Any], exact_match: bool = True, device: th.device | str = "auto") -> None:
        """SB3's ``set_parameters``; a file or dict without the curiosity state (``save(..., exclude=["curiosity"])``)
        leaves the module as it is, with a warning."""
        if not isinstance(load_path_or_dict, dict):
            _, load_path_or_dict, _ = load_from_zip_file(load_path_or_dict, device=device, load_data=False)
        self._omitted_objects = set(self.GOCU_OBJECTS) - set(load_path_or_dict)
        if "curiosity" in self._omitted_objects and not self._acting_only:
            warnings.warn("the parameters hold no curiosity state (saved with exclude=['curiosity']): the curiosity module starts afresh")
        try:
            super().set_parameters(load_path_or_dict, exact_match=exact_match, device=device)
        finally:
            self._omitted_objects = set()

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfPPOGoCu],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        restore_env: bool = False,
        curiosity: bool = True,
        **kwargs: Any,
    ) -> SelfPPOGoCu:
        """SB3's ``load``, with the curiosity module. A corrupt or truncated file raises a ``ValueError`` naming it.

        :param restore_env: use the env stack saved in the file (``save(..., save_env=True)``) as it was at the
            save, ``_last_obs`` included, so ``learn(..., reset_num_timesteps=False)`` continues the run
            exactly (unpickles code from the file: only for files you wrote)
        :param curiosity: False: to act only, leave the file's curiosity state unread and build no curiosity module
            (less memory and time); such a model predicts but does not learn
        """
        if restore_env and env is not None:
            raise ValueError("give either env or restore_env=True, not both")
        if restore_env and not curiosity:
            raise ValueError("restore_env=True continues the run: it needs the curiosity state (curiosity=True)")
        if not isinstance(path, io.IOBase):
            path = check_model_file(path)
        source: Any = path if curiosity else without_members(path, [f"{name}.pth" for name in cls.GOCU_OBJECTS])
        try:
            # SB3 sets the keywords on the new model before it builds it (_setup_model) and loads its parameters
            model = super().load(source, env=env, device=device, custom_objects=custom_objects, print_system_info=print_system_info,
                                 force_reset=force_reset, _acting_only=not curiosity, **kwargs)
        except (zipfile.BadZipFile, EOFError, pickle.UnpicklingError, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{path}: the model file is corrupt or unreadable ({type(e).__name__}: {e})") from e
        if restore_env:
            model.set_env(read_env_state(path, model.curiosity), force_reset=False)
        return model

    def train(self) -> None:
        """SB3's PPO update; ``train/explained_variance`` is the extrinsic head's, and
        ``train/explained_variance_intrinsic`` the curiosity head's."""
        super().train()
        buffer = self.rollout_buffer
        assert isinstance(buffer, (GoCuRolloutBuffer, GoCuDictRolloutBuffer))
        self.logger.record("train/explained_variance_intrinsic", explained_variance(buffer.intrinsic_values.flatten(), buffer.intrinsic_returns.flatten()))

    # ------------------------------------------------------------------ rollout
    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3's rollout loop with two value heads: stores r_gc (from ``infos``) beside r_e, and bootstraps
        both heads on time-limit truncations (the curiosity head only if the stream is episodic).

        :return: True if ``n_rollout_steps`` steps were collected, False if a callback stopped the rollout
        """
        assert self._last_obs is not None, "No previous observation was provided"
        assert isinstance(rollout_buffer, (GoCuRolloutBuffer, GoCuDictRolloutBuffer))
        self.policy.set_training_mode(False)
        n_steps = 0
        rollout_buffer.reset()
        if self.use_sde:
            self.policy.reset_noise(env.num_envs)
        callback.on_rollout_start()
        while n_steps < n_rollout_steps:
            if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
                self.policy.reset_noise(env.num_envs)
            with th.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)  # type: ignore[arg-type]
                actions, values, log_probs = self.policy(obs_tensor)  # values: (n_envs, 2)
            actions = actions.cpu().numpy()
            clipped_actions = actions
            if isinstance(self.action_space, spaces.Box):
                if self.policy.squash_output:
                    clipped_actions = self.policy.unscale_action(clipped_actions)
                else:
                    clipped_actions = np.clip(actions, self.action_space.low, self.action_space.high)

            new_obs, rewards, dones, infos = env.step(clipped_actions)
            intrinsic = np.array([info["gocu_reward"] for info in infos], dtype=np.float32)
            self.num_timesteps += env.num_envs

            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            if isinstance(self.action_space, spaces.Discrete):
                actions = actions.reshape(-1, 1)

            # time-limit truncation: bootstrap each stream with its own head and discount
            for idx, done in enumerate(dones):
                if done and infos[idx].get("terminal_observation") is not None and infos[idx].get("TimeLimit.truncated", False):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with th.no_grad():
                        terminal_value = self.policy.predict_values(terminal_obs)[0]  # type: ignore[arg-type]
                    rewards[idx] += self.gamma * terminal_value[0].item()
                    if self.intrinsic_episodic:
                        intrinsic[idx] += rollout_buffer.intrinsic_gamma * terminal_value[1].item()

            rollout_buffer.add(
                self._last_obs,  # type: ignore[arg-type]
                actions,
                rewards,
                self._last_episode_starts,  # type: ignore[arg-type]
                values,
                log_probs,
                intrinsic_reward=intrinsic,
            )
            self._last_obs = new_obs  # type: ignore[assignment]
            self._last_episode_starts = dones

        with th.no_grad():
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device))  # type: ignore[arg-type]
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def learn(
        self: SelfPPOGoCu,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 1,
        tb_log_name: str = "PPO_GoCu",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfPPOGoCu:
        """SB3's ``learn``, at the caller's torch thread count, as SB3 trains (for runs side by side, give each
        ``torch.set_num_threads(1)``: docs/results.md, "Threads")."""
        if self._acting_only:
            raise ValueError("this model was loaded with curiosity=False, to act: load it with curiosity=True to train it")
        if reset_num_timesteps:
            self.global_rng.pending = None
        else:
            self.global_rng.restore()  # a loaded model continues with the random numbers of the saved run
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )
