"""Where is a trained PPO_GoCu agent curious? Intrinsic-reward and mastery maps over a DoorKey grid.

    python examples/curiosity_map.py --model gocu_doorkey8.zip --env GoCu/DoorKey-8x8-v0 --seed 0 --out maps/

For one DoorKey layout (``env.reset(seed=--seed)``) and each of three phases of the task,

* ``no_key``:    the key lies on the floor, the door is locked, the agent carries nothing;
* ``key``:       the agent carries the key (taken off the floor), the door is still locked;
* ``door_open``: the agent carries the key and the door is open,

the agent is put on every cell it can reach in that phase (flood fill from its start cell over the cells it can
stand on: the right room is out of reach until the door opens) facing each of the 4 directions; its 32x32
observation is rendered through the env's own observation wrapper (as in training) and scored against a fixed
set of K goals drawn once from the model's goal buffer (``--n-goals``, default the module's K; the same goals
for every phase):

* intrinsic reward: raw r_gc of eq 13, ``(alpha - h(m_1..m_K)) / delta`` with the module's alpha, h and delta
  (what the agent is paid before the normalisation of eq 14; the normaliser's scale is printed);
* max mastery: ``max_k m(phi(s), phi(g_k))``, how sure the predictor is that some goal is reachable from s.

Both are averaged over the 4 directions and drawn as heatmaps over the grid (walls, objects and unreachable cells
blank), next to a picture of the layout. A second figure shows goals from the buffer above their VAE
reconstructions. Files written to ``--out``: ``curiosity_map.png``, ``vae_reconstructions.png`` and
``curiosity_map.npz`` (the arrays).

On a model trained for a few thousand steps the maps are nearly flat (the predictor has hardly learned); after
training, mastered regions (the start room, often) pay less than the cells beyond the door.
"""

from __future__ import annotations

import argparse
import pathlib
from collections import deque
from typing import Any

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch as th  # noqa: E402
from minigrid.core.world_object import Door, Key  # noqa: E402

import sb3_gocu  # noqa: E402,F401  (registers the GoCu ids)
from sb3_gocu import PPO_GoCu  # noqa: E402
from sb3_gocu.curiosity.reward import curiosity_reward  # noqa: E402

PHASES = ("no_key", "key", "door_open")
PHASE_TITLES = {"no_key": "(a) no key, door locked", "key": "(b) carrying the key, door locked", "door_open": "(c) key, door open"}
DIRECTIONS = 4


# ---------------------------------------------------------------------------------------------- env control
def find_objects(base: Any) -> tuple[Key, tuple[int, int], Door, tuple[int, int]]:
    """The key and the door of a DoorKey grid, with their cells."""
    key = door = None
    for x in range(base.width):
        for y in range(base.height):
            cell = base.grid.get(x, y)
            if isinstance(cell, Key):
                key, key_pos = cell, (x, y)
            elif isinstance(cell, Door):
                door, door_pos = cell, (x, y)
    if key is None or door is None:
        raise ValueError("this env has no key or no door on its grid: the map needs a DoorKey layout")
    return key, key_pos, door, door_pos


def set_phase(base: Any, phase: str, key: Key, key_pos: tuple[int, int], door: Door) -> None:
    """Put the MiniGrid env in one of :data:`PHASES` (as MiniGrid's own pickup/toggle would)."""
    if phase == "no_key":
        base.grid.set(*key_pos, key)
        key.cur_pos = key_pos
        base.carrying = None
        door.is_locked, door.is_open = True, False
    elif phase in ("key", "door_open"):
        base.grid.set(*key_pos, None)
        key.cur_pos = np.array([-1, -1])
        base.carrying = key
        door.is_locked, door.is_open = (True, False) if phase == "key" else (False, True)
    else:
        raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")


def standable(base: Any, x: int, y: int) -> bool:
    cell = base.grid.get(x, y)
    return cell is None or cell.can_overlap()


def reachable_cells(base: Any, start: tuple[int, int]) -> np.ndarray:
    """(height, width) bool mask of the cells reachable from ``start`` over cells the agent can stand on."""
    mask = np.zeros((base.height, base.width), dtype=bool)
    queue = deque([tuple(int(v) for v in start)])
    mask[start[1], start[0]] = True
    while queue:
        x, y = queue.popleft()
        for nx, ny in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)):
            if 0 <= nx < base.width and 0 <= ny < base.height and not mask[ny, nx] and standable(base, nx, ny):
                mask[ny, nx] = True
                queue.append((nx, ny))
    return mask


def observation_wrappers(env: gym.Env) -> list[gym.ObservationWrapper]:
    """The env's observation wrappers, innermost first."""
    chain = []
    e = env
    while isinstance(e, gym.Wrapper):
        if isinstance(e, gym.ObservationWrapper):
            chain.append(e)
        e = e.env
    return chain[::-1]


