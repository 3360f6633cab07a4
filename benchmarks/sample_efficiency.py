"""Sample efficiency of PPO_GoCu against plain PPO: learning curves over several seeds, resumable.

    python benchmarks/sample_efficiency.py --env GoCu/DoorKey-8x8-v0 --timesteps 800000 --seeds 0 1 2 \\
        --out benchmarks/out/doorkey8
    python benchmarks/sample_efficiency.py --out benchmarks/out/doorkey8 --summary-only
    python benchmarks/plot_curves.py benchmarks/out/doorkey8

Both algorithms get the paper's PPO settings (16 envs, n_steps 128, batch 256, 4 epochs, lr 1e-4, ent 0.01,
gamma 0.99, vf 0.5, clip 0.2) and the paper's CNN (plain PPO: ``features_extractor_class=PaperCNN``;
PPO_GoCu's CnnPolicy picks it itself). PPO_GoCu uses the module's defaults (the paper's settings) unless
``--goal-strategy``, ``--n-goals`` or ``--curiosity-kwargs`` say otherwise. The paper's other learners (Fig. 6):
``a2c`` / ``dqn`` take the settings of ``sb3_gocu/hyperparams/<a2c|dqn>.yml`` for the env (the zoo launcher's files),
``a2c_sum`` / ``dqn_sum`` the same on ``GoCuVecEnvWrapper(mode="sum")`` with ``GoCuCallback``.

Atari (``--zoo``, the default for ``ALE/...`` ids): ``ppo`` and ``ppo_gocu`` are built as the zoo launcher builds them
from ``sb3_gocu/hyperparams/<algo>.yml`` (AtariWrapper, 4 stacked frames, 8 envs, the schedules, sigma and the
curiosity settings of the file; ``--curiosity-kwargs``, ``--goal-strategy`` and ``--n-goals`` are merged into the
file's ``curiosity_kwargs``; ``--n-envs``, ``--n-steps``, ``--batch-size`` and ``--intrinsic-coef`` do not apply), and the
summary adds Table 3's measures: the best 100-episode mean return, the best episode return and the rooms visited::

    python benchmarks/sample_efficiency.py --env ALE/MontezumaRevenge-v5 --algos ppo ppo_gocu --seeds 0 1 \\
        --timesteps 5000000 --checkpoint-freq 200000 --out benchmarks/out/atari/montezuma

Runs execute one at a time (seed-major: seed 0 of every algo, then seed 1, ...), each writing
``<out>/<algo>_seed<seed>.csv`` with one row per rollout end (A2C's and DQN's rollouts are shorter: one row at the
first rollout end past each multiple of a PPO rollout's steps, ``--n-envs`` x ``--n-steps``):

* ``steps``: env steps so far (all envs); ``episodes``: episodes finished so far;
* ``window_episodes``: episodes in the return window (at most ``--window``, 100);
* ``mean_return``: mean extrinsic return of the last ``--window`` episodes (Monitor's returns: the
  GoCu wrapper sits above Monitor, so they are extrinsic); ``success_rate``: fraction of them with return > 0;
* ``key_rate`` / ``door_rate`` (DoorKey ids, from ``info["task_phase"]``): fraction of the same episodes in which
  the agent picked up the key / opened the door, a measure of exploration that moves before the return does;
* ``final_distance`` / ``final_success``: over the same episodes, the mean of ``info["distance"]`` at their last step
  (the Sawyer and MuJoCo ids: Table 2's final distance) and the fraction whose last step has ``info["is_success"]``;
  empty where the env reports neither;
* ``max_return``: the best episode return so far; ``rooms_mean`` / ``rooms_total`` (where the env reports
  ``info["room"]``: Montezuma's Revenge through ``sb3_gocu.RoomInfoWrapper``): rooms visited per episode over the same
  episodes, and distinct rooms visited so far (the exploration measures of ``sb3_gocu.ExplorationCallback``, kept in
  the checkpoint so that a resumed run continues its counts);
* ``intrinsic_mean`` / ``intrinsic_std``: mean and std of the raw r_gc (eq 13, ``infos["gocu_raw_reward"]``)
  over the rollout's steps, ``intrinsic_norm_mean``: mean of the normalised r_gc (eq 14), ``goals``: goals in the
  goal buffer; empty for PPO; for ppo_rnd the intrinsic columns are RND's raw and normalised reward;
* ``predictor_auc_far`` / ``predictor_auc_goals``: the held-out AUCs of the last predictor update (near goals against
  far ones of the same episode / against goals of the buffer; ``GoalCuriosityModule.pop_reward_stats``);
* ``wall_time_s``: training wall time of the run so far (summed over the resumed parts; the time between
  the last checkpoint and a crash is not counted, those steps are redone); ``fps``: steps/s of that rollout (PPO: its
  collection, the update excluded; A2C and DQN: the steps since the previous row, their updates included).

Checkpoints. Every ``--checkpoint-freq`` env steps (at the start of the next rollout, after the PPO update
and the curiosity update, where the whole training state is consistent) and at the end, the run writes
``<out>/checkpoints/<algo>_seed<seed>/model_<steps>.zip`` (the model; PPO_GoCu's carries the curiosity
module's whole state and the global RNG states) and then ``state_<steps>.json`` (the CSV rows so far, the
episode-return window, the wall time, the run's configuration), each atomically (temporary file, fsync,
``os.replace``); the ``--keep-checkpoints`` (2) newest pairs are kept (about 90 MB each for PPO_GoCu with
the paper's settings, 6 MB for PPO). Run the same command again after a crash and each run
continues from its newest complete checkpoint (``load(..., env=...)`` + ``learn(..., reset_num_timesteps=False)``)
and finished runs are skipped; a larger ``--timesteps`` extends finished runs. On resumption the envs are
fresh (seeded with ``seed + steps``): episodes in progress at the checkpoint are not finished, so the
continuation is statistically, not bit-for-bit, the uninterrupted run; a resumed DQN run starts with an empty replay
buffer (not checkpointed: ~600 MB) and makes no gradient step until it holds ``learning_starts`` transitions again (the
agent acting with its own policy meanwhile). A checkpoint written with other
settings (env, n_envs, PPO or curiosity settings) is refused; ``--restart`` discards it.

Stopping once solved. With ``--stop-at-threshold`` a run ends at the first rollout end where it reaches the
threshold as the summary counts it (below): PPO's update on that rollout is still made, the checkpoint is written
at the start of the next rollout (where the training state is consistent) and marked ``stopped_at_threshold``,
and the run stops at that rollout's first step (one vector step is taken and discarded; the CSV ends at the row
that reached the threshold). A later command with the flag skips any run whose rows reach the threshold; one
without it continues the run from its newest checkpoint to ``--timesteps``.

The summary (printed and written to ``<out>/summary.md``) gives per algo the env steps to a mean return of
``--threshold`` (0.9: the first rollout end where the last-100 mean is >= 0.9, counted only once the window
holds ``--min-window`` episodes) and the final success rate, as mean +- std over seeds, with the command,
seeds, machine and threads. ``--summary-only`` re-summarises the CSVs in ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import pathlib
import re
import shlex
import shutil
import sys
import time
from collections import deque
from typing import Any, Sequence

import numpy as np
import torch as th
from stable_baselines3 import A2C, DQN, PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import sb3_gocu  # noqa: F401  (registers the GoCu ids)
from sb3_gocu import ExplorationCallback, GoCuCallback, GoCuVecEnvWrapper, PaperCNN, PPO_GoCu
from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.goals import GOAL_STRATEGIES
from sb3_gocu.curiosity.reachability import QUALITY_KEYS
from sb3_gocu.wrappers import find_gocu_module

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from peers.rnd import PPO_RND  # noqa: E402
from run_settings import (  # noqa: E402, F401  (re-exported, as above)
    CURIOUS,
    HYPERPARAMS,
    N_ENVS,
    PPO_SETTINGS,
    SUM_ALGOS,
    ZOO_KEYS,
    curiosity_kwargs,
    model_settings,
    ppo_settings,
    run_config,
    zoo_entry,
    zoo_overrides,
    zoo_settings,
)
from throughput import zoo_manager  # noqa: E402
from run_switches import REPLACEMENTS, refill_before_training, replace_curiosity  # noqa: E402, F401  (re-exported)
from run_records import (  # noqa: E402, F401  (re-exported: ablations.py, the probes and the tests use them from here)
    COLUMNS,
    atomic_write_bytes,
    csv_bytes,
    list_checkpoints,
    machine_line,
    model_readable,
    read_csv,
    recorded,
    run_name,
    steps_to_threshold,
    wall_time_to_threshold,
    summarize,
)

#: ppo: plain PPO; ppo_gocu: PPO_GoCu (two value heads); ppo_sum: plain PPO (one value head) on
#: ``GoCuVecEnvWrapper(mode="sum")`` with ``GoCuCallback``, the drop-in pipeline; ppo_rnd: PPO_GoCu's PPO with RND
#: as its intrinsic reward (``benchmarks/peers/rnd.py``); a2c / dqn: plain SB3 A2C / DQN with the settings of
#: ``sb3_gocu/hyperparams/<a2c|dqn>.yml`` (the paper's Fig. 6); a2c_sum / dqn_sum: the same on the drop-in pipeline
ALGOS = ("ppo", "ppo_gocu", "ppo_sum", "ppo_rnd", "a2c", "a2c_sum", "dqn", "dqn_sum")
MODEL_CLASSES: dict[str, type] = {
    "ppo": PPO, "ppo_gocu": PPO_GoCu, "ppo_sum": PPO, "ppo_rnd": PPO_RND, "a2c": A2C, "a2c_sum": A2C, "dqn": DQN, "dqn_sum": DQN,
}


# ---------------------------------------------------------------------------------------------- the run
class SampleEfficiencyCallback(BaseCallback):
    """Records one CSV row per rollout end and writes checkpoints at rollout starts.

    :param run: the :class:`Run` it reports to
    """

    def __init__(self, run: "Run") -> None:
        super().__init__(0)
        self.run = run
        self._sum = self._sq = self._norm = 0.0
        self._count = 0
        self._infos: list[list[dict]] = []
        self._t_rollout = time.perf_counter()
        self._steps_rollout = 0
        self._stop = False
        self._fresh = True  # the next rollout starts a new row's figures
        self._next_row = 0

    def _on_training_start(self) -> None:
        self._next_row = (self.num_timesteps // self.run.row_every + 1) * self.run.row_every

    def _on_rollout_start(self) -> None:
        run = self.run
        if run.reached_at is not None:  # --stop-at-threshold: the update on that rollout is made; stop here
            run.stopped_at_threshold = run.reached_at
            run.checkpoint(self.model)
            self._stop = True
            return
        if self.num_timesteps - run.last_checkpoint >= run.checkpoint_freq:
            run.checkpoint(self.model)
        if self._fresh:
            self._fresh = False
            self._sum = self._sq = self._norm = 0.0
            self._count = 0
            self._t_rollout = time.perf_counter()
            self._steps_rollout = self.num_timesteps

    def _on_step(self) -> bool:
        if self._stop:
            return False
        infos = self.locals["infos"]
        for info in infos:
            ep = info.get("episode")
            if ep is not None:  # Monitor's end of a whole episode (a whole game on Atari)
                self.run.add_episode(float(ep["r"]), info.get("task_phase"), info.get("distance"), info.get("is_success"))
        self._infos.append(infos)  # read at the rollout's end
        return True

    def _on_rollout_end(self) -> None:
        for infos in self._infos:
            for info in infos:
                raw = info.get("gocu_raw_reward", info.get("rnd_raw_reward"))
                if raw is not None:
                    self._sum += raw
                    self._sq += raw * raw
                    self._norm += info.get("gocu_reward", float("nan"))
                    self._count += 1
        self._infos = []
        if self.num_timesteps < self._next_row:  # A2C's and DQN's rollouts are short: one row per PPO rollout's steps
            return
        self._next_row = (self.num_timesteps // self.run.row_every + 1) * self.run.row_every
        self._fresh = True
        if self._count:
            mean = self._sum / self._count
            std = math.sqrt(max(0.0, self._sq / self._count - mean * mean))
            norm = self._norm / self._count
        else:
            mean = std = norm = float("nan")
        dt = time.perf_counter() - self._t_rollout
        module = self.run.module(self.model)
        goals = module.goal_buffer.size if module is not None else float("nan")
        quality = {k: module.stats.get(k, float("nan")) if module is not None else float("nan") for k in QUALITY_KEYS}
        self.run.add_row(self.num_timesteps, mean, std, norm, (self.num_timesteps - self._steps_rollout) / max(dt, 1e-9), goals, quality)


class Run:
    """One (algo, seed) run: builds or resumes the model, trains it, keeps its CSV and checkpoints."""

    def __init__(self, args: argparse.Namespace, algo: str, seed: int, command: str) -> None:
        self.args = args
        self.algo = algo
        self.seed = seed
        self.command = command
        self.name = run_name(algo, seed)
        self.out = pathlib.Path(args.out)
        self.csv_path = self.out / f"{self.name}.csv"
        self.ckpt_dir = self.out / "checkpoints" / self.name
        #: with --zoo: the zoo file's entry for the env (its settings build the env and the model)
        self.zoo = zoo_entry(algo, args.env) if args.zoo else None
        rollout = self.zoo["n_envs"] * self.zoo["n_steps"] if self.zoo else args.n_envs * args.n_steps
        #: env steps between CSV rows: a PPO rollout (a row at every rollout end of PPO; at the first rollout end past
        #: each multiple for A2C's and DQN's shorter rollouts)
        self.row_every = rollout
        # checkpoints happen at rollout boundaries
        self.checkpoint_freq = max(rollout, int(math.ceil(args.checkpoint_freq / rollout)) * rollout)
        self.config = run_config(args, algo, seed)
        self.rows: list[dict[str, Any]] = []
        self.window: deque = deque(maxlen=args.window)
        self.phases: deque = deque(maxlen=args.window)  # info["task_phase"] at episode ends (DoorKey ids)
        self.finals: deque = deque(maxlen=args.window)  # (info["distance"], info["is_success"]) at episode ends
        #: rooms visited per episode and in total (info["room"], Montezuma's Revenge) and the best episode return
        self.exploration = ExplorationCallback(window=args.window)
        self.episodes = 0
        self.wall_before = 0.0
        self.process_start = time.perf_counter()
        self.last_checkpoint = 0
        self.resumed_from: list[int] = []
        self.commands: list[str] = [command]
        self.done = False
        #: with --stop-at-threshold: the rollout end where the run reached the threshold (in this process)
        self.reached_at: int | None = None
        #: the step at which this process stopped the run by --stop-at-threshold (written into its checkpoint; a
        #: resumption decides from the rows, so it does not read it back)
        self.stopped_at_threshold: int | None = None

    # ------------------------------------------------------------ recording
    def add_episode(self, ret: float, phase: int | None = None, distance: float | None = None, success: bool | None = None) -> None:
        self.window.append(ret)
        if phase is not None:
            self.phases.append(int(phase))
        if distance is not None or success is not None:
            self.finals.append((float("nan") if distance is None else float(distance), float("nan") if success is None else float(success)))
        self.episodes += 1

    def wall_time(self) -> float:
        return self.wall_before + time.perf_counter() - self.process_start

    def add_row(
        self, steps: int, intrinsic_mean: float, intrinsic_std: float, intrinsic_norm: float, fps: float, goals: float = float("nan"),
        quality: dict[str, float] | None = None,
    ) -> None:
        w = np.asarray(self.window, dtype=np.float64)
        ph = np.asarray(self.phases, dtype=np.int64)
        finals = np.asarray(self.finals, dtype=np.float64).reshape(-1, 2)
        explored = self.exploration
        row = {
            "algo": self.algo,
            "seed": self.seed,
            "steps": int(steps),
            "episodes": self.episodes,
            "window_episodes": len(w),
            "mean_return": float(w.mean()) if len(w) else float("nan"),
            "success_rate": float((w > 0).mean()) if len(w) else float("nan"),
            "key_rate": float((ph >= 1).mean()) if len(ph) else float("nan"),
            "door_rate": float((ph >= 2).mean()) if len(ph) else float("nan"),
            "final_distance": float(np.mean(finals[:, 0])) if len(finals) else float("nan"),
            "final_success": float(np.mean(finals[:, 1])) if len(finals) else float("nan"),
            "max_return": explored.max_return if np.isfinite(explored.max_return) else float("nan"),
            "rooms_mean": float(np.mean(explored.episode_rooms)) if explored.episode_rooms else float("nan"),
            "rooms_total": len(explored.rooms) if explored.rooms else float("nan"),
            "intrinsic_mean": intrinsic_mean,
            "intrinsic_std": intrinsic_std,
            "intrinsic_norm_mean": intrinsic_norm,
            "goals": goals,
            **{k: (quality or {}).get(k, float("nan")) for k in QUALITY_KEYS},
            "wall_time_s": self.wall_time(),
            "fps": fps,
        }
        self.rows.append(row)
        if self.args.stop_at_threshold and steps_to_threshold([row], self.args.threshold, self.args.min_window) is not None:
            self.reached_at = int(steps)
        # the live CSV (for watching a run); the checkpoint's copy is the one a resumption trusts
        atomic_write_bytes(self.csv_path, csv_bytes(self.rows))
        n_rollouts = len(self.rows)
        if self.args.verbose and (n_rollouts % self.args.print_every == 0 or steps >= self.args.timesteps):
            print(
                f"[{self.name}] {steps:>9d}/{self.args.timesteps} steps  {self.episodes:6d} episodes  "
                f"mean return {row['mean_return']:.3f}  success {row['success_rate']:.2f}  "
                + (f"rooms {row['rooms_mean']:.1f} (total {len(explored.rooms)})  best {explored.max_return:g}  " if explored.rooms
                   else f"key {row['key_rate']:.2f}  door {row['door_rate']:.2f}  ")
                + f"r_gc {intrinsic_mean:.4f}  {fps:5.0f} steps/s  {row['wall_time_s'] / 60:6.1f} min",
                flush=True,
            )

    # ------------------------------------------------------------ checkpoints
    def state(self, steps: int) -> dict[str, Any]:
        return {
            "config": self.config,
            "steps": int(steps),
            "episodes": self.episodes,
            "window": list(self.window),
            "phases": list(self.phases),
            "finals": [list(f) for f in self.finals],
            **self.exploration.state_dict(),  # episode_rooms, rooms, max_return
            "wall_time_s": self.wall_time(),
            "rows": self.rows,
            "resumed_from": self.resumed_from,
            "done": self.done,
            "stopped_at_threshold": self.stopped_at_threshold,
            "commands": self.commands,
            "machine": machine_line(self.args.threads),
        }

    def checkpoint(self, model: Any) -> None:
        steps = int(model.num_timesteps)
        t0 = time.perf_counter()
        buf = io.BytesIO()
        model.save(buf, exclude=["train"] if "train" in vars(model) else None)  # refill_before_training's gate stays out
        atomic_write_bytes(self.ckpt_dir / f"model_{steps}.zip", buf.getvalue())
        if self.algo in SUM_ALGOS:  # a plain SB3 model file does not hold the wrapper's curiosity module
            module_buf = io.BytesIO()
            th.save(self.module(model).state_dict(), module_buf)
            atomic_write_bytes(self.ckpt_dir / f"curiosity_{steps}.pth", module_buf.getvalue())
        # the state names the model file: written second, so a state file always has its model
        atomic_write_bytes(self.ckpt_dir / f"state_{steps}.json", json.dumps(self.state(steps), allow_nan=True).encode())
        atomic_write_bytes(self.csv_path, csv_bytes(self.rows))
        self.last_checkpoint = steps
        for old_steps, _ in list_checkpoints(self.ckpt_dir)[: -self.args.keep_checkpoints]:
            (self.ckpt_dir / f"state_{old_steps}.json").unlink(missing_ok=True)
            (self.ckpt_dir / f"model_{old_steps}.zip").unlink(missing_ok=True)
            (self.ckpt_dir / f"curiosity_{old_steps}.pth").unlink(missing_ok=True)
        if self.args.verbose:
            print(f"[{self.name}] checkpoint at {steps} steps ({time.perf_counter() - t0:.1f} s)", flush=True)

    def _restore(self) -> tuple[int, pathlib.Path] | None:
        """Read the newest complete checkpoint of this run, if any. :return: (steps, model path)"""
        self.commands = [self.command]
        if self.args.restart and self.ckpt_dir.exists():
            shutil.rmtree(self.ckpt_dir)
        for steps, state_path in reversed(list_checkpoints(self.ckpt_dir)):
            model_path = self.ckpt_dir / f"model_{steps}.zip"
            try:
                state = json.loads(state_path.read_text())
            except (OSError, ValueError) as e:
                print(f"[{self.name}] skipping unreadable {state_path.name}: {e}")
                continue
            if not model_readable(model_path) or (
                self.algo in SUM_ALGOS and not (self.ckpt_dir / f"curiosity_{steps}.pth").is_file()
            ):
                print(f"[{self.name}] skipping checkpoint {steps}: {model_path.name} is missing or corrupt")
                continue
            if state["config"] != self.config:
                diff = {k: (state["config"].get(k), v) for k, v in self.config.items() if state["config"].get(k) != v}
                raise SystemExit(
                    f"[{self.name}] {state_path} was written with other settings {diff} (checkpoint, now): "
                    "use another --out, the same settings, or --restart to discard it"
                )
            self.rows = state["rows"]
            self.window = deque(state["window"], maxlen=self.args.window)
            self.phases = deque(state.get("phases", []), maxlen=self.args.window)
            self.finals = deque([tuple(f) for f in state.get("finals", [])], maxlen=self.args.window)
            self.exploration.load_state_dict({k: state.get(k, d) for k, d in (("episode_rooms", []), ("rooms", []), ("max_return", None))})
            self.episodes = int(state["episodes"])
            self.wall_before = float(state["wall_time_s"])
            self.resumed_from = list(state.get("resumed_from", []))
            self.done = bool(state.get("done", False))
            self.commands = list(state.get("commands", [])) + ([self.command] if self.command not in state.get("commands", []) else [])
            self.last_checkpoint = steps
            return steps, model_path
        return None

    # ------------------------------------------------------------ training
    def make_env(self, seed: int, module_state: dict[str, Any] | None = None) -> Any:
        """The training env; for the SUM_ALGOS wrapped in ``GoCuVecEnvWrapper(mode="sum")`` (its module restored from
        ``module_state`` when given); with --zoo the env the zoo launcher builds (its wrappers, frame stack)."""
        if self.zoo is not None:
            manager = zoo_manager(self.algo, self.args.env, seed, zoo_overrides(self.args, self.algo, self.zoo))
            with contextlib.redirect_stdout(io.StringIO()):  # the zoo prints the settings it read
                _, manager.env_wrapper, _, manager.vec_env_wrapper = manager._preprocess_hyperparams(manager.read_hyperparameters()[0])
                return manager.create_envs(manager.n_envs, no_log=True)
        env = make_vec_env(self.args.env, n_envs=self.args.n_envs, seed=seed)
        if self.algo not in SUM_ALGOS:
            return env
        module = GoalCuriosityModule(env.observation_space, seed=self.seed, **curiosity_kwargs(self.args))
        if module_state is not None:
            module.load_state_dict(module_state)
        return GoCuVecEnvWrapper(env, module=module, mode="sum", intrinsic_coef=self.args.intrinsic_coef, centred=not self.args.uncentred)

    @staticmethod
    def module(model: Any) -> GoalCuriosityModule | None:
        """The model's curiosity module (PPO_GoCu's, or that of a GoCu wrapper in its env), None for plain PPO."""
        if isinstance(model, PPO_GoCu):
            return model.curiosity
        found = find_gocu_module(model.get_env())
        return None if found is None else found[0]

    def build(self) -> Any:
        a = self.args
        if self.zoo is not None:  # the model and env the zoo launcher builds
            with contextlib.redirect_stdout(io.StringIO()):
                model, _ = zoo_manager(self.algo, a.env, self.seed, zoo_overrides(a, self.algo, self.zoo)).setup_experiment()
            return model
        ppo = ppo_settings(a)
        if self.algo in ("ppo", "ppo_sum"):
            return PPO("CnnPolicy", self.make_env(self.seed), seed=self.seed, policy_kwargs=dict(features_extractor_class=PaperCNN), **ppo)
        if self.algo == "ppo_rnd":
            return PPO_RND("CnnPolicy", self.make_env(self.seed), seed=self.seed, verbose=0, **ppo)
        if self.algo not in ("ppo", "ppo_gocu", "ppo_sum"):  # a2c, dqn (and their _sum)
            kw = model_settings(a, self.algo)
            if "policy_kwargs" in kw:  # a string in the zoo's files, evaluated as the zoo evaluates it
                kw["policy_kwargs"] = eval(kw["policy_kwargs"])
            return MODEL_CLASSES[self.algo]("CnnPolicy", self.make_env(self.seed), seed=self.seed, verbose=0, **kw)
        return PPO_GoCu(
            "CnnPolicy", self.make_env(self.seed), seed=self.seed, intrinsic_coef=a.intrinsic_coef,
            curiosity_kwargs=curiosity_kwargs(a), verbose=0, **ppo,
        )

    def callbacks(self) -> list[BaseCallback]:
        callbacks: list[BaseCallback] = [self.exploration, SampleEfficiencyCallback(self)]
        if self.algo in SUM_ALGOS:
            callbacks.append(GoCuCallback())
        return callbacks

    def execute(self) -> None:
        restored = self._restore()
        if restored is not None:
            steps, model_path = restored
            reached = steps_to_threshold(self.rows, self.args.threshold, self.args.min_window)
            if self.args.stop_at_threshold and reached is not None:
                print(f"[{self.name}] reached {self.args.threshold} at {reached} steps (checkpoint at {steps}): skipped")
                atomic_write_bytes(self.csv_path, csv_bytes(self.rows))
                return
            if steps >= self.args.timesteps:
                print(f"[{self.name}] already at {steps} >= {self.args.timesteps} steps: skipped")
                atomic_write_bytes(self.csv_path, csv_bytes(self.rows))
                return
            cls = MODEL_CLASSES[self.algo]
            module_state = None
            if self.algo in SUM_ALGOS:
                module_state = th.load(self.ckpt_dir / f"curiosity_{steps}.pth", weights_only=True)
            model = cls.load(model_path, env=self.make_env(self.seed + steps, module_state), device="cpu")
            self.resumed_from.append(steps)
            self.done = False
            atomic_write_bytes(self.csv_path, csv_bytes(self.rows))  # drop rows written after the checkpoint
            print(f"[{self.name}] resuming from {model_path} ({steps} steps, {self.episodes} episodes)", flush=True)
            if isinstance(model, DQN):  # the replay buffer (~600 MB) is not checkpointed: refill it before learning on
                refill_before_training(model)
                print(f"[{self.name}] the replay buffer starts empty: no gradient step until it holds "
                      f"{model.learning_starts} transitions (the agent acts with its policy meanwhile)", flush=True)
            remaining, reset = self.args.timesteps - steps, False
        else:
            if self.csv_path.exists():
                self.csv_path.unlink()
            model = self.build()
            remaining, reset = self.args.timesteps, True
            print(f"[{self.name}] new run: {self.args.env}, {self.args.timesteps} steps", flush=True)
        self.process_start = time.perf_counter()
        if self.args.constant_curiosity:
            replace_curiosity(self.module(model), "constant")
        model.learn(remaining, callback=self.callbacks(), reset_num_timesteps=reset)
        if self.stopped_at_threshold is None:
            self.done = True
            self.checkpoint(model)
        else:  # the checkpoint of the rollout start is the run's last; the vector step after it is discarded
            atomic_write_bytes(self.csv_path, csv_bytes(self.rows))
            print(f"[{self.name}] reached {self.args.threshold} at {self.stopped_at_threshold} steps: stopped", flush=True)
        model.env.close()


def write_summary(args: argparse.Namespace, command: str) -> str:
    out = pathlib.Path(args.out)
    cmds, machines, env = recorded(out)
    table, _ = summarize(out, args.threshold, args.min_window, args.algos or ALGOS, atari=(env or args.env).startswith("ALE/"))
    seeds = sorted({int(m.group(1)) for p in out.glob("*_seed*.csv") if (m := re.search(r"_seed(\d+)\.csv$", p.name))})
    text = "\n".join(
        [
            f"# Sample efficiency: {env or (args.env if args.env_given else 'env not recorded in --out (pass --env)')}",
            "",
            table,
            "",
            f"Steps to threshold: first rollout end where the mean extrinsic return of the last {args.window} episodes "
            f"is >= {args.threshold} (counted once the window holds >= {args.min_window} episodes); mean +- std over the "
            "seeds that reached it. Final success rate: fraction of the last episodes of the window with return > 0, "
            "at the last row of each run.",
            "",
            f"- command: `{command}`",
            *(f"- runs written by: `{c}`" for c in cmds if c != command),
            f"- seeds: {', '.join(map(str, seeds))}",
            *(f"- machine (runs): {m}" for m in machines),
            *([f"- machine (this summary): {here}"] if (here := machine_line(args.threads)) not in machines else []),
            f"- threads: {args.threads} (torch.set_num_threads) in this command; each run's own is the --threads of the "
            "command that wrote it (default 1). One command executes its runs one after another; separate commands "
            "may have run side by side.",
            "",
        ]
    )
    atomic_write_bytes(out / "summary.md", text.encode())
    print("\n" + text)
    return text


# ---------------------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default=None, help="any registered gymnasium id (default GoCu/DoorKey-8x8-v0)")
    p.add_argument("--algos", nargs="+", choices=ALGOS, default=["ppo", "ppo_gocu"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--timesteps", type=int, default=800_000)
    p.add_argument("--out", default=None, help="output dir (default benchmarks/out/<env name>)")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (1: the scoring process and the updates use the other cores; README, \"Use\")")
    p.add_argument("--checkpoint-freq", type=int, default=100_000, help="env steps between checkpoints (rounded up to rollouts)")
    p.add_argument("--keep-checkpoints", type=int, default=2, help="newest checkpoints kept per run (a PPO_GoCu one is ~90 MB)")
    p.add_argument("--restart", action="store_true", help="discard existing checkpoints of the selected runs")
    p.add_argument("--summary-only", action="store_true", help="only summarise the CSVs in --out")
    p.add_argument("--threshold", type=float, default=0.9, help="mean return for 'steps to threshold'")
    p.add_argument("--window", type=int, default=100, help="episodes in the return window")
    p.add_argument("--min-window", type=int, default=100, help="episodes the window must hold before the threshold counts")
    p.add_argument(
        "--stop-at-threshold", action="store_true",
        help="end each run at the first rollout end where it reaches --threshold (checkpointed; a later command "
        "without the flag continues it to --timesteps)",
    )
    # GoCu settings
    p.add_argument("--goal-strategy", default=None, choices=list(GOAL_STRATEGIES), help="(default: the module's, proportional)")
    p.add_argument("--n-goals", type=int, default=None, help="K")
    p.add_argument("--intrinsic-coef", type=float, default=0.25, help="sigma of eq 10")
    p.add_argument("--uncentred", action="store_true", help="the _sum algos: the paper's uncentred sum r_e + sigma r_gc (GoCuVecEnvWrapper(centred=False))")
    p.add_argument("--curiosity-kwargs", default="{}", help="JSON dict of GoalCuriosityModule keywords")
    p.add_argument(
        "--constant-curiosity", action="store_true",
        help="ablation: r_gc replaced by its running mean (benchmarks/ablations.py; not a library setting)",
    )
    # overrides of the paper's PPO settings (for tests and quick checks)
    p.add_argument("--n-envs", type=int, default=N_ENVS)
    p.add_argument("--n-steps", type=int, default=PPO_SETTINGS["n_steps"])
    p.add_argument("--batch-size", type=int, default=PPO_SETTINGS["batch_size"])
    p.add_argument("--model-kwargs", default="{}", help="JSON dict overriding model settings of the zoo file: a2c / dqn's, or with --zoo any entry's")
    p.add_argument("--zoo", action=argparse.BooleanOptionalAction, default=None,
                   help="build env and model as the zoo launcher does, from sb3_gocu/hyperparams/<algo>.yml (ppo and ppo_gocu; "
                   "--n-envs, --n-steps, --batch-size and --intrinsic-coef then come from the file; default: for ALE/... ids)")
    p.add_argument("--print-every", type=int, default=10, help="print a progress line every this many rollouts")
    p.add_argument("--quiet", dest="verbose", action="store_false")
    return p


def main(argv: Sequence[str] | None = None) -> str:
    """Run (or resume) every (algo, seed) run, then summarise. :return: the summary's markdown."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.env_given = args.env is not None
    args.env = args.env or "GoCu/DoorKey-8x8-v0"
    args.zoo = args.env.startswith("ALE/") if args.zoo is None else args.zoo
    if args.zoo and not set(args.algos) <= {"ppo", "ppo_gocu"}:
        parser.error(f"--zoo runs ppo and ppo_gocu (their zoo files), got --algos {' '.join(args.algos)}")
    if args.keep_checkpoints < 1:
        parser.error("--keep-checkpoints must be >= 1")
    argv_list = list(sys.argv[1:] if argv is None else argv)
    if args.out is None:
        args.out = os.path.join("benchmarks", "out", args.env.split("/")[-1].lower())
    th.set_num_threads(args.threads)
    command = shlex.join(["python", "benchmarks/sample_efficiency.py", *argv_list])
    print(f"command: {command}")
    print(f"machine: {machine_line(args.threads)}; seeds {args.seeds}")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.summary_only:
        for seed in args.seeds:
            for algo in args.algos:
                Run(args, algo, seed, command).execute()
    return write_summary(args, command)


if __name__ == "__main__":
    main()
