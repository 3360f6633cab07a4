"""Installing the package: the extras named by missing-module errors, the hyperparameter files shipped as package
data, and a built wheel installed in a fresh virtual environment running the launcher from an empty folder."""

from __future__ import annotations

import importlib
import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import gymnasium as gym
import pytest

import sb3_gocu
from sb3_gocu._extras import check_env_extra

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "sb3_gocu"
CONFIG_FILES = ("ppo_gocu.yml", "ppo.yml", "ppo_dropin.yml", "a2c.yml", "a2c_dropin.yml", "dqn.yml", "dqn_dropin.yml")
DOORKEY = "GoCu/DoorKey-5x5-v0"
DOORKEY_DIR = "GoCu-DoorKey-5x5-v0"


def hide(monkeypatch: pytest.MonkeyPatch, *names: str) -> None:
    """Make the modules ``names`` (and their submodules already imported) unimportable for this test."""
    for name in names:
        for key in [k for k in sys.modules if k.startswith(name + ".")]:
            monkeypatch.setitem(sys.modules, key, None)
        monkeypatch.setitem(sys.modules, name, None)


def forget(monkeypatch: pytest.MonkeyPatch, *names: str) -> None:
    """Drop the modules ``names`` from ``sys.modules`` for this test, so that importing them runs them again."""
    for name in names:
        monkeypatch.delitem(sys.modules, name, raising=False)


# ------------------------------------------------------------------------------------------ missing extras
def test_the_launchers_name_the_zoo_extra(monkeypatch):
    hide(monkeypatch, "rl_zoo3")
    forget(monkeypatch, "sb3_gocu.zoo", "sb3_gocu.train", "sb3_gocu.enjoy", "sb3_gocu.record_video")
    with pytest.raises(ModuleNotFoundError) as info:
        importlib.import_module("sb3_gocu.zoo")
    assert str(info.value) == 'sb3_gocu.zoo needs rl_zoo3: pip install "sb3-gocu[zoo]"'
    assert info.value.name == "rl_zoo3"
    for launcher in ("train", "enjoy", "record_video"):
        with pytest.raises(ModuleNotFoundError, match=rf'^sb3_gocu\.{launcher} needs rl_zoo3: pip install "sb3-gocu\[zoo\]"$'):
            importlib.import_module(f"sb3_gocu.{launcher}")


def test_doorkey_names_the_minigrid_extra(monkeypatch):
    hide(monkeypatch, "minigrid")
    forget(monkeypatch, "sb3_gocu.envs.minigrid_envs")
    with pytest.raises(ModuleNotFoundError, match=r'needs minigrid: pip install "sb3-gocu\[minigrid\]"$'):
        gym.make(DOORKEY)


def test_mujoco_ids_name_the_mujoco_extra(monkeypatch):
    hide(monkeypatch, "mujoco")
    forget(monkeypatch, "sb3_gocu.envs.mujoco_envs")
    forget(monkeypatch, "sb3_gocu.envs.sawyer_envs")
    for env_id in ("GoCu/VisualReacher-v0", "GoCu/VisualSawyerPusher-v1"):
        with pytest.raises(ModuleNotFoundError, match=r'needs mujoco: pip install "sb3-gocu\[mujoco\]"$'):
            check_env_extra(env_id)


def test_atari_ids_name_the_atari_extra(monkeypatch):
    hide(monkeypatch, "ale_py")
    with pytest.raises(ModuleNotFoundError) as info:
        check_env_extra("ALE/Pitfall-v5")
    assert str(info.value) == 'ALE/Pitfall-v5 needs ale_py: pip install "sb3-gocu[atari]"'
    check_env_extra("CartPole-v1")  # other ids are not checked


# ------------------------------------------------------------------------------------------ package data
def test_the_config_files_are_package_data(monkeypatch, tmp_path):
    from sb3_gocu.zoo import HYPERPARAMS_ENV_VAR, default_conf_file, hyperparams_dir

    monkeypatch.delenv(HYPERPARAMS_ENV_VAR, raising=False)
    assert (PACKAGE / "py.typed").is_file()
    assert hyperparams_dir() == Path(sb3_gocu.__file__).resolve().parent / "hyperparams" == PACKAGE / "hyperparams"
    assert all((PACKAGE / "hyperparams" / name).is_file() for name in CONFIG_FILES)
    assert not (REPO / "hyperparams").exists(), "one copy of the config files, in the package"
    assert default_conf_file("ppo_gocu", DOORKEY) == PACKAGE / "hyperparams" / "ppo_gocu.yml"
    # $SB3_GOCU_HYPERPARAMS names another directory
    (tmp_path / "ppo_gocu.yml").write_text("GoCu/DoorKey-5x5-v0: {}\n")
    monkeypatch.setenv(HYPERPARAMS_ENV_VAR, str(tmp_path))
    assert hyperparams_dir() == tmp_path
    assert default_conf_file("ppo_gocu", DOORKEY) == tmp_path / "ppo_gocu.yml"
    assert default_conf_file("ppo", DOORKEY) is None, "that directory has no ppo.yml"


