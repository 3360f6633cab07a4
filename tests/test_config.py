"""The module's settings: one checked, frozen config; the paper's preset; retired and unknown names refused."""

import dataclasses
import inspect

import pytest
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import PAPER_CURIOSITY_KWARGS, CuriosityConfig, GoalCuriosityModule, PPO_GoCu

from conftest import SMALL_CURIOSITY, ChainEnv

BOX = ChainEnv().observation_space


def test_the_paper_preset_names_only_departures_of_the_defaults():
    defaults = CuriosityConfig()
    fields = {f.name for f in dataclasses.fields(CuriosityConfig)}
    assert PAPER_CURIOSITY_KWARGS and set(PAPER_CURIOSITY_KWARGS) <= fields
    for name, value in PAPER_CURIOSITY_KWARGS.items():
        assert getattr(defaults, name) != value, f"{name}: the default is the paper's already"
    module = GoalCuriosityModule(BOX, **{**SMALL_CURIOSITY, **PAPER_CURIOSITY_KWARGS})
    assert all(getattr(module, name) == value for name, value in PAPER_CURIOSITY_KWARGS.items())
    model = PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), curiosity_kwargs=PAPER_CURIOSITY_KWARGS)
    assert model.curiosity.config.revisit_decay == "none" and not model.curiosity.config.vae_dedupe


def test_settings_are_fixed_at_construction():
    module = GoalCuriosityModule(BOX, **SMALL_CURIOSITY)
    assert module.n_goals == SMALL_CURIOSITY["n_goals"] == module.config.n_goals
    with pytest.raises(AttributeError, match="n_goals is a setting, fixed at construction"):
        module.n_goals = 3
    with pytest.raises(dataclasses.FrozenInstanceError):
        module.config.n_goals = 3


def test_unknown_and_retired_names_are_refused_with_the_name():
    with pytest.raises(TypeError, match=r"unknown settings \['n_goal'\]"):
        GoalCuriosityModule(BOX, n_goal=3)
    for name in ("predictor_lead", "train_in_background", "vae_shards", "scoring_dtype", "overlap_ppo_update"):
        with pytest.raises(TypeError, match=rf"\['{name}'\] retired"):
            GoalCuriosityModule(BOX, **{name: 1})


def test_the_module_keeps_at_most_40_keywords():
    keywords = [p for p in inspect.signature(GoalCuriosityModule).parameters if p not in ("observation_space", "settings")]
    assert len(keywords) + len(dataclasses.fields(CuriosityConfig)) <= 40