def render_observation(env: gym.Env) -> np.ndarray:
    """The observation the agent would get in the env's current state: MiniGrid's ``gen_obs()`` passed through
    the env's observation wrappers (for the ``GoCu/DoorKey`` ids, :class:`DoorKeyRGB32`'s 32x32 agent-POV image)."""
    base = env.unwrapped
    if hasattr(base, "last_view"):
        base.last_view = None
    obs = base.gen_obs()
    for wrapper in observation_wrappers(env):
        obs = wrapper.observation(obs)
    return np.asarray(obs)


def to_module_layout(obs: np.ndarray, raw_shape: tuple[int, ...]) -> np.ndarray:
    """Env observations (n, H, W, C) in the module's raw layout (SB3 feeds image policies channel-first)."""
    if obs.shape[1:] == tuple(raw_shape):
        return obs
    if obs.ndim == 4 and tuple(raw_shape) == (obs.shape[3], obs.shape[1], obs.shape[2]):
        return np.ascontiguousarray(obs.transpose(0, 3, 1, 2))
    raise ValueError(f"observations of shape {obs.shape[1:]} do not fit the curiosity module's {tuple(raw_shape)}")


def to_hwc(img: np.ndarray) -> np.ndarray:
    """An image (C, H, W) or (H, W, C) as (H, W, C) for imshow."""
    if img.ndim == 3 and img.shape[0] in (1, 3, 4) and img.shape[-1] not in (1, 3, 4):
        img = img.transpose(1, 2, 0)
    return img[..., 0] if img.shape[-1] == 1 else img


# ---------------------------------------------------------------------------------------------- the map
def sample_goals(module: Any, n_goals: int | None, seed: int) -> np.ndarray:
    """A fixed set of K goals (raw observations) drawn without replacement from the module's goal buffer."""
    size = module.goal_buffer.size
    k = min(module.n_goals if n_goals is None else n_goals, size)
    idx = np.sort(np.random.default_rng(seed).choice(size, size=k, replace=False)) if k else np.zeros(0, dtype=np.int64)
    return module.goal_buffer.observations[:size][idx]


