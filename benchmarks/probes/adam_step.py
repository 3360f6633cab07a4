"""Adam's optimiser step for the 5x512 mastery predictor: SB3-style default (for-loop), ``foreach`` and the fused
CPU kernel, timed and compared to the bit with the default.

    python benchmarks/probes/adam_step.py --steps 50

The predictor's updates take one Adam step per minibatch (128 per update with the defaults). The fused kernel is
much faster, but its weights differ from the default step's in the last bits, so using it would make every seeded
run another draw (docs/results.md, "What a step costs"). 1 torch thread.
"""

from __future__ import annotations

import argparse
import copy
import os
import platform
import time

import torch as th


def run(net: th.nn.Module, steps: int, **adam_kwargs) -> tuple[th.nn.Module, float]:
    """``steps`` Adam steps on seeded random gradients; the network and the mean seconds per step."""
    net = copy.deepcopy(net)
    opt = th.optim.Adam(net.parameters(), lr=5e-4, **adam_kwargs)
    gen = th.Generator().manual_seed(1)
    total = 0.0
    for _ in range(steps):
        for p in net.parameters():
            p.grad = th.randn(p.shape, generator=gen)
        t0 = time.perf_counter()
        opt.step()
        total += time.perf_counter() - t0
    return net, total / steps


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    th.manual_seed(0)
    net = th.nn.Sequential(th.nn.Linear(256, 512), *[th.nn.Linear(512, 512) for _ in range(4)], th.nn.Linear(512, 2))
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {th.__version__}, 1 thread; "
          f"{sum(p.numel() for p in net.parameters()):,} parameters, {args.steps} steps")
    base, base_s = run(net, args.steps)
    rows = [{"kind": "default", "ms_per_step": base_s * 1e3, "same_as_default": True}]
    for kind, kwargs in (("foreach", {"foreach": True}), ("fused", {"fused": True})):
        other, s = run(net, args.steps, **kwargs)
        rows.append({"kind": kind, "ms_per_step": s * 1e3,
                     "same_as_default": all(th.equal(a, b) for a, b in zip(base.parameters(), other.parameters()))})
    for r in rows:
        print(f"{r['kind']:8s} {r['ms_per_step']:6.2f} ms per step   same weights as the default: {r['same_as_default']}")
    return rows


if __name__ == "__main__":
    main()
