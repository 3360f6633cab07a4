"""A :class:`~sb3_gocu.curiosity.module.GoalCuriosityModule`'s state dict (:func:`module_state`,
:func:`load_module_state`) and its compact form (tensors and plain Python
values, loadable with ``torch.load(..., weights_only=True)``). No SB3 import.

The raw observations the module keeps (memory bank, goal buffer, goals and states of the current episodes) repeat a
lot: the saved state holds each distinct one once, compressed, and the places that held them hold indices into that
table; the trajectory store's embeddings likewise (:func:`pack`, :func:`unpack`)."""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np
import torch as th

from sb3_gocu.curiosity.episodes import memo_from_state, memo_to_state
from sb3_gocu.curiosity.revisits import cell_from_state
from sb3_gocu.curiosity.stores import distinct_rows
from sb3_gocu.curiosity.training import nonfinite_entries


#: where the saved state holds raw observations: (entry, key) of one array, or of a list of arrays (``[]``)
OBSERVATION_PLACES = (("memory", "observations"), ("goal_buffer", "observations"), ("envs", "goal_obs"), ("envs", "episodes[]"),
                      ("envs", "finished_episodes[]"))


def _compressed(array: np.ndarray) -> dict[str, Any]:
    return {"zlib": th.frombuffer(bytearray(zlib.compress(np.ascontiguousarray(array).tobytes(), 6)), dtype=th.uint8),
            "shape": list(array.shape), "dtype": str(array.dtype)}


def _decompressed(entry: dict[str, Any]) -> np.ndarray:
    return np.frombuffer(zlib.decompress(entry["zlib"].numpy().tobytes()), dtype=np.dtype(entry["dtype"])).reshape(entry["shape"]).copy()


def _table(arrays: list[np.ndarray], row_shape: tuple[int, ...]) -> tuple[dict[str, Any], list[th.Tensor]]:
    """The distinct rows of ``arrays`` (each of rows of ``row_shape``) compressed, and each array as row indices."""
    rows = np.concatenate([a.reshape(-1, *row_shape) for a in arrays])
    first, inverse = distinct_rows(rows)
    bounds = np.cumsum([0] + [int(np.prod(a.shape[: a.ndim - len(row_shape)])) for a in arrays])
    indices = [th.from_numpy(inverse[lo:hi].astype(np.int32).reshape(a.shape[: a.ndim - len(row_shape)]))
               for a, lo, hi in zip(arrays, bounds[:-1], bounds[1:])]
    return _compressed(rows[first]), indices


def pack(state: dict[str, Any], row_shape: tuple[int, ...]) -> dict[str, Any]:
    """``state`` with its raw observations (rows of ``row_shape``) and the trajectory store's embeddings each kept
    once: ``state["observation_table"]`` holds the distinct observations, and each place of
    :data:`OBSERVATION_PLACES` an index tensor in their stead."""
    state = {k: dict(v) if isinstance(v, dict) else v for k, v in state.items()}
    arrays, slots = [], []
    for entry, key in OBSERVATION_PLACES:
        if key.endswith("[]"):
            key = key[:-2]
            state[entry][key] = list(state[entry][key])
            for i, t in enumerate(state[entry][key]):
                if t.ndim > len(row_shape):  # an episode without states is a zeros(0)
                    arrays.append(t.numpy())
                    slots.append((entry, key, i))
        else:
            arrays.append(state[entry][key].numpy())
            slots.append((entry, key, None))
    state["observation_table"], indices = _table(arrays, row_shape)
    for (entry, key, i), index in zip(slots, indices):
        if i is None:
            state[entry][key] = index
        else:
            state[entry][key][i] = index
    embeddings = state["trajectories"]["embeddings"].numpy()
    state["trajectories"]["embedding_table"], (state["trajectories"]["embeddings"],) = _table([embeddings], embeddings.shape[-1:])
    return state


