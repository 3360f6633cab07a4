"""Crash-safe checkpoints and exact resumption for PPO_GoCu.

What this file provides (see ``docs/reliability.md`` for the guarantees and their conditions):

* :func:`atomic_write` and :func:`save_model`: a model file is written to a temporary file in the same
  directory, flushed to disk, then renamed over the target. A reader (or a process killed with SIGKILL
  mid-save) sees either the previous complete file or the new complete file, never a half-written one.
  :meth:`PPO_GoCu.save <sb3_gocu.PPO_GoCu.save>` goes through it, so SB3's ``CheckpointCallback`` and the
  zoo's ``--save-freq`` write atomic checkpoints too.
* :func:`check_model_file`: a corrupt or truncated model file is refused with a ``ValueError`` naming the
  file, before SB3 or torch read it.
* :class:`GlobalRNGState`: the process-wide generators SB3 draws from (torch: action sampling; numpy: PPO's
  minibatch order; python ``random``), saved in the model file as ``global_rng.pth`` (plain tensors, loadable
  with ``weights_only=True``) and put back by ``learn(..., reset_num_timesteps=False)``.
* the env state: SB3 saves ``_last_obs`` and ``_last_episode_starts`` but not the env they belong to. With
  ``save_env=True`` the whole training env stack (a ``DummyVecEnv`` of picklable envs and its wrappers; the
  curiosity module is stored by reference, not twice) is pickled into the model zip as ``gocu_env_state.pkl``;
  ``PPO_GoCu.load(path, restore_env=True)`` unpickles it. Unpickling runs code from the file: restore env
  states only from files you wrote.
* :class:`GoCuCheckpointCallback`: checkpoints at rollout boundaries, where the whole training state is
  consistent (after PPO's update and the curiosity update), and :func:`latest_checkpoint` to find the newest
  readable one after a crash.
"""

from __future__ import annotations

import inspect
import io
import os
import pathlib
import pickle
import random
import re
import uuid
import warnings
import zipfile
from typing import Any, Callable, Union

import cloudpickle
import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from sb3_gocu.curiosity.checks import is_integer

#: zip member holding the pickled env stack (not ``.pth``: SB3's loader ignores it)
ENV_MEMBER = "gocu_env_state.pkl"
_MODULE_ID = "gocu_curiosity_module"
_TMP_SUFFIX = ".tmp"

PathLike = Union[str, "os.PathLike[str]"]


# ---------------------------------------------------------------------------------------------- files
def zip_path(path: PathLike) -> pathlib.Path:
    """The file SB3's ``save(path)`` writes: ``path`` with ``.zip`` appended when it has no suffix."""
    p = pathlib.Path(path)
    return p.with_name(p.name + ".zip") if p.suffix == "" else p