# ------------------------------------------------------------------------------------------ wheel
def build_wheel(out: Path) -> Path:
    """A wheel of the working tree, built offline from a copy (an in-tree build would write build/ and *.egg-info
    into the repository)."""
    src = out / "src"
    src.mkdir(parents=True)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(PACKAGE, src / "sb3_gocu", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-index", "--no-deps", "--no-build-isolation", "-w", str(out), str(src)],
        check=True, capture_output=True, text=True, timeout=300,
    )
    (wheel,) = out.glob("sb3_gocu-*.whl")
    return wheel


def see_site_packages_of_this_interpreter(venv_python: Path) -> None:
    """Let a new venv see the site-packages of the interpreter running the tests, after its own.

    ``venv --system-site-packages`` does not do it when that interpreter is itself a venv's: the new venv would see
    the *base* interpreter's site-packages, without the dependencies. A ``.pth`` line that starts with ``import``
    runs at start-up; ``site.addsitedir`` appends each directory to ``sys.path`` (after the venv's own
    site-packages) and runs the ``.pth`` files there, as for the interpreter running the tests."""
    dirs = [d for d in dict.fromkeys(site.getsitepackages() + [p for p in sys.path if Path(p).name in ("site-packages", "dist-packages")])
            if Path(d).is_dir()]
    own = subprocess.run([str(venv_python), "-c", "import site; print(site.getsitepackages()[0])"],
                         check=True, capture_output=True, text=True, timeout=120).stdout.strip()
    (Path(own) / "_sb3_gocu_test_parent_site.pth").write_text(
        "import site; " + "; ".join(f"site.addsitedir({d!r})" for d in dirs) + "\n")


@pytest.mark.slow
def test_wheel_installs_and_trains_from_an_empty_folder(tmp_path):
    """Build a wheel, install it (``--no-deps``) into a new venv that sees this interpreter's site-packages after
    its own (torch and the other dependencies come from there, whether this interpreter is a venv's or the
    system's), and from an empty folder run the launcher with the config file the wheel carries. About a minute on
    2 busy cores.

    The interpreter running the tests may have the package installed editable: its site-packages then holds
    setuptools' ``__editable___sb3_gocu_*_finder``, which the venv sees too. That finder is appended to
    ``sys.meta_path``, after the ordinary path finder, and the venv's site-packages comes before the others on
    ``sys.path``, so the venv's copy wins; the test checks that ``sb3_gocu`` is imported from the venv (with
    ``PYTHONPATH`` removed and ``PYTHONNOUSERSITE=1``, so that neither can bring the source tree in)."""
    wheel = build_wheel(tmp_path / "dist")
    names = zipfile.ZipFile(wheel).namelist()
    assert "sb3_gocu/py.typed" in names
    assert {f"sb3_gocu/hyperparams/{name}" for name in CONFIG_FILES} <= set(names)

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    see_site_packages_of_this_interpreter(python)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "SB3_GOCU_HYPERPARAMS")}
    env.update(PYTHONNOUSERSITE="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    # this interpreter's pip (seen through the .pth file) installs into the venv; --ignore-installed: the editable
    # sb3-gocu of the test interpreter's site is not uninstalled
    subprocess.run(
        [str(python), "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--ignore-installed", str(wheel)],
        check=True, capture_output=True, text=True, env=env, timeout=300,
    )
    assert (venv / "bin" / "sb3-gocu-train").is_file()

    work = tmp_path / "work"
    work.mkdir()
    where = subprocess.run(
        [str(python), "-c", "import sb3_gocu, sb3_gocu.zoo; print(sb3_gocu.__file__); print(sb3_gocu.zoo.hyperparams_dir())"],
        cwd=work, env=env, capture_output=True, text=True, timeout=300, check=False,
    )
    assert where.returncode == 0, where.stderr[-3000:]
    module_file, conf_dir = (Path(line) for line in where.stdout.split())
    assert module_file.is_relative_to(venv) and not module_file.is_relative_to(REPO), module_file
    assert conf_dir == module_file.parent / "hyperparams"

    proc = subprocess.run(
        [str(python), "-m", "sb3_gocu.train", "--algo", "ppo_gocu", "--env", DOORKEY, "-n", "4096"],
        cwd=work, env=env, capture_output=True, text=True, timeout=900, check=False,
    )
    assert proc.returncode == 0, f"{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    assert f"Loading hyperparameters from: {conf_dir / 'ppo_gocu.yml'}" in proc.stdout
    model = work / "logs" / "ppo_gocu" / f"{DOORKEY_DIR}_1" / f"{DOORKEY_DIR}.zip"
    assert model.is_file()
    assert sb3_gocu.PPO_GoCu.load(model).num_timesteps == 4096
