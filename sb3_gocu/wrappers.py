"""Reward wrappers that put goal-based curiosity into any Stable-Baselines3 pipeline.

Both wrappers are thin: the maths lives in :class:`~sb3_gocu.curiosity.GoalCuriosityModule`. Each step
they hand the module the states just reached (the terminal observation where an episode ended), and
report in ``infos``:

* ``"gocu_reward"``: r_gc normalised by the std of intrinsic returns (eq 14), the reward GoCu adds;
* ``"gocu_raw_reward"``: r_gc before normalisation (eq 13);
* ``"extrinsic_reward"``: the environment's reward, unchanged.

Where an episode ends, Monitor's ``info["episode"]`` gets ``"gocu_r"``: the episode's sum of normalised r_gc (what
``rollout/ep_intrinsic_rew_mean`` averages).

``mode="sum"`` returns ``r_e + intrinsic_coef * (r_gc - mean r_gc)`` as the reward (for any SB3 algorithm): r_gc
centred on its running mean over the recorded steps (``module.reward_centre``), so that a longer episode is worth no
more in itself and a learner with one episodic value head is not paid to avoid the goal (``centred=False``: the
paper's ``r_e + intrinsic_coef * r_gc``);
``mode="separate"`` leaves the reward extrinsic (for :class:`~sb3_gocu.PPO_GoCu`, which reads r_gc from
``infos``). Put the wrappers *above* ``Monitor`` (as ``make_vec_env`` does), so that the episode returns
Monitor reports stay extrinsic.

A life lost under SB3's ``EpisodicLifeEnv`` (``AtariWrapper``'s ``terminal_on_life_loss``) ends the learner's episode,
not the curiosity's: the first-visit memory, the K goals and the reachability spans last the whole game, so that
losing a life does not pay the game's cells anew. :class:`GoCuWrapper` reads ``EpisodicLifeEnv.was_real_done`` at the
step; :class:`GoCuVecEnvWrapper` sees the step only after the VecEnv's reset, whose ``FireResetEnv`` steps have
overwritten that flag, so it reads the game's end where SB3's ``evaluate_policy`` does: in the ``info["episode"]`` of
the ``Monitor`` beneath ``EpisodicLifeEnv`` (``make_atari_env`` and rl-zoo3 put it there).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.atari_wrappers import EpisodicLifeEnv
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper, VecMonitor, is_vecenv_wrapped
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.checks import DEFAULT_INTRINSIC_COEF, check_intrinsic_coef

MODES = ("sum", "separate")


def _make_module(
    observation_space: gym.Space, module: GoalCuriosityModule | None, curiosity_kwargs: dict[str, Any] | None
) -> GoalCuriosityModule:
    if module is None:
        return GoalCuriosityModule(observation_space, **(curiosity_kwargs or {}))
    if not isinstance(module, GoalCuriosityModule):
        raise TypeError(f"module must be a GoalCuriosityModule or None, got {type(module).__name__}")
    if curiosity_kwargs:
        raise ValueError("give either `module` or `curiosity_kwargs`, not both")
    if module.observation_space != observation_space:
        raise ValueError(
            f"module was built for {module.observation_space}, but the env observes {observation_space}"
        )
    return module


def _monitor_beneath_lives(env: gym.Env) -> bool:
    """Whether a ``Monitor`` lies beneath the env's ``EpisodicLifeEnv`` (so that it ends episodes at game over only)."""
    lives = False
    while isinstance(env, gym.Wrapper):
        lives = lives or isinstance(env, EpisodicLifeEnv)
        if lives and isinstance(env, Monitor):
            return True
        env = env.env
    return False


