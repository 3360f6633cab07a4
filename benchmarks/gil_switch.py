"""Why PPO_GoCu shortens the GIL switch interval during a rollout: the wall time of one scoring call in a worker
thread while the main thread runs pure Python (as env stepping does), at several switch intervals.

    python benchmarks/gil_switch.py --intervals 0.005 0.0005 0.0001 --states 3

The worker scores ``--states`` states against K = 50 goals with the folded 5x512 predictor (the module's hot path);
each of its tensor operations releases the GIL and must get it back from the busy main thread, which Python grants
only after the switch interval. Prints the mean wall and CPU time per call, alone and beside the busy thread.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import threading
import time

import numpy as np
import torch as th

from sb3_gocu.curiosity.networks import MasteryPredictor


def score_times(folded, phi: th.Tensor, goal_parts: th.Tensor, calls: int, busy: bool) -> tuple[float, float]:
    """Mean (wall, cpu) seconds of one scoring call in a worker thread, the main thread busy in Python or idle."""
    times: list[tuple[float, float]] = []

    def worker() -> None:
        with th.inference_mode():
            for _ in range(calls):
                c0, w0 = time.thread_time(), time.perf_counter()
                folded.mastery_from_parts(folded.state_part(phi), goal_parts)
                times.append((time.perf_counter() - w0, time.thread_time() - c0))

    thread = threading.Thread(target=worker)
    thread.start()
    while busy and thread.is_alive():
        sum(range(1000))  # pure Python, as MiniGrid's step is
    thread.join()
    a = np.array(times)
    return float(a[:, 0].mean()), float(a[:, 1].mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--intervals", type=float, nargs="+", default=[0.005, 0.0005, 0.0001])
    parser.add_argument("--states", type=int, default=3, help="states per scoring call (about 3 per env step on DoorKey-8x8)")
    parser.add_argument("--calls", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    print(f"command: {' '.join([os.path.basename(sys.executable)] + sys.argv)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, torch threads 1, seed {args.seed}")
    folded = MasteryPredictor(128).eval().fold()
    phi = th.randn(args.states, 128)
    goal_parts = folded.goal_part(th.randn(args.states, 50, 128))
    default = sys.getswitchinterval()
    wall, cpu = score_times(folded, phi, goal_parts, args.calls, busy=False)
    print(f"main thread idle:                       wall {wall * 1e3:6.2f} ms  cpu {cpu * 1e3:6.2f} ms per call")
    for interval in args.intervals:
        sys.setswitchinterval(interval)
        wall, cpu = score_times(folded, phi, goal_parts, args.calls, busy=True)
        print(f"main thread in Python, interval {interval * 1e3:5.2f} ms: wall {wall * 1e3:6.2f} ms  cpu {cpu * 1e3:6.2f} ms per call")
    sys.setswitchinterval(default)


if __name__ == "__main__":
    main()
