"""How the training thread sends its messages to the scoring process: written at once when the pipe has room
(the default) against always handed to the writer thread (as before 5d8efba), in one process, same seed.

    python benchmarks/scoring_messages.py --timesteps 40960 --repeats 2

Each repeat trains PPO_GoCu on DoorKey-8x8 from scratch (paper settings, 16 envs, 1 torch thread) once each way,
the order alternating, and prints the wall time, the training thread's time in ``_Writer.send`` (the call that
hands a message over), how many messages went each way, and a hash of the trained weights (the same both ways:
only the I/O path differs).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from typing import Any

import torch as th
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import PPO_GoCu
from sb3_gocu.curiosity import scoring

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from throughput import PPO_SETTINGS, weights_hash  # noqa: E402


def one_run(env_id: str, timesteps: int, seed: int, direct: bool) -> dict[str, Any]:
    """Train once; ``direct=False`` makes every message go through the writer thread."""
    room, send = scoring._pipe_room, scoring._Writer.send
    spent = {"send_s": 0.0, "messages": 0}

    def timed_send(self: Any, payload: bytes) -> None:
        t0 = time.perf_counter()
        send(self, payload)
        spent["send_s"] += time.perf_counter() - t0
        spent["messages"] += 1

    scoring._Writer.send = timed_send  # type: ignore[method-assign]
    if not direct:
        scoring._pipe_room = lambda fd: 0  # no room, as far as the writer knows: the thread writes everything
    try:
        venv = make_vec_env(env_id, n_envs=16, seed=seed)
        model = PPO_GoCu("CnnPolicy", venv, seed=seed, **PPO_SETTINGS)
        t0 = time.perf_counter()
        model.learn(timesteps)
        total = time.perf_counter() - t0
        process = model.curiosity._process
        out = {"direct": direct, "total_s": total, **spent, "written_by_caller": process._send.direct if process else 0,
               "weights": weights_hash(model)}
        if process is not None:
            process.close()
        return out
    finally:
        scoring._pipe_room, scoring._Writer.send = room, send


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="GoCu/DoorKey-8x8-v0")
    parser.add_argument("--timesteps", type=int, default=40960)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    print(f"command: python benchmarks/scoring_messages.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, 1 torch thread, seed {args.seed}")
    rows = []
    for rep in range(args.repeats):
        for direct in ((True, False) if rep % 2 == 0 else (False, True)):
            rows.append(one_run(args.env, args.timesteps, args.seed, direct))
            r = rows[-1]
            print(f"direct writes {str(direct):5s}  total {r['total_s']:7.1f} s  in send {r['send_s']:6.2f} s  "
                  f"messages {r['messages']:6d}  written by the caller {r['written_by_caller']:6d}  weights {r['weights']}")
    for direct in (True, False):
        mine = [r for r in rows if r["direct"] == direct]
        print(f"mean, direct writes {str(direct):5s}: total {sum(r['total_s'] for r in mine) / len(mine):7.1f} s, "
              f"in send {sum(r['send_s'] for r in mine) / len(mine):6.2f} s")
    return rows


if __name__ == "__main__":
    main()
