"""The multi-machine recipe of docs/zoo.md: ``-optimize`` workers sharing one study through PostgreSQL.

The fixture starts a throw-away PostgreSQL server on 127.0.0.1 (Debian's ``postgresql`` package: ``initdb`` /
``pg_ctl`` under ``/usr/lib/postgresql/*/bin``, or on the PATH), with password authentication over TCP as in the
docs, and creates the database with ``createdb``; two launcher processes then share one study through a
``postgresql+psycopg2://USER:PASSWORD@HOST:PORT/optuna`` URL. Where no server can be started (no binaries,
no ``postgres`` user to run it as root, initdb or start failing), the test is skipped with the reason. About
80 s on 2 busy cores, as long as the journal-file test in test_zoo.py (+ ~5 s for the server).
"""

from __future__ import annotations

import collections
import contextlib
import glob
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import optuna
import pytest

from sb3_gocu.zoo import GOCU_TRIAL_PARAMS

# as in test_zoo.py (the journal-file version of this test)
DOORKEY = "GoCu/DoorKey-5x5-v0"
TINY_CURIOSITY = (
    "dict(pretrain_steps=128, predictor_train_freq=256, vae_epochs=1, vae_update_epochs=1, predictor_pairs=256, predictor_epochs=1, "
    "predictor_hidden=(64, 64))"
)
N_TRIALS = 2  # per worker
#: where Debian's postgresql-NN packages put the server binaries (not on the PATH)
PG_BIN_GLOB = "/usr/lib/postgresql/*/bin"


def find_pg_bin(pattern: str = PG_BIN_GLOB) -> Path | None:
    """The folder of ``initdb``/``pg_ctl``/``createdb``: the newest Debian version, else the PATH's; None if none."""

    def version(path: str) -> tuple:
        v = Path(path).parent.name
        return tuple(int(p) for p in v.split(".") if p.isdigit())

    for folder in sorted(glob.glob(pattern), key=version, reverse=True):
        if all(os.access(Path(folder) / b, os.X_OK) for b in ("initdb", "pg_ctl", "createdb")):
            return Path(folder)
    initdb = shutil.which("initdb")
    if pattern == PG_BIN_GLOB and initdb:
        folder = Path(initdb).resolve().parent
        if all(os.access(folder / b, os.X_OK) for b in ("pg_ctl", "createdb")):
            return folder
    return None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _as_server_user() -> list[str]:
    """The command prefix that runs the server binaries: initdb and postgres refuse to run as root."""
    if os.geteuid() != 0:
        return []
    try:
        import pwd

        pwd.getpwnam("postgres")
    except KeyError:
        pytest.skip("running as root and there is no 'postgres' user to run the PostgreSQL server as")
    if shutil.which("runuser"):
        return ["runuser", "-u", "postgres", "--"]
    pytest.skip("running as root and runuser (util-linux) is missing: cannot run PostgreSQL as 'postgres'")


def _check(cmd: list[str], what: str, log: Path | None = None, **kwargs) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False, **kwargs)
    if proc.returncode != 0:
        tail = log.read_text()[-2000:] if log is not None and log.exists() else ""
        pytest.skip(f"PostgreSQL server unavailable: {what} failed ({proc.returncode}): {proc.stdout[-1000:]}{proc.stderr[-1000:]}{tail}")


