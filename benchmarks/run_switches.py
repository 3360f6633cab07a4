"""What a benchmark run changes in its model on purpose: r_gc replaced (the ablations' constant r_gc and the learning
test's broken variants; not library settings), and a resumed DQN's gradient steps held until its replay buffer,
which checkpoints leave out, has refilled."""

from __future__ import annotations

from typing import Any

import numpy as np

from run_settings import CURIOUS
from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.reward import revisit_factor

#: how ``replace_curiosity`` replaces r_gc (ablations and the learning test's broken variants; not library settings)
REPLACEMENTS = ("constant", "zero", "negative")


def replace_curiosity(module: GoalCuriosityModule | None, how: str) -> None:
    """Ablation, not a library setting: every state's r_gc, as the module commits it, replaced by ``how``:
    ``"constant"`` the running mean of the r_gc the module computed so far (over the visits the revisit rule pays),
    so what remains of the curiosity is the revisit rule and the normalisation (``--constant-curiosity``);
    ``"zero"``; ``"negative"`` its negative. The module computes and trains as before; the ``gocu_raw_reward`` a step
    reports is the replacement times the revisit factor. The running mean lives in this process: a resumed run
    starts it afresh."""
    if how not in REPLACEMENTS:
        raise ValueError(f"how must be one of {REPLACEMENTS}, got {how!r}")
    if module is None:
        raise SystemExit(f"replacing r_gc applies to the curious algos {CURIOUS}")
    score = module.scorer.score
    sums = [0.0, 0.0]  # sum of the paid r_gc, visits paid

    def score_replaced(raw: Any, env_indices: np.ndarray, keys: list[bytes], *args: Any) -> tuple[np.ndarray, np.ndarray]:
        rewards, phi = score(raw, env_indices, keys, *args)  # the episode memos keep the true values
        if how == "zero":
            return np.zeros_like(rewards), phi
        if how == "negative":
            return -rewards, phi
        decay = module.config.revisit_decay
        paid = np.ones(len(rewards))  # the revisit factor this step will pay (the module counts the visit after scoring)
        if decay != "none":
            visits = np.array([module.episodes.visits[e].get(k, 0) + 1 for e, k in zip(env_indices, keys)])
            paid = revisit_factor(visits, decay).astype(np.float64)
        values = rewards.astype(np.float64)
        finite = np.isfinite(values)
        if module.recording:
            sums[0] += float((values * paid)[finite].sum())
            sums[1] += float(paid[finite].sum())
        mean = sums[0] / sums[1] if sums[1] > 0 else float(np.mean(values[finite])) if finite.any() else 0.0
        return np.full(len(rewards), mean, dtype=np.float32), phi

    module.scorer.score = score_replaced


def refill_before_training(model: Any) -> None:
    """A resumed DQN's replay buffer starts empty: its gradient steps wait until the buffer again holds
    ``learning_starts`` transitions, while the agent keeps acting with its own (epsilon-greedy) policy."""
    train = model.train

    def train_once_refilled(gradient_steps: int, batch_size: int = 100) -> None:
        if model.replay_buffer.size() * model.n_envs >= model.learning_starts:
            train(gradient_steps, batch_size)

    model.train = train_once_refilled