def unpack(state: dict[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`pack` (a state saved before packing is returned as it is)."""
    if "observation_table" not in state:
        return state
    state = {k: dict(v) if isinstance(v, dict) else v for k, v in state.items()}
    table = _decompressed(state.pop("observation_table"))
    for entry, key in OBSERVATION_PLACES:
        if key.endswith("[]"):
            key = key[:-2]
            state[entry][key] = [th.from_numpy(table[t.numpy()]) if t.dtype == th.int32 else t for t in state[entry][key]]
        else:
            state[entry][key] = th.from_numpy(table[state[entry][key].numpy()])
    trajectories = state["trajectories"]
    trajectories["embeddings"] = th.from_numpy(_decompressed(trajectories.pop("embedding_table"))[trajectories["embeddings"].numpy()])
    return state


def module_state(module: Any) -> dict[str, Any]:
    """Everything a :class:`~sb3_gocu.curiosity.module.GoalCuriosityModule` learned and remembers, as tensors and plain Python values (loadable with
    ``torch.load(..., weights_only=True)``), each raw observation kept once (:func:`persistence.pack`), so that a
    resumed run continues bit for bit (the memos included: recomputing a value in another batch can change its
    last bits)."""
    state = {
        "vae": module.vae.state_dict(),
        "vae_optimizer": module.trainer.vae_optimizer.state_dict(),
        "predictor": module.predictor.state_dict(),
        "predictor_optimizer": module.trainer.predictor_optimizer.state_dict(),
        "goal_buffer": module.goal_buffer.state_dict(),
        "memory": module.memory.state_dict(),
        "trajectories": module.trajectories.state_dict(),
        "normalizer": module.normalizer.state_dict(),
        "reward_centre": module.reward_centre.state_dict(),
        "rng": module.rng.bit_generator.state,
        "torch_rng": module.trainer.generator.get_state(),
        "envs": module.episodes.state_dict(),
        "phi_cache": memo_to_state(module.scorer.phi_memo),
        # the loss the VAE trains with goes with the VAE, so a resumed run keeps it (see load_state_dict)
        "settings": {"vae_pixel_weighting": module.vae_pixel_weighting},
        "revisit_key": module.revisit_key.state_dict(),
        "counters": {"pretrained": module.pretrained, "n_recorded_steps": module.n_recorded_steps,
                     "last_vae_update": module.last_vae_update, "last_predictor_update": module.last_predictor_update},
    }
    return pack(state, module.adapter.raw_shape)


def load_module_state(module: Any, state: dict[str, Any], strict: bool = True) -> None:
    """Restore a :func:`module_state` into ``module``; a ``ValueError`` for a state that is not one or holds non-finite weights.

    :param state: what :func:`module_state` returned
    :param strict: as for ``torch.nn.Module.load_state_dict`` (accepted for SB3's ``set_parameters``)
    """
    missing = {"vae", "predictor", "goal_buffer", "memory", "normalizer", "counters"} - set(state)
    if missing:
        raise ValueError(f"curiosity state is missing {sorted(missing)}: not a GoalCuriosityModule state_dict")
    state = unpack(state)
    for net in ("vae", "predictor"):
        bad = nonfinite_entries(state[net])
        if bad:
            raise ValueError(f"curiosity state: the {net} holds non-finite values in {bad[:3]} (a corrupt file or a diverged run)")
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
    if "reward_centre" in state:  # a state saved before the centring starts its mean afresh
        module.reward_centre.load_state_dict(state["reward_centre"])
    if "rng" in state:
        module.rng.bit_generator.state = state["rng"]
    if "torch_rng" in state:
        module.trainer.generator.set_state(state["torch_rng"])
    settings = state.get("settings", {})
    if "vae_pixel_weighting" in settings:
        module.vae_pixel_weighting = float(settings["vae_pixel_weighting"])
    elif not module._pixel_weighting_given:
        module.vae_pixel_weighting = 0.0  # saved before the weighting existed: the VAE trained without it
    # a state saved before the cell key: Go-Explore's cell (it had counted visits by the observation's bytes)
    module.revisit_key = (cell_from_state(state["revisit_key"], module.adapter.layout, module.adapter.scale, module.adapter.raw_shape)
                        if "revisit_key" in state else module._default_cell())
    c = state["counters"]
    module.pretrained = bool(c["pretrained"])
    module.n_recorded_steps = int(c["n_recorded_steps"])
    module.last_vae_update = int(c["last_vae_update"])
    module.last_predictor_update = int(c["last_predictor_update"])
    module._folded = module.predictor.fold()
    envs = state.get("envs")
    if envs is not None:
        n = int(envs["episode_ids"].shape[0])
        module.episodes, module.trajectories = module._new_env_stores()
        module.scorer.episodes = module.episodes
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