@th.inference_mode()
def score(module: Any, raw_states: np.ndarray, goals: np.ndarray, batch: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Raw r_gc (eq 13) and max mastery of each state against ``goals``."""
    rewards, max_m = [], []
    for i in range(0, len(raw_states), batch):
        chunk = raw_states[i : i + batch]
        if len(goals):
            m = module.mastery(chunk, goals)
            max_m.append(m.max(dim=1).values.numpy())
        else:  # no goal: h = 0 (the module's convention)
            m = th.zeros(len(chunk), 0)
            max_m.append(np.zeros(len(chunk), dtype=np.float32))
        rewards.append(curiosity_reward(m, module.alpha, module.aggregation, module.reward_scale).numpy())
    return np.concatenate(rewards), np.concatenate(max_m)


def phase_observations(env: gym.Env, phase: str, objects: tuple[Key, tuple[int, int], Door, tuple[int, int]]) -> tuple[np.ndarray, list[tuple[int, int]], np.ndarray]:
    """Put the grid in ``phase`` and render the observation at every cell the agent can reach from where it
    stands, facing each direction; the agent is put back where it was (the grid stays in ``phase``).

    :param objects: :func:`find_objects` of the layout, taken before any phase was set (the key leaves the grid)
    :return: reachable mask (height, width), the reachable cells (row-major) and their observations
        (n_cells, 4, H, W, C)
    """
    base = env.unwrapped
    key, key_pos, door, _ = objects
    start_pos = tuple(int(v) for v in base.agent_pos)
    set_phase(base, phase, key, key_pos, door)
    reach = reachable_cells(base, start_pos)
    cells = [(x, y) for y in range(base.height) for x in range(base.width) if reach[y, x]]
    return reach, cells, observations_at(env, cells)


def observations_at(env: gym.Env, cells: list[tuple[int, int]]) -> np.ndarray:
    """The observation at each of ``cells`` facing each direction, in the grid's current state, (n_cells, 4, H, W, C);
    the agent is put back where it was."""
    base = env.unwrapped
    start_pos, start_dir = tuple(int(v) for v in base.agent_pos), int(base.agent_dir)
    obs = np.empty((len(cells), DIRECTIONS, *env.observation_space.shape), dtype=env.observation_space.dtype)
    for i, (x, y) in enumerate(cells):
        for d in range(DIRECTIONS):
            base.agent_pos, base.agent_dir = (x, y), d
            obs[i, d] = render_observation(env)
    base.agent_pos, base.agent_dir = start_pos, start_dir
    return obs


def compute_maps(model: PPO_GoCu, env_id: str = "GoCu/DoorKey-8x8-v0", seed: int = 0, n_goals: int | None = None) -> dict[str, Any]:
    """Intrinsic reward and max-mastery maps of the three phases.

    :return: dict with ``phases`` ({phase: {"reward", "mastery", "masked", "observations", "cells", "layout"}}),
        ``goals`` (the K raw goals), ``alpha``, ``reward_scale``, ``normaliser_std``, ``grid_shape``;
        ``reward`` and ``mastery`` are (height, width) float arrays, NaN exactly where ``masked`` is True
        (walls, objects, unreachable cells), ``observations`` is (n_cells, 4, H, W, C) uint8, one per reachable
        cell (row-major order of ``cells``) and direction
    """
    module = model.curiosity
    if module is None:
        raise ValueError("the model has no curiosity module (not a PPO_GoCu model?)")
    env = gym.make(env_id)
    env.reset(seed=seed)
    base = env.unwrapped
    objects = find_objects(base)
    goals = sample_goals(module, n_goals, seed)
    phases: dict[str, Any] = {}
    for phase in PHASES:
        reach, cells, obs = phase_observations(env, phase, objects)
        layout = base.get_frame(highlight=False, tile_size=16)
        flat = obs.reshape(-1, *obs.shape[2:])
        r, m = score(module, to_module_layout(flat, module.adapter.raw_shape), goals)
        reward = np.full((base.height, base.width), np.nan)
        mastery = np.full((base.height, base.width), np.nan)
        for i, (x, y) in enumerate(cells):
            reward[y, x] = r.reshape(len(cells), DIRECTIONS)[i].mean()
            mastery[y, x] = m.reshape(len(cells), DIRECTIONS)[i].mean()
        phases[phase] = {"reward": reward, "mastery": mastery, "masked": ~reach, "observations": obs, "cells": cells, "layout": layout}
    set_phase(base, "no_key", *objects[:3])
    env.close()
    return {
        "phases": phases,
        "goals": goals,
        "alpha": module.alpha,
        "reward_scale": module.reward_scale,
        "aggregation": module.aggregation,
        "normaliser_std": module.normalizer.std,
        "grid_shape": (base.height, base.width),
        "env_id": env_id,
        "seed": seed,
    }


@th.inference_mode()
def reconstructions(model: PPO_GoCu, n: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` goals from the buffer (spread over it) and their VAE reconstructions, both (n, H, W, C) in [0, 1]."""
    module = model.curiosity
    size = module.goal_buffer.size
    if size == 0:
        data = module.memory.observations[: min(n, module.memory.size)]
    else:
        data = module.goal_buffer.observations[:size][np.linspace(0, size - 1, min(n, size)).round().astype(int)]
    x = module.adapter.to_tensor(data, module.device)
    recon = module.vae.reconstruct(x).cpu().numpy()
    inputs = x.cpu().numpy()
    if module.adapter.is_image:
        inputs, recon = inputs.transpose(0, 2, 3, 1), recon.transpose(0, 2, 3, 1)
    return np.clip(inputs, 0, 1), np.clip(recon, 0, 1)


def draw_maps(maps: dict[str, Any], path: pathlib.Path, fixed_scale: bool = False) -> None:
    """Heatmaps of the three phases. The reward colour scale is shared by the phases and spans the values found
    (``fixed_scale``: the whole range of eq 13, [(alpha - 1) / delta, alpha / delta])."""
    phases = maps["phases"]
    finite = [p["reward"][np.isfinite(p["reward"])] for p in phases.values()]
    values = np.concatenate(finite) if finite else np.zeros(0)
    if fixed_scale or len(values) == 0:
        r_min, r_max = (maps["alpha"] - 1.0) / maps["reward_scale"], maps["alpha"] / maps["reward_scale"]
    else:
        r_min, r_max = float(values.min()), float(values.max())
    if r_max - r_min < 1e-9:
        r_min, r_max = r_min - 1e-4, r_max + 1e-4
    h, w = maps["grid_shape"]
    fig, axes = plt.subplots(len(phases), 3, figsize=(11, 3.6 * len(phases)), dpi=110)
    cmap_r = plt.get_cmap("magma").with_extremes(bad="#d9d9d9")
    cmap_m = plt.get_cmap("viridis").with_extremes(bad="#d9d9d9")
    for row, (phase, p) in enumerate(phases.items()):
        ax = axes[row, 0]
        ax.imshow(p["layout"])
        ax.set_title(PHASE_TITLES[phase], fontsize=10)
        ax.axis("off")
        for col, (name, arr, cmap, vmin, vmax) in enumerate(
            (("intrinsic reward r_gc (raw, eq 13)", p["reward"], cmap_r, r_min, r_max), ("max mastery over the K goals", p["mastery"], cmap_m, 0.0, 1.0)), start=1
        ):
            ax = axes[row, col]
            im = ax.imshow(np.ma.masked_invalid(arr), cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
            ax.set_title(name, fontsize=10)
            ax.set_xticks(range(w))
            ax.set_yticks(range(h))
            ax.tick_params(labelsize=6)
            if w <= 11:
                for y in range(h):
                    for x in range(w):
                        if np.isfinite(arr[y, x]):
                            v = arr[y, x]
                            ax.text(x, y, f"{v:.4f}" if col == 1 else f"{v:.2f}", ha="center", va="center", fontsize=5.5,
                                    color="white" if (v - vmin) / (vmax - vmin + 1e-12) < 0.6 else "black")
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    fig.suptitle(
        f"{maps['env_id']} seed {maps['seed']}: K = {len(maps['goals'])} goals from the buffer, h = {maps['aggregation']}, "
        f"alpha = {maps['alpha']}, delta = {maps['reward_scale']}; mean over 4 directions\n"
        f"(the agent is paid r_gc / {maps['normaliser_std']:.4g}, the std of intrinsic returns, eq 14)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def draw_reconstructions(inputs: np.ndarray, recon: np.ndarray, path: pathlib.Path) -> None:
    n = len(inputs)
    fig, axes = plt.subplots(2, max(n, 1), figsize=(1.4 * max(n, 1), 3.2), dpi=110, squeeze=False)
    for i in range(max(n, 1)):
        for row, imgs in enumerate((inputs, recon)):
            ax = axes[row, i]
            ax.axis("off")
            if i < n:
                ax.imshow(to_hwc(imgs[i]), interpolation="nearest")
    axes[0, 0].set_title("goal (input)", fontsize=8, loc="left")
    axes[1, 0].set_title("VAE reconstruction", fontsize=8, loc="left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def make_curiosity_maps(
    model: PPO_GoCu | str | pathlib.Path,
    env_id: str = "GoCu/DoorKey-8x8-v0",
    seed: int = 0,
    out: str | pathlib.Path = "curiosity_maps",
    n_goals: int | None = None,
    n_reconstructions: int = 8,
    fixed_scale: bool = False,
) -> dict[str, Any]:
    """Compute the maps of a PPO_GoCu model (or a model file) and write the PNGs and the arrays to ``out``.

    :return: :func:`compute_maps`'s dict, with ``files`` (the paths written)
    """
    if not isinstance(model, PPO_GoCu):
        model = PPO_GoCu.load(model, device="cpu")
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    maps = compute_maps(model, env_id, seed, n_goals)
    inputs, recon = reconstructions(model, n_reconstructions, seed)
    files = {"maps": out / "curiosity_map.png", "reconstructions": out / "vae_reconstructions.png", "arrays": out / "curiosity_map.npz"}
    draw_maps(maps, files["maps"], fixed_scale)
    draw_reconstructions(inputs, recon, files["reconstructions"])
    np.savez_compressed(
        files["arrays"],
        **{f"{ph}_{k}": maps["phases"][ph][k] for ph in PHASES for k in ("reward", "mastery", "masked")},
        goals=maps["goals"],
    )
    maps["files"] = files
    maps["reconstruction_inputs"], maps["reconstructions"] = inputs, recon
    return maps


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, help="a PPO_GoCu model file (.zip)")
    p.add_argument("--env", default="GoCu/DoorKey-8x8-v0", help="a GoCu/DoorKey id (same observation as in training)")
    p.add_argument("--seed", type=int, default=0, help="layout seed (env.reset(seed=...)) and seed of the goal draw")
    p.add_argument("--n-goals", type=int, default=None, help="K goals drawn from the buffer (default: the module's n_goals)")
    p.add_argument("--n-reconstructions", type=int, default=8)
    p.add_argument("--out", default="curiosity_maps", help="output directory")
    p.add_argument("--fixed-scale", action="store_true", help="reward colours over the whole range of eq 13, not the values found")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    args = p.parse_args(argv)
    th.set_num_threads(args.threads)
    maps = make_curiosity_maps(args.model, args.env, args.seed, args.out, args.n_goals, args.n_reconstructions, args.fixed_scale)
    for phase, ph in maps["phases"].items():
        print(
            f"{phase:10s} {len(ph['cells']):3d} cells  r_gc {np.nanmin(ph['reward']):.4f} .. {np.nanmax(ph['reward']):.4f} "
            f"(mean {np.nanmean(ph['reward']):.4f})  max mastery {np.nanmin(ph['mastery']):.3f} .. {np.nanmax(ph['mastery']):.3f}"
        )
    for f in maps["files"].values():
        print(f"wrote {f}")
    return maps


if __name__ == "__main__":
    main()
