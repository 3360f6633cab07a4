"""refit_predictor_after_vae: at a VAE update the trajectory store is embedded again with the new encoder (not
emptied) and the predictor is retrained on it before the new embeddings score a state."""

import numpy as np
import pytest
import torch as th

from sb3_gocu.curiosity import GoalCuriosityModule, TrajectoryStore
from tests.conftest import SMALL_CURIOSITY, ChainEnv, record_steps


def filled_store(keep_observations: bool = True) -> TrajectoryStore:
    """2 envs x ring of 6; env 0 wrote 8 states (wrapped), env 1 wrote 3; observations repeat."""
    store = TrajectoryStore(12, embed_dim=2, min_per_env=6, obs_shape=(3,) if keep_observations else None, obs_dtype=np.uint8)
    store.ensure_envs(2)
    for step in range(8):
        envs = np.array([0, 1]) if step < 3 else np.array([0])
        obs = np.array([[step % 3, 0, 0], [7, step, 0]], dtype=np.uint8)[: len(envs)]
        store.add(th.full((len(envs), 2), -1.0), np.array([0, 1])[: len(envs)], envs, obs if keep_observations else None)
    return store


def test_store_embeds_its_filled_slots_again_once_per_distinct_observation():
    store = filled_store()
    calls = []

    def embed(raw: np.ndarray) -> th.Tensor:
        calls.append(raw.copy())
        return th.from_numpy(raw.astype(np.float32))[:, :2] * 10 + 1

    out = store.embedded(embed)
    assert len(calls) == 1 and len(calls[0]) == 3 + 3, "observations 0, 1, 2 of env 0 and (7, 0..2) of env 1, once each"
    assert {tuple(r) for r in calls[0].tolist()} == {(0, 0, 0), (1, 0, 0), (2, 0, 0), (7, 0, 0), (7, 1, 0), (7, 2, 0)}
    # env 0: ring of 6 holds steps 2..7 (positions 2,3,4,5,0,1), i.e. observations step % 3
    for step in range(2, 8):
        assert out[step % 6, 0].tolist() == [(step % 3) * 10 + 1, 1.0]
    for step in range(3):
        assert out[step, 1].tolist() == [71.0, step * 10 + 1]
    assert out[3:, 1].tolist() == [[0.0, 0.0]] * 3, "slots never written are left as they are"
    assert bool((store.embeddings[store.embeddings != 0] == -1).all()), "the store itself is not changed"


def test_store_without_observations_refuses_to_embed_again_and_one_with_them_needs_them():
    with pytest.raises(ValueError, match="keeps no observations"):
        filled_store(keep_observations=False).embedded(lambda raw: th.zeros(len(raw), 2))
    store = filled_store()
    with pytest.raises(ValueError, match="add\\(\\) needs them"):
        store.add(th.zeros(1, 2), np.array([0]), np.array([0]))


def test_pairs_of_a_draw_are_those_of_sample_pairs_and_can_take_other_embeddings():
    store = filled_store()
    store.embeddings = th.arange(6 * 2 * 2, dtype=th.float32).reshape(6, 2, 2)
    a = store.sample_pairs(50, 3, np.random.default_rng(1), first_visit=True)
    draw = store.draw_pairs(50, 3, np.random.default_rng(1), first_visit=True)
    b = store.pairs(draw)
    assert all(th.equal(x, y) for x, y in zip(a, b))
    other = store.embeddings * 2
    c = store.pairs(draw, other)
    assert th.equal(c[0], a[0] * 2) and th.equal(c[1], a[1] * 2) and th.equal(c[2], a[2])


def test_store_observations_survive_a_state_dict_and_a_state_without_them_starts_empty():
    store = filled_store()
    copy = TrajectoryStore(12, 2, 6, obs_shape=(3,))
    copy.load_state_dict(store.state_dict())
    assert np.array_equal(copy.observations, store.observations) and th.equal(copy.embeddings, store.embeddings)
    assert len(copy) == len(store) == 9
    empty = TrajectoryStore(12, 2, 6, obs_shape=(3,))
    empty.load_state_dict(filled_store(keep_observations=False).state_dict())
    assert len(empty) == 0 and empty.observations.shape == (6, 2, 3)
    with pytest.raises(ValueError, match="shape \\(3,\\), expected \\(4,\\)"):
        TrajectoryStore(12, 2, 6, obs_shape=(4,)).load_state_dict(store.state_dict())