class _RewardReport:
    """What both wrappers share: settings, checks, and how r_gc is reported and added."""

    module: GoalCuriosityModule

    def _setup_gocu(
        self,
        observation_space: gym.Space,
        module: GoalCuriosityModule | None,
        mode: str,
        intrinsic_coef: float | None,
        curiosity_kwargs: dict[str, Any] | None,
        centred: bool | None,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if centred is None:
            centred = mode == "sum"
        if not isinstance(centred, (bool, np.bool_)):
            raise ValueError(f"centred must be True or False, got {centred!r}")
        if mode == "separate" and centred:
            raise ValueError("centred applies to mode='sum' only: in mode='separate' the reward is r_e and PPO_GoCu's curiosity head runs across episodes")
        if mode == "separate" and intrinsic_coef is not None:
            raise ValueError(
                "intrinsic_coef weighs r_gc in mode='sum' only; in mode='separate' PPO_GoCu weighs the curiosity "
                "advantage: give PPO_GoCu(intrinsic_coef=...)"
            )
        self.module = _make_module(observation_space, module, curiosity_kwargs)
        self.mode = mode
        # None in mode="separate": nothing weighs r_gc here, PPO_GoCu does
        self.intrinsic_coef: float | None = None
        if mode == "sum":
            self.intrinsic_coef = check_intrinsic_coef(DEFAULT_INTRINSIC_COEF if intrinsic_coef is None else intrinsic_coef)
        self.centred = bool(centred)
        self._episode_sums: dict[int, float] = {}  # env -> normalised r_gc summed over its current episode

    def _centre(self) -> float:
        """What the sum subtracts from this step's normalised r_gc: the running mean before the step (0 uncentred)."""
        # getattr: a wrapper pickled by an older version has no flag and paid the uncentred sum
        # (centred is True in mode="sum" only: _setup_gocu refuses it with "separate")
        return self.module.reward_centre.mean if getattr(self, "centred", False) else 0.0

    def _report(self, info: dict, extrinsic: float, raw: float, normalized: float, env: int = 0, centre: float = 0.0) -> float:
        """Write the three rewards into ``info`` (and the episode's curiosity sum into Monitor's ``info["episode"]``
        at its end) and return the reward the algorithm sees (``centre`` is subtracted from r_gc in the sum)."""
        info["extrinsic_reward"] = float(extrinsic)
        info["gocu_raw_reward"] = float(raw)
        info["gocu_reward"] = float(normalized)
        self._episode_sums[env] = self._episode_sums.get(env, 0.0) + float(normalized)
        if isinstance(info.get("episode"), dict):
            info["episode"]["gocu_r"] = self._episode_sums.pop(env)
        # by mode, not by intrinsic_coef: an env stack pickled by an older version holds 0.25 in mode="separate" too
        return float(extrinsic) + self.intrinsic_coef * (float(normalized) - centre) if self.mode == "sum" else float(extrinsic)


class GoCuVecEnvWrapper(_RewardReport, VecEnvWrapper):
    """Goal-based curiosity for a whole VecEnv, batched over its envs.

    :param venv: the vectorised environment (with ``Monitor`` below this wrapper)
    :param module: the curiosity module; default: a new one built from ``curiosity_kwargs`` and the
        env's observation space
    :param mode: ``"sum"`` (reward = r_e + intrinsic_coef * (r_gc - its running mean)) or ``"separate"`` (reward = r_e)
    :param intrinsic_coef: sigma, weight of r_gc in the summed reward (``mode="sum"`` only, default 0.25 as
        PPO_GoCu's; given with ``mode="separate"`` it is an error)
    :param curiosity_kwargs: keywords of :class:`~sb3_gocu.GoalCuriosityModule` when ``module`` is None
    :param centred: ``mode="sum"`` only: subtract r_gc's running mean in the sum (False: the paper's uncentred sum)
    """

    def __init__(
        self,
        venv: VecEnv,
        module: GoalCuriosityModule | None = None,
        mode: str = "sum",
        intrinsic_coef: float | None = None,
        curiosity_kwargs: dict[str, Any] | None = None,
        centred: bool | None = None,
    ) -> None:
        VecEnvWrapper.__init__(self, venv)
        self._setup_gocu(venv.observation_space, module, mode, intrinsic_coef, curiosity_kwargs, centred)
        self.module.ensure_envs(self.num_envs)
        self._lives = self._find_lives()

    #: per env, whether it is wrapped in ``EpisodicLifeEnv`` (None until the first step: env stacks pickled before it
    #: existed load without it)
    _lives: np.ndarray | None = None

    def _find_lives(self) -> np.ndarray:
        """Per env, whether it is wrapped in ``EpisodicLifeEnv``; such envs need a ``Monitor`` beneath it, which tells
        the game's end (one above, or a ``VecMonitor``, ends an episode at every lost life)."""
        lives = np.array(self.venv.env_is_wrapped(EpisodicLifeEnv), dtype=bool)
        if lives.any():
            base = self.venv.unwrapped
            if isinstance(base, DummyVecEnv):  # the order of the wrappers can be read
                monitored = np.array([_monitor_beneath_lives(e) for e in base.envs], dtype=bool)
            else:
                monitored = np.array(self.venv.env_is_wrapped(Monitor), dtype=bool)
            unmonitored = np.flatnonzero(lives & ~monitored)
            if len(unmonitored) or is_vecenv_wrapped(self.venv, VecMonitor):
                raise ValueError(
                    f"venv: env {int(unmonitored[0]) if len(unmonitored) else 0} is wrapped in EpisodicLifeEnv, and GoCu tells "
                    "a game's end from a lost life by the info['episode'] of a Monitor beneath it: wrap each env in Monitor "
                    "before AtariWrapper (make_vec_env, make_atari_env and rl-zoo3 do), not after it nor in a VecMonitor"
                )
        return lives

    def reset(self) -> Any:
        obs = self.venv.reset()
        self.module.begin_episodes(np.arange(self.num_envs))
        self._episode_sums.clear()
        return obs

    def _games_over(self, dones: np.ndarray, infos: list[dict]) -> np.ndarray:
        """``dones`` less the lives lost under ``EpisodicLifeEnv``: there the game is over where the Monitor beneath it
        ended an episode (``EpisodicLifeEnv.was_real_done`` was overwritten by the VecEnv's reset)."""
        if self._lives is None:
            self._lives = self._find_lives()
        ends = dones.copy()
        for i in np.flatnonzero(dones & self._lives):
            ends[i] = "episode" in infos[i]
        return ends

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        reached = obs
        if dones.any():
            # the reward of the last transition is the curiosity of the terminal state, not of the reset one
            done_idx = [i for i in np.flatnonzero(dones) if infos[i].get("terminal_observation") is not None]
            if done_idx:
                if isinstance(obs, dict):
                    reached = {k: v.copy() for k, v in obs.items()}
                    for i in done_idx:
                        for k in reached:
                            reached[k][i] = infos[i]["terminal_observation"][k]
                else:
                    reached = obs.copy()
                    for i in done_idx:
                        reached[i] = infos[i]["terminal_observation"]
        centre = self._centre()
        raw, normalized = self.module.step(reached, self._games_over(dones, infos) if dones.any() else dones)
        rewards = np.array([self._report(info, rewards[i], raw[i], normalized[i], i, centre) for i, info in enumerate(infos)], dtype=np.float32)
        return obs, rewards, dones, infos


class GoCuWrapper(_RewardReport, gym.Wrapper):
    """Goal-based curiosity for one gymnasium env (rl-zoo3's ``env_wrapper``, or a ``DummyVecEnv`` of such
    envs). Several envs of one ``DummyVecEnv`` should share one module (pass the same ``module``); each
    wrapper takes an env index in it.

    :param env: the environment
    :param module: the curiosity module (default: a new one from ``curiosity_kwargs``)
    :param mode: ``"sum"`` or ``"separate"``, as for :class:`GoCuVecEnvWrapper`
    :param intrinsic_coef: sigma, weight of r_gc in the summed reward (``mode="sum"`` only, default 0.25 as
        PPO_GoCu's; given with ``mode="separate"`` it is an error)
    :param curiosity_kwargs: keywords of :class:`~sb3_gocu.GoalCuriosityModule` when ``module`` is None
    :param centred: ``mode="sum"`` only: subtract r_gc's running mean in the sum, as for :class:`GoCuVecEnvWrapper`
    """

    def __init__(
        self,
        env: gym.Env,
        module: GoalCuriosityModule | None = None,
        mode: str = "sum",
        intrinsic_coef: float | None = None,
        curiosity_kwargs: dict[str, Any] | None = None,
        centred: bool | None = None,
    ) -> None:
        gym.Wrapper.__init__(self, env)
        self._setup_gocu(env.observation_space, module, mode, intrinsic_coef, curiosity_kwargs, centred)
        self.env_index = self.module.register_env()
        self._index = np.array([self.env_index])
        self._lives = is_wrapped(env, EpisodicLifeEnv)

    #: whether the env is wrapped in ``EpisodicLifeEnv`` (False for a wrapper pickled before it existed)
    _lives: bool = False
    #: whether the last step ended the game, not just a life (True before the first step: the first reset begins one)
    _game_over: bool = True

    @staticmethod
    def _batch(obs: Any) -> Any:
        if isinstance(obs, dict):
            return {k: np.asarray(v)[None] for k, v in obs.items()}
        return np.asarray(obs)[None]

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        obs, info = self.env.reset(**kwargs)
        if self._game_over:  # after a lost life the game, and the curiosity's episode, go on
            self.module.begin_episodes(self._index)
            self._episode_sums.clear()
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        # read now: a reset's FireResetEnv steps overwrite was_real_done
        self._game_over = not self._lives or bool(self.env.get_wrapper_attr("was_real_done"))
        done = bool(terminated or truncated) and self._game_over
        centre = self._centre()
        raw, normalized = self.module.step(self._batch(obs), np.array([done]), self._index)
        return obs, self._report(info, reward, raw[0], normalized[0], centre=centre), terminated, truncated, info


def find_gocu_wrappers(env: VecEnv | gym.Env) -> list[GoCuVecEnvWrapper | GoCuWrapper]:
    """Every GoCu wrapper in a VecEnv's wrapper stack, including per-env wrappers of a ``DummyVecEnv``."""
    found: list[GoCuVecEnvWrapper | GoCuWrapper] = []
    venv: Any = env
    while isinstance(venv, VecEnvWrapper):
        if isinstance(venv, GoCuVecEnvWrapper):
            found.append(venv)
        venv = venv.venv
    envs = venv.envs if isinstance(venv, DummyVecEnv) else ([venv] if isinstance(venv, gym.Env) else [])
    for e in envs:
        while isinstance(e, gym.Wrapper):
            if isinstance(e, GoCuWrapper):
                found.append(e)
            e = e.env
    return found


def find_gocu_module(env: VecEnv | gym.Env) -> tuple[GoalCuriosityModule, str] | None:
    """The curiosity module of an env's GoCu wrappers and their mode, or None if there is none.

    :raises ValueError: if the wrappers hold several modules or mix modes
    """
    wrappers = find_gocu_wrappers(env)
    if not wrappers:
        return None
    modules = {id(w.module): w.module for w in wrappers}
    modes = {w.mode for w in wrappers}
    if len(modules) > 1 or len(modes) > 1:
        raise ValueError(
            f"found {len(wrappers)} GoCu wrappers holding {len(modules)} modules in modes {sorted(modes)}: "
            "all wrappers of one training env must share one module and one mode"
        )
    return wrappers[0].module, wrappers[0].mode