@contextlib.contextmanager
def postgres_server(pattern: str = PG_BIN_GLOB):
    """A fresh server on 127.0.0.1: yields ``postgresql+psycopg2://postgres:PASSWORD@127.0.0.1:PORT/optuna``.

    Stops it (``pg_ctl stop -m fast``) and removes its data folder on the way out; skips the calling test where
    the server cannot be started.
    """
    bindir = find_pg_bin(pattern)
    if bindir is None:
        pytest.skip(f"no PostgreSQL server binaries (initdb, pg_ctl, createdb) under {pattern} or on the PATH: apt-get install postgresql")
    pytest.importorskip("psycopg2", reason="the PostgreSQL driver psycopg2 (the tests extra: psycopg2-binary) is missing")
    prefix = _as_server_user()
    # not under pytest's tmp_path: /tmp/pytest-of-root is 0700, the 'postgres' user could not reach a folder there
    root = Path(tempfile.mkdtemp(prefix="sb3gocu-pg-"))
    data, log, pwfile = root / "data", root / "server.log", root / "pw"
    password = secrets.token_hex(12)
    started = False
    try:
        pwfile.write_text(password + "\n")
        if prefix:
            shutil.chown(root, "postgres", "postgres")
            shutil.chown(pwfile, "postgres", "postgres")
        os.chmod(pwfile, 0o600)
        _check(
            [*prefix, str(bindir / "initdb"), "-D", str(data), "-U", "postgres", f"--pwfile={pwfile}", "-E", "UTF8",
             "--no-locale", "--auth-local=trust", "--auth-host=scram-sha-256", "--no-sync"],
            "initdb",
        )
        port = free_port()
        opts = (f"-c listen_addresses=127.0.0.1 -p {port} -k {root} -c fsync=off -c shared_buffers=16MB "
                "-c max_connections=20")
        started = True  # from here on, stop it whatever happens
        _check([*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-l", str(log), "-w", "-t", "30", "-o", opts, "start"], "pg_ctl start", log)
        # step 1 of the recipe, over TCP with the password, as a worker logs in
        env = {**os.environ, "PGPASSWORD": password}
        _check([str(bindir / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "postgres", "optuna"], "createdb", log, env=env)
        yield f"postgresql+psycopg2://postgres:{password}@127.0.0.1:{port}/optuna"
    finally:
        if started:
            for mode in ("fast", "immediate"):  # never leave a server running on a removed data folder
                stop = subprocess.run([*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-m", mode, "-w", "stop"], capture_output=True, timeout=60, check=False)
                if stop.returncode == 0 or not (data / "postmaster.pid").exists():
                    break
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def postgres_url():
    with postgres_server() as url:
        yield url


def test_no_server_binaries_skips():
    """The skip path: without binaries the server does not start and the test says why, it does not pass."""
    with pytest.raises(pytest.skip.Exception, match="no PostgreSQL server binaries"), postgres_server("/nonexistent/postgresql/*/bin"):
        pytest.fail("a server started without binaries")


def test_optimize_two_workers_share_one_postgres_study(tmp_path, postgres_url):
    """Two ``-optimize`` processes started at once on one PostgreSQL URL fill one study (docs/zoo.md's recipe)."""
    common = [
        "-m", "sb3_gocu.train", "--algo", "ppo_gocu", "--env", DOORKEY, "-n", "512", "-f", "logs", "--num-threads", "1",
        "-optimize", "--storage", postgres_url, "--study-name", "gocu-test", "--n-trials", str(N_TRIALS),
        "--n-startup-trials", "1", "--n-evaluations", "1", "--eval-episodes", "1", "--no-optim-plots",
        # seeded random sampling: cheap PPO draws (n_steps <= 128) for these two seeds
        "--sampler", "random", "--hyperparams", "n_envs:2", f"curiosity_kwargs:{TINY_CURIOSITY}",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    # the recipe creates the study once before the workers start: two workers creating Optuna's tables at the same
    # time on an empty database can collide (IntegrityError on CREATE TYPE studydirection), one of them then exits
    optuna_cli = [sys.executable, "-c", "import sys; from optuna.cli import main; sys.exit(main())"]
    create = subprocess.run(
        [*optuna_cli, "create-study", "--storage", postgres_url, "--study-name", "gocu-test", "--direction", "maximize"],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert create.returncode == 0, create.stdout + create.stderr
    procs = [
        subprocess.Popen([sys.executable, *common, "--seed", seed], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for seed in ("11", "6")
    ]
    try:
        outputs = [p.communicate(timeout=240)[0] for p in procs]
    finally:
        for p in procs:  # a timeout must not leave a worker holding the server's connections
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, out in zip(procs, outputs):
        assert p.returncode == 0, out[-4000:]
        assert "Number of finished trials" in out
    study = optuna.load_study(study_name="gocu-test", storage=postgres_url)
    assert len(optuna.get_all_study_names(postgres_url)) == 1, "both workers joined one study"
    done = [t for t in study.trials if t.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)]
    assert len(done) == len(study.trials), [(t.number, t.state) for t in study.trials]
    # each trial records the process that ran it ("host:pid"): every worker ran its --n-trials 2, all in the one study
    per_worker = collections.Counter(int(t.user_attrs["worker"].rsplit(":", 1)[1]) for t in done)
    assert per_worker == {p.pid: N_TRIALS for p in procs}, f"trials per worker pid: {dict(per_worker)}"
    assert len(study.trials) == sum(per_worker.values()) == 2 * N_TRIALS
    for t in done:
        assert set(GOCU_TRIAL_PARAMS) <= t.params.keys(), "the ppo_gocu sampler drew the GoCu parameters"
    assert sorted(t.number for t in study.trials) == list(range(2 * N_TRIALS)), "no trial number lost or taken twice"
