"""The compact form of a :class:`~sb3_gocu.curiosity.module.GoalCuriosityModule` state dict (tensors and plain Python
values, loadable with ``torch.load(..., weights_only=True)``). No SB3 import.

The raw observations the module keeps (memory bank, goal buffer, goals and states of the current episodes) repeat a
lot: the saved state holds each distinct one once, compressed, and the places that held them hold indices into that
table; the trajectory store's embeddings likewise (:func:`pack`, :func:`unpack`)."""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np
import torch as th

from sb3_gocu.curiosity.stores import distinct_rows


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