def modules_after_steps(*variants: dict) -> list[GoalCuriosityModule]:
    """Modules with one seed and ``variants`` settings after the same 300 recorded steps of 2 envs on random
    observations (with repeats), so that a VAE update is due at the next maybe_train."""
    space = ChainEnv().observation_space
    settings = {**SMALL_CURIOSITY, "vae_train_freq": 512, "predictor_train_freq": 256}
    modules = [GoalCuriosityModule(space, **{**settings, **v}, seed=3) for v in variants]
    rng = np.random.default_rng(0)
    values = rng.random((12, 2)).astype(np.float32)
    batches = [(values[rng.integers(12, size=2)], rng.random(2) < 0.1) for _ in range(300)]
    for module in modules:
        record_steps(module, batches[:251])
        module.maybe_train()  # a predictor update, so that the next one is not due with the VAE's
        record_steps(module, batches[251:])
    return modules


def test_a_vae_update_renews_the_store_and_retrains_the_predictor_on_the_new_embeddings(monkeypatch):
    refit, plain = modules_after_steps({"refit_predictor_after_vae": True}, {})
    assert not plain.refit_predictor_after_vae, "off by default"
    assert plain.trajectories.observations is None and refit.trajectories.observations is not None
    n_before, old = len(refit.trajectories), refit.trajectories.embeddings.clone()
    old_predictor = {k: v.clone() for k, v in refit.predictor.state_dict().items()}
    fitted_on = []
    fit_predictor = refit._fit_predictor
    monkeypatch.setattr(refit, "_fit_predictor", lambda **job: fitted_on.append(job) or fit_predictor(**job))
    assert refit.n_recorded_steps - refit.last_predictor_update < refit.predictor_train_freq, "the predictor is not due"
    out = refit.maybe_train()
    assert "vae_loss" in out and "predictor_loss" in out, "the predictor is retrained with the VAE"
    assert refit.last_predictor_update == refit.n_recorded_steps
    assert len(fitted_on) == 1
    assert any(not th.equal(v, refit.predictor.state_dict()[k]) for k, v in old_predictor.items())
    # the store keeps its states, embedded with the new encoder
    store = refit.trajectories
    assert len(store) == n_before > 0
    filled = np.arange(store.capacity)[:, None] < np.minimum(store.count, store.capacity)[None, :]
    t, e = np.nonzero(filled)
    new = refit.embed(store.observations[t, e])
    assert th.allclose(store.embeddings[t, e], new, atol=1e-5)
    assert not th.allclose(old[t, e], new, atol=1e-3), "the VAE moved: the old embeddings would be stale"
    # the predictor's pairs are rows of the renewed embeddings
    rows = {tuple(r) for r in store.embeddings[t, e].tolist()}
    job = fitted_on[0]
    assert all(tuple(r) in rows for r in job["phi_s"].tolist()) and all(tuple(r) in rows for r in job["phi_g"].tolist())
    # without the option, the VAE update empties the store and the predictor waits for its schedule
    out_plain = plain.maybe_train()
    assert "vae_loss" in out_plain and "predictor_loss" not in out_plain and len(plain.trajectories) == 0


def test_the_refit_gives_the_same_networks_in_place_and_overlapping_ppos_update():
    in_place, overlap = modules_after_steps({"refit_predictor_after_vae": True},
                                            {"refit_predictor_after_vae": True, "overlap_ppo_update": True})
    out_in_place = in_place.maybe_train()
    overlap.maybe_train()
    assert overlap.update_running
    obs = np.array([[0.3, 0.09], [0.6, 0.36]], dtype=np.float32)
    assert np.array_equal(in_place.step(obs, np.zeros(2, bool))[0], overlap.step(obs, np.zeros(2, bool))[0])
    for name in ("vae", "predictor"):
        a, b = getattr(in_place, name).state_dict(), getattr(overlap, name).state_dict()
        assert all(th.equal(a[k], b[k]) for k in a), name
    assert th.equal(in_place.trajectories.embeddings, overlap.trajectories.embeddings)
    out_next = overlap.maybe_train()
    assert out_next["predictor_loss"] == out_in_place["predictor_loss"] and out_next["vae_loss"] == out_in_place["vae_loss"]


