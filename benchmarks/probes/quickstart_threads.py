"""The quickstart with torch's default thread count against one thread set by the caller, in one process, alternating.

    python benchmarks/probes/quickstart_threads.py --timesteps 100000 --pairs 2

``PPO_GoCu.learn`` trains with one torch thread on a CPU and gives the caller's count back, so a user who never calls
``torch.set_num_threads`` should take no longer than one who sets 1. Prints each run's wall time, the ratio, the
thread count before and after each run, the command and the CPU.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch as th

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "examples"))
import quickstart  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))  # run_records (benchmarks/)
from run_records import cpu_model  # noqa: E402


def main(argv: list[str] | None = None) -> list[dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--timesteps", type=int, default=100_000)
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--pairs", type=int, default=2)
    parser.add_argument("--save", default="/tmp/gocu_quickstart_threads")
    args = parser.parse_args(argv)
    default = th.get_num_threads()
    print(f"command: python {' '.join(sys.argv if argv is None else [__file__, *argv])}")
    print(f"CPU: {cpu_model()}, {os.cpu_count()} CPUs; torch {th.__version__}, default thread count {default}")
    rows = []
    for pair in range(args.pairs):
        order = ("default", "one") if pair % 2 == 0 else ("one", "default")
        for setting in order:
            th.set_num_threads(1 if setting == "one" else default)
            before = th.get_num_threads()
            t0 = time.perf_counter()
            quickstart.main(["--timesteps", str(args.timesteps), "--eval-episodes", str(args.eval_episodes), "--save", args.save])
            rows.append({"pair": pair, "setting": setting, "threads_before": before, "threads_after": th.get_num_threads(),
                         "seconds": time.perf_counter() - t0})
            print(f"pair {pair} {setting:8s} threads {before} -> {rows[-1]['threads_after']}  {rows[-1]['seconds']:7.1f} s", flush=True)
    th.set_num_threads(default)
    for pair in range(args.pairs):
        t = {r["setting"]: r["seconds"] for r in rows if r["pair"] == pair}
        print(f"pair {pair}: default / one thread = {t['default'] / t['one']:.3f}")
    return rows


if __name__ == "__main__":
    main()
