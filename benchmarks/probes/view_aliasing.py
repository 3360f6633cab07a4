"""How much of what the agent sees beyond the door it has already seen before opening it, on DoorKey.

    python benchmarks/probes/view_aliasing.py --envs GoCu/DoorKey-8x8-v0 GoCu/DoorKey-16x16-v0 --layouts 20

GoCu's curiosity works on observations: a state pays only if its image (through the VAE) is unlike the goals'
images. On DoorKey the agent sees a 7x7 egocentric view, and in a large room most views are floor and wall only, the
same pixels wherever the agent stands. For each layout (``env.reset(seed=i)``, i < ``--layouts``) this script
renders the view of every cell the agent can stand on, facing each of the 4 directions, in two phases (the
key carried with the door locked: the left room; the door open: both rooms) and counts the right-room
views that are byte-identical to a left-room view

* of the same layout (what the agent could have seen in this episode before opening the door), and
* of any of the layouts (what it could have seen in earlier episodes).

An identical view has the same embedding and the same reward as the left-room view it repeats: beyond the door
there is nothing new to find in it. No training, no model: env rendering only (a few seconds per layout).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

import sb3_gocu  # noqa: F401  (registers the GoCu ids)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
import curiosity_map  # noqa: E402  (phases, flood fill and rendering of examples/curiosity_map.py)


def phase_views(env: gym.Env, phase: str, objects: tuple) -> dict[tuple[int, int, int], bytes]:
    """:func:`curiosity_map.phase_observations` as bytes, keyed by (x, y, direction)."""
    _, cells, obs = curiosity_map.phase_observations(env, phase, objects)
    return {(x, y, d): obs[i, d].tobytes() for i, (x, y) in enumerate(cells) for d in range(curiosity_map.DIRECTIONS)}


def aliasing(env_id: str, layouts: int) -> dict[str, float]:
    """Fractions of right-room views identical to a left-room view (same layout: mean, min, max over layouts;
    any layout: pooled), and the mean number of right-room views per layout."""
    same, pooled_left, right_all = [], set(), []
    for seed in range(layouts):
        env = gym.make(env_id)
        env.reset(seed=seed)
        objects = curiosity_map.find_objects(env.unwrapped)
        door_x = objects[3][0]
        left = set(phase_views(env, "key", objects).values())
        right = [v for (x, _, _), v in phase_views(env, "door_open", objects).items() if x > door_x]
        env.close()
        same.append(float(np.mean([v in left for v in right])))
        pooled_left |= left
        right_all += right
    return {
        "same_layout_mean": float(np.mean(same)),
        "same_layout_min": float(np.min(same)),
        "same_layout_max": float(np.max(same)),
        "any_layout": float(np.mean([v in pooled_left for v in right_all])),
        "right_views_per_layout": len(right_all) / layouts,
    }


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--envs", nargs="+", default=["GoCu/DoorKey-8x8-v0", "GoCu/DoorKey-16x16-v0"], help="DoorKey ids")
    p.add_argument("--layouts", type=int, default=20, help="layouts per env: env.reset(seed=0..layouts-1)")
    args = p.parse_args(argv)
    if args.layouts < 1:
        p.error(f"--layouts must be >= 1, got {args.layouts}")
    print("command: python benchmarks/probes/view_aliasing.py " + " ".join(sys.argv[1:] if argv is None else argv))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; layouts reset(seed=0..{args.layouts - 1})")
    results = {}
    for env_id in args.envs:
        r = results[env_id] = aliasing(env_id, args.layouts)
        print(
            f"{env_id}: {r['right_views_per_layout']:.0f} right-room views per layout (cells x 4 directions); identical to a "
            f"left-room view of the same layout: {r['same_layout_mean']:.0%} (min {r['same_layout_min']:.0%}, max "
            f"{r['same_layout_max']:.0%}); to a left-room view of any of the {args.layouts} layouts: {r['any_layout']:.0%}"
        )
    return results


if __name__ == "__main__":
    main()