def test_background_updates_renew_the_store_states_written_meanwhile():
    """train_in_background: the module goes on recording while the update runs; at its finish the store (states
    written meanwhile included) holds the new encoder's embeddings."""
    (module,) = modules_after_steps({"refit_predictor_after_vae": True, "train_in_background": True})
    module.maybe_train()
    assert module.update_running
    module.step(np.array([[0.3, 0.09], [0.6, 0.36]], dtype=np.float32), np.zeros(2, bool))
    module.collect_all()
    out = module.finish_background_update()
    assert "predictor_loss" in out and "vae_loss" in out
    store = module.trajectories
    filled = np.arange(store.capacity)[:, None] < np.minimum(store.count, store.capacity)[None, :]
    t, e = np.nonzero(filled)
    assert th.allclose(store.embeddings[t, e], module.embed(store.observations[t, e]), atol=1e-5)


def test_a_rolled_back_vae_update_discards_the_refit(monkeypatch):
    (module,) = modules_after_steps({"refit_predictor_after_vae": True})
    predictor = {k: v.clone() for k, v in module.predictor.state_dict().items()}
    embeddings = module.trajectories.embeddings.clone()
    fit_vae = module._fit_vae

    def breaking(**job):
        out = fit_vae(**job)
        with th.no_grad():
            next(module.vae.decoder_parameters() if hasattr(module.vae, "decoder_parameters") else iter(list(module.vae.parameters())[-1:])).fill_(float("nan"))
        return out

    monkeypatch.setattr(module, "_fit_vae", breaking)
    with pytest.warns(UserWarning, match="rolled back"):
        out = module.maybe_train()
    assert "predictor_loss" not in out
    assert all(th.equal(v, module.predictor.state_dict()[k]) for k, v in predictor.items()), "the predictor is as before"
    assert th.equal(module.trajectories.embeddings, embeddings), "the old encoder's embeddings are still valid"
    assert module.stats["vae_restored_updates"] == 1


def test_refit_setting_is_checked_and_survives_a_save_and_load():
    with pytest.raises(ValueError, match="refit_predictor_after_vae must be True or False, got 'yes'"):
        GoalCuriosityModule(ChainEnv().observation_space, refit_predictor_after_vae="yes")
    (module,) = modules_after_steps({"refit_predictor_after_vae": True})
    state = module.state_dict()
    other = GoalCuriosityModule(ChainEnv().observation_space, **{**SMALL_CURIOSITY, "refit_predictor_after_vae": True}, seed=9)
    other.load_state_dict(state)
    assert np.array_equal(other.trajectories.observations, module.trajectories.observations)
    assert th.equal(other.trajectories.embeddings, module.trajectories.embeddings)
    assert np.array_equal(other.trajectories.count, module.trajectories.count)


def test_pretraining_is_followed_by_a_predictor_fit_on_the_random_policy_trajectories():
    space = ChainEnv().observation_space
    modules = [GoalCuriosityModule(space, **{**SMALL_CURIOSITY, "refit_predictor_after_vae": v}, seed=1) for v in (True, False)]
    rng = np.random.default_rng(2)
    batches = [(rng.random((2, 2)).astype(np.float32), rng.random(2) < 0.1) for _ in range(64)]
    for module in modules:
        record_steps(module, batches)
    refit, plain = modules
    before = {k: v.clone() for k, v in refit.predictor.state_dict().items()}
    out = refit.pretrain()
    assert "vae_loss" in out and "predictor_loss" in out and len(refit.trajectories) == 128
    assert any(not th.equal(v, refit.predictor.state_dict()[k]) for k, v in before.items())
    assert refit.last_predictor_update == refit.n_recorded_steps == 128
    out_plain = plain.pretrain()
    assert "predictor_loss" not in out_plain and len(plain.trajectories) == 0