def atomic_write(path: PathLike, write: Callable[[io.BufferedRandom], None]) -> pathlib.Path:
    """Write a file all at once or not at all.

    ``write(f)`` fills a temporary file ``.{name}.{pid}.{random}.tmp`` beside ``path``; it is flushed and
    fsynced, then renamed onto ``path`` (``os.replace``, atomic on POSIX and Windows), and the directory is
    fsynced. On any error the temporary file is removed and ``path`` is left as it was.

    :return: ``path``
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}{_TMP_SUFFIX}")
    fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies, as for open()
    try:
        with os.fdopen(fd, "w+b") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass
    return path


def remove_stale_temporaries(directory: PathLike, name_prefix: str = "") -> int:
    """Delete the temporary files that processes killed mid-save left in ``directory``.

    Only files named like :func:`atomic_write`'s temporaries whose writer process no longer exists are removed.

    :return: number of files removed
    """
    removed = 0
    pattern = re.compile(rf"^\.{re.escape(name_prefix)}.*\.(\d+)\.[0-9a-f]{{8}}{re.escape(_TMP_SUFFIX)}$")
    for f in pathlib.Path(directory).glob(f".{name_prefix}*{_TMP_SUFFIX}"):
        m = pattern.match(f.name)
        if m is None or _pid_alive(int(m.group(1))):
            continue
        f.unlink(missing_ok=True)
        removed += 1
    return removed


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def check_model_file(path: PathLike) -> pathlib.Path:
    """Refuse a corrupt or truncated model file with a clear error, before anything deserialises it.

    Reads the zip's central directory and every member's CRC-32 (``ZipFile.testzip``), and checks that the
    archive holds SB3's ``data`` entry.

    :param path: the model file (``.zip`` is appended when ``path`` does not exist and has no suffix, as SB3 does)
    :return: the file's path
    :raises FileNotFoundError: if there is no such file
    :raises ValueError: naming the file, if it is corrupt, truncated or not a model file
    """
    p = pathlib.Path(path)
    if not p.exists() and p.suffix == "":
        p = zip_path(p)
    if not p.is_file():
        raise FileNotFoundError(f"no model file at {path}")
    try:
        with zipfile.ZipFile(p) as archive:
            bad = archive.testzip()
            names = archive.namelist()
    except (OSError, MemoryError) as e:
        if isinstance(e, (FileNotFoundError, PermissionError, IsADirectoryError)):
            raise
        raise ValueError(f"{p}: cannot read the model file ({e}); it may be corrupt or truncated") from e
    except Exception as e:  # BadZipFile, EOFError, zlib.error, struct.error, NotImplementedError, ...
        raise ValueError(
            f"{p}: the model file is corrupt or truncated, not a readable zip archive ({type(e).__name__}: {e}). "
            "Load an earlier checkpoint."
        ) from e
    if bad is not None:
        raise ValueError(f"{p}: the model file is corrupt: its member {bad!r} fails its CRC-32 check. Load an earlier checkpoint.")
    if "data" not in names:
        # a truncated model zip can still open as a zip: the last complete .pth inside it is itself a zip archive
        raise ValueError(
            f"{p}: the model file is truncated or corrupt, or not a Stable-Baselines3 model file (the zip has no 'data' "
            f"entry; members: {names[:4]}). Load an earlier checkpoint."
        )
    return p


# ---------------------------------------------------------------------------------------------- global RNG
class GlobalRNGState:
    """The process-wide random generators, as a state_dict of plain tensors and numbers.

    SB3 draws actions from the global torch generator and shuffles PPO's minibatches with the global numpy
    generator; SB3 itself saves neither. :meth:`state_dict` captures them (torch CPU, CUDA if present, numpy's
    legacy generator, python ``random``); :meth:`load_state_dict` only *keeps* a loaded state, and
    :meth:`restore` puts it back (PPO_GoCu does so in ``learn(..., reset_num_timesteps=False)``), so loading
    a model to evaluate it does not touch the process's generators.
    """

    def __init__(self) -> None:
        self.pending: dict[str, Any] | None = None

    def state_dict(self) -> dict[str, Any]:
        name, keys, pos, has_gauss, cached = np.random.get_state(legacy=True)  # type: ignore[misc]
        version, internal, gauss_next = random.getstate()
        state: dict[str, Any] = {
            "torch": th.get_rng_state(),
            "numpy": {"name": str(name), "keys": th.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
                      "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "python": {"version": int(version), "state": th.tensor(internal, dtype=th.int64), "gauss_next": gauss_next},
        }
        if th.cuda.is_available():
            state["cuda"] = th.cuda.get_rng_state_all()
        return state

    def load_state_dict(self, state: dict[str, Any], strict: bool = True) -> None:
        """Keep ``state`` until :meth:`restore` (``strict`` is accepted for SB3's ``set_parameters``)."""
        if strict and not {"torch", "numpy", "python"} <= set(state):
            raise ValueError(f"not a GlobalRNGState state_dict (keys {sorted(state)})")
        self.pending = state

    def restore(self) -> bool:
        """Put the kept state back into the process's generators (once).

        :return: whether there was a state to restore
        """
        state, self.pending = self.pending, None
        if state is None:
            return False
        th.set_rng_state(state["torch"].cpu())
        n = state["numpy"]
        np.random.set_state((n["name"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached_gaussian"]))
        p = state["python"]
        random.setstate((p["version"], tuple(int(x) for x in p["state"].tolist()), p["gauss_next"]))
        if "cuda" in state and th.cuda.is_available() and len(state["cuda"]) == th.cuda.device_count():
            th.cuda.set_rng_state_all(state["cuda"])
        return True


# ---------------------------------------------------------------------------------------------- env state
def _new_vec_env_wrapper(cls: type) -> Any:
    return cls.__new__(cls)


def _set_vec_env_wrapper_state(obj: Any, state: dict) -> None:
    obj.__dict__.update(state)
    obj.class_attributes = dict(inspect.getmembers(type(obj)))


class _EnvPickler(cloudpickle.Pickler):
    """Pickles an env stack; the curiosity module is written as a reference, and SB3's VecEnvWrappers (which
    hold unpicklable class attributes, or drop their ``venv`` like VecNormalize) are pickled whole."""

    def __init__(self, file: io.BytesIO, module: Any) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._gocu_module = module

    def persistent_id(self, obj: Any) -> str | None:
        return _MODULE_ID if obj is self._gocu_module and obj is not None else None

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, VecEnvWrapper):
            state = {k: v for k, v in vars(obj).items() if k != "class_attributes"}
            return _new_vec_env_wrapper, (type(obj),), state, None, None, _set_vec_env_wrapper_state
        return super().reducer_override(obj)


class _EnvUnpickler(pickle.Unpickler):
    def __init__(self, file: io.BytesIO, module: Any) -> None:
        super().__init__(file)
        self._gocu_module = module

    def persistent_load(self, pid: Any) -> Any:
        if pid == _MODULE_ID:
            return self._gocu_module
        raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")


def dump_env_state(env: VecEnv, module: Any = None) -> bytes:
    """Pickle a training env stack (its envs' internal state, RNGs, wrappers, buffers), with ``module`` (the
    curiosity module its GoCu wrappers hold) as a reference.

    :raises TypeError: if the stack cannot be pickled (a ``SubprocVecEnv``, an env holding an open file, a
        rendering context, ...)
    """
    buf = io.BytesIO()
    try:
        _EnvPickler(buf, module).dump(env)
    except Exception as e:
        raise TypeError(
            f"the training env cannot be pickled ({type(e).__name__}: {e}): env states can be saved for in-process "
            "envs (DummyVecEnv) whose envs and wrappers pickle (no SubprocVecEnv, open files, rendering contexts)"
        ) from e
    return buf.getvalue()


def load_env_state(data: bytes, module: Any = None) -> VecEnv:
    """Unpickle an env stack from :func:`dump_env_state`; its GoCu wrappers get ``module``.

    Unpickling runs code from ``data``: only load env states you saved yourself.
    """
    return _EnvUnpickler(io.BytesIO(data), module).load()


def read_env_state(path: PathLike, module: Any = None) -> VecEnv:
    """The env stack saved in a model zip with ``save_env=True`` (see :func:`load_env_state`)."""
    p = check_model_file(path)
    with zipfile.ZipFile(p) as archive:
        if ENV_MEMBER not in archive.namelist():
            raise ValueError(f"{p} holds no env state: save it with save(..., save_env=True) or GoCuCheckpointCallback(save_env=True)")
        return load_env_state(archive.read(ENV_MEMBER), module)


def without_members(path: PathLike | io.BufferedIOBase, members: list[str]) -> io.BytesIO:
    """A copy of the zip at ``path`` in memory, less ``members`` (which are never read)."""
    out = io.BytesIO()
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(out, mode="w") as copy:
        for info in source.infolist():
            if info.filename not in members:
                copy.writestr(info, source.read(info))
    out.seek(0)
    return out


# ---------------------------------------------------------------------------------------------- saving
def save_model(
    model: BaseAlgorithm,
    path: PathLike | io.BufferedIOBase,
    exclude: list[str] | None = None,
    include: list[str] | None = None,
    save_env: bool = False,
) -> pathlib.Path | None:
    """SB3's ``save`` made atomic (see :func:`atomic_write`), optionally with the env state in the zip.

    :param path: a path (``.zip`` appended when it has no suffix, as SB3 does) or a writable binary file object
        (written in place: atomicity is then the caller's business)
    :param save_env: also pickle the training env stack into the zip (:func:`dump_env_state`)
    :return: the file written, or None for a file object
    """
    env_blob = None
    if save_env:
        if model.env is None:
            raise ValueError("save_env=True: the model has no env")
        env_blob = dump_env_state(model.env, getattr(model, "curiosity", None))

    def write(f: Any) -> None:
        BaseAlgorithm.save(model, f, exclude=exclude, include=include)
        if env_blob is not None:
            f.seek(0)
            with zipfile.ZipFile(f, mode="a") as archive:
                archive.writestr(ENV_MEMBER, env_blob)

    if isinstance(path, (str, os.PathLike)):
        return atomic_write(zip_path(path), write)
    write(path)
    return None


_CHECKPOINT_RE = r"^{prefix}_(\d+)_steps\.zip$"


def list_checkpoints(save_path: PathLike, name_prefix: str = "rl_model") -> list[tuple[int, pathlib.Path]]:
    """Checkpoints ``{name_prefix}_{steps}_steps.zip`` in ``save_path`` (the names SB3's ``CheckpointCallback``
    and :class:`GoCuCheckpointCallback` write), oldest first, as (steps, path)."""
    pattern = re.compile(_CHECKPOINT_RE.format(prefix=re.escape(name_prefix)))
    out = []
    for f in pathlib.Path(save_path).glob(f"{name_prefix}_*_steps.zip"):
        m = pattern.match(f.name)
        if m:
            out.append((int(m.group(1)), f))
    return sorted(out)


def latest_checkpoint(save_path: PathLike, name_prefix: str = "rl_model", verify: bool = True) -> pathlib.Path | None:
    """The newest checkpoint in ``save_path``, or None.

    :param verify: skip files that fail :func:`check_model_file` (with a warning)
    """
    for _, path in reversed(list_checkpoints(save_path, name_prefix)):
        if not verify:
            return path
        try:
            check_model_file(path)
            return path
        except ValueError as e:
            warnings.warn(f"skipping an unreadable checkpoint: {e}")
    return None


class GoCuCheckpointCallback(CheckpointCallback):
    """SB3's ``CheckpointCallback`` for PPO_GoCu: the same arguments with the same meaning (``save_freq`` counts
    calls, i.e. vector steps: ``save_freq * n_envs`` env steps between checkpoints), the same file names
    (``{save_path}/{name_prefix}_{num_timesteps}_steps.zip``, the VecNormalize statistics beside them), and three
    differences: a checkpoint due in a rollout is written at the start of the next one (after PPO's update and the
    curiosity update: the one point where the whole training state is consistent), or at the end of training; the
    file is written atomically (:func:`save_model`); and it carries the curiosity module's whole state and the global
    RNG states (as every ``PPO_GoCu.save`` does).

    Resume after a crash with::

        path = latest_checkpoint(save_path, name_prefix)
        model = PPO_GoCu.load(path, restore_env=True)    # or env=make_env() without save_env
        model.learn(total - model.num_timesteps, reset_num_timesteps=False, callback=GoCuCheckpointCallback(...))

    (SB3's ``CheckpointCallback`` also writes atomic PPO_GoCu files, since ``PPO_GoCu.save`` is atomic, but it
    saves in the middle of a rollout: a run resumed from it repeats that rollout's steps.)

    :param save_freq: calls (vector steps) between checkpoints (>= 1), as for ``CheckpointCallback``
    :param save_path: directory of the checkpoints (created)
    :param name_prefix: file name prefix
    :param save_replay_buffer: as for ``CheckpointCallback`` (PPO_GoCu has no replay buffer)
    :param save_vecnormalize: also save the ``VecNormalize`` statistics, if the env has them
    :param save_env: also save the env stack in the file, for an exact resumption with ``load(..., restore_env=True)``
        (``DummyVecEnv`` of picklable envs only; if it cannot be pickled a warning is given once and the checkpoints
        go on without it)
    :param verbose: 2 prints each checkpoint written
    """

    def __init__(
        self,
        save_freq: int,
        save_path: PathLike,
        name_prefix: str = "rl_model",
        save_replay_buffer: bool = False,
        save_vecnormalize: bool = False,
        save_env: bool = False,
        verbose: int = 0,
    ) -> None:
        if not (is_integer(save_freq) and save_freq >= 1):
            raise ValueError(f"save_freq must be an integer >= 1, got {save_freq!r}")
        super().__init__(int(save_freq), os.fspath(save_path), name_prefix, save_replay_buffer, save_vecnormalize, verbose)
        self.save_env = save_env
        self._due = False
        self.last_path: pathlib.Path | None = None

    def _init_callback(self) -> None:
        if not hasattr(self.model, "curiosity"):
            raise TypeError("GoCuCheckpointCallback saves PPO_GoCu models (their file carries the curiosity state)")
        super()._init_callback()
        remove_stale_temporaries(self.save_path, self.name_prefix)

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            self._due = True  # written at the rollout boundary
        return True

    def _on_rollout_start(self) -> None:
        self._save_if_due()

    def _on_training_end(self) -> None:
        self._save_if_due()

    def _save_if_due(self) -> None:
        if not self._due:
            return
        self._due = False
        path = pathlib.Path(self._checkpoint_path(extension="zip"))
        if self.save_env:
            try:
                save_model(self.model, path, save_env=True)
            except TypeError as e:
                warnings.warn(f"GoCuCheckpointCallback: saving without the env state from now on: {e}")
                self.save_env = False
        if not self.save_env:
            save_model(self.model, path)
        self.last_path = path
        if self.verbose >= 2:
            print(f"Saving model checkpoint to {path}")
        if self.save_replay_buffer and getattr(self.model, "replay_buffer", None) is not None:
            self.model.save_replay_buffer(self._checkpoint_path("replay_buffer_", extension="pkl"))  # type: ignore[attr-defined]
        if self.save_vecnormalize and self.model.get_vec_normalize_env() is not None:
            self.model.get_vec_normalize_env().save(self._checkpoint_path("vecnormalize_", extension="pkl"))  # type: ignore[union-attr]
