"""Optional dependencies: which extra of ``sb3-gocu`` brings what, and the error that says so.

``pip install sb3-gocu`` brings what ``import sb3_gocu`` needs (Stable-Baselines3, PyTorch, Gymnasium, NumPy);
the rest comes with extras: ``[minigrid]`` (the ``GoCu/DoorKey-*`` ids), ``[mujoco]`` (``GoCu/VisualReacher-v0``,
``GoCu/VisualPusher-v0``, the ``GoCu/VisualSawyer*`` ids),
``[atari]`` (the ``ALE/...`` ids), ``[zoo]`` (the rl-zoo3 launchers ``sb3_gocu.train``,
``.enjoy``, ``.record_video`` and rl-zoo3's plots), ``[plots]`` (matplotlib), ``[all]`` (all of them).
"""

from __future__ import annotations

import importlib

#: Gymnasium id prefix -> (modules its environments need, the extra that brings them)
ENV_EXTRAS: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ("GoCu/DoorKey-", ("sb3_gocu.envs.minigrid_envs",), "minigrid"),
    ("GoCu/VisualSawyer", ("sb3_gocu.envs.sawyer_envs",), "mujoco"),
    ("GoCu/Visual", ("sb3_gocu.envs.mujoco_envs",), "mujoco"),
    ("ALE/", ("ale_py", "cv2"), "atari"),
)


def missing_extra(error: ImportError, needed_by: str, extra: str) -> ModuleNotFoundError:
    """The error to raise (``from error``) when an optional module is missing: it names the module, what needs
    it and the extra to install, e.g. ``sb3_gocu.zoo needs rl_zoo3: pip install "sb3-gocu[zoo]"``.

    :param error: the original ``ModuleNotFoundError``
    :param needed_by: what needs the module (a module of sb3_gocu, an environment id, ...)
    :param extra: the extra of ``sb3-gocu`` that brings it
    """
    name = getattr(error, "name", None) or str(error)
    package = name.partition(".")[0]  # the top-level package is what gets installed
    return ModuleNotFoundError(f'{needed_by} needs {package}: pip install "sb3-gocu[{extra}]"', name=name)


def check_env_extra(env_id: str) -> None:
    """Import what the environments of ``env_id`` need (see :data:`ENV_EXTRAS`); raise the error of
    :func:`missing_extra` if one is missing. Ids of other families are not checked."""
    for prefix, modules, extra in ENV_EXTRAS:
        if env_id.startswith(prefix):
            for module in modules:
                if module.startswith("sb3_gocu."):
                    importlib.import_module(module)  # its own error names the extra
                    continue
                try:
                    importlib.import_module(module)
                except ModuleNotFoundError as e:
                    raise missing_extra(e, env_id, extra) from e
