"""Saving and restoring a :class:`~sb3_gocu.curiosity.module.GoalCuriosityModule`: its whole state as tensors and
plain Python values, loadable with ``torch.load(..., weights_only=True)``, so that a resumed run continues bit for
bit (the memos included: recomputing a value in another batch can change its last bits). No SB3 import."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sb3_gocu.curiosity.episodes import Episodes, memo_from_state, memo_to_state
from sb3_gocu.curiosity.stores import TrajectoryStore
from sb3_gocu.curiosity.training import nonfinite_entries

if TYPE_CHECKING:
    from sb3_gocu.curiosity.module import GoalCuriosityModule


def module_state(module: GoalCuriosityModule) -> dict[str, Any]:
    """The module's state dict (scores in flight taken first)."""
    module.collect_all()
    return {
        "vae": module.vae.state_dict(),
        "vae_optimizer": module.trainer.vae_optimizer.state_dict(),
        "predictor": module.predictor.state_dict(),
        "predictor_optimizer": module.trainer.predictor_optimizer.state_dict(),
        "goal_buffer": module.goal_buffer.state_dict(),
        "memory": module.memory.state_dict(),
        "trajectories": module.trajectories.state_dict(),
        "normalizer": module.normalizer.state_dict(),
        "rng": module.rng.bit_generator.state,
        "torch_rng": module.trainer.generator.get_state(),
        "envs": module.episodes.state_dict(),
        "phi_cache": memo_to_state(module.scorer.phi_memo),
        # the loss the VAE trains with goes with the VAE, so a resumed run keeps it (see load_state_dict)
        "settings": {"vae_pixel_weighting": module.vae_pixel_weighting},
        "counters": {"pretrained": module.pretrained, "n_recorded_steps": module.n_recorded_steps,
                     "last_vae_update": module.last_vae_update, "last_predictor_update": module.last_predictor_update},
    }


def load_module_state(module: GoalCuriosityModule, state: dict[str, Any], strict: bool = True) -> None:
    """Restore a :func:`module_state` into ``module``; a ``ValueError`` for a state that is not one or holds
    non-finite weights."""
    missing = {"vae", "predictor", "goal_buffer", "memory", "normalizer", "counters"} - set(state)
    if missing:
        raise ValueError(f"curiosity state is missing {sorted(missing)}: not a GoalCuriosityModule state_dict")
    for net in ("vae", "predictor"):
        bad = nonfinite_entries(state[net])
        if bad:
            raise ValueError(f"curiosity state: the {net} holds non-finite values in {bad[:3]} (a corrupt file or a diverged run)")
    module.collect_all()
    module.vae.load_state_dict(state["vae"], strict=strict)
    module.scorer.phi_memo.clear()
    module.predictor.load_state_dict(state["predictor"], strict=strict)
    for name, optimizer in (("vae_optimizer", module.trainer.vae_optimizer), ("predictor_optimizer", module.trainer.predictor_optimizer)):
        if name in state:
            optimizer.load_state_dict(state[name])
            for group in optimizer.param_groups:  # a state saved before foreach was on keeps the multi-tensor step
                group["foreach"] = True
    module.vae.eval()
    module._encoder = module._frozen_encoder()
    module.predictor.eval()
    module.goal_buffer.load_state_dict(state["goal_buffer"])
    module.memory.load_state_dict(state["memory"])
    module.normalizer.load_state_dict(state["normalizer"])
    if "rng" in state:
        module.rng.bit_generator.state = state["rng"]
    if "torch_rng" in state:
        module.trainer.generator.set_state(state["torch_rng"])
    settings = state.get("settings", {})
    if "vae_pixel_weighting" in settings:
        module.vae_pixel_weighting = float(settings["vae_pixel_weighting"])
    elif not module._pixel_weighting_given:
        module.vae_pixel_weighting = 0.0  # saved before the weighting existed: the VAE trained without it
    c = state["counters"]
    module.pretrained = bool(c["pretrained"])
    module.n_recorded_steps = int(c["n_recorded_steps"])
    module.last_vae_update = int(c["last_vae_update"])
    module.last_predictor_update = int(c["last_predictor_update"])
    module._folded = module.predictor.fold()
    envs = state.get("envs")
    if envs is not None:
        n = int(envs["episode_ids"].shape[0])
        cfg = module.config
        module.episodes = Episodes(cfg.n_goals, module.adapter.raw_shape, module.adapter.raw_dtype, module.predictor.hidden[0].out_features)
        module.scorer.episodes, module.scorer.pending = module.episodes, []
        module.trajectories = TrajectoryStore(cfg.predictor_train_freq, cfg.embed_dim, min_per_env=2 * cfg.max_distance)
        module.normalizer.returns = module.normalizer.returns[:0]
        rng_state = module.rng.bit_generator.state
        module.ensure_envs(n)  # allocates; the goals it draws are overwritten below
        module.rng.bit_generator.state = rng_state
        module.normalizer.load_state_dict(state["normalizer"])
        module.episodes.load_state_dict(envs)
        module.trajectories.load_state_dict(state["trajectories"])
        module._refresh_active_goals()
        module.episodes.load_memos(envs)
    if "phi_cache" in state:
        module.scorer.phi_memo.update(memo_from_state(state["phi_cache"]))
