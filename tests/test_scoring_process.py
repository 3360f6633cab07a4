"""Scoring in a worker process (``scoring_process=True``): the same values as scoring in the caller, bit for bit."""

import threading

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.env_util import make_vec_env

from sb3_gocu import GoalCuriosityModule, PPO_GoCu
from sb3_gocu.curiosity.scoring import ProcessScorer

from conftest import SMALL_CURIOSITY, ChainEnv

SPACE = spaces.Box(0, 255, (16, 16, 3), np.uint8)


def frames_with_repeats(n_steps: int, n_envs: int, seed: int) -> np.ndarray:
    """Frames drawn from a small pool, so that states recur within and across envs and steps (memo hits,
    rows embedded by an earlier ticket still in flight)."""
    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 256, (12, 16, 16, 3), dtype=np.uint8)
    return pool[rng.integers(0, len(pool), (n_steps, n_envs))]


def run_module(mode: str, frames: np.ndarray, dones: np.ndarray, in_flight: int, **kwargs) -> tuple[list, GoalCuriosityModule]:
    """Feed the frames through a fresh module: ``sync`` (step), ``thread`` or ``process`` (submit, with up to
    ``in_flight`` tickets outstanding); a predictor and a VAE update halfway (new encoder, folded predictor and
    goal halves). ``kwargs``: more module keywords."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, revisit_decay="none", scoring_process=mode == "process", seed=3, **kwargs)
    module.recording = True
    module.pretrain()
    out, tickets = [], []
    for t, (f, d) in enumerate(zip(frames, dones)):
        if t == len(frames) // 4:  # goals from the episodes so far: later episodes are scored against them
            module.collect_all()
            module.add_finished_episode_goals()
        if t == len(frames) // 2:
            module.collect_all()
            module.train_predictor()
            module.train_vae()
        if mode == "sync":
            out.append(module.step(f, d))
            continue
        tickets.append(module.submit(f, d))
        if len(tickets) > in_flight:
            out.append(module.collect(tickets.pop(0)))
    out += [module.collect(t) for t in tickets]
    return out, module


def test_module_scores_the_same_in_a_process_as_in_the_caller():
    frames = frames_with_repeats(120, 3, seed=0)
    dones = np.random.default_rng(1).random((120, 3)) < 0.08
    sync, m_sync = run_module("sync", frames, dones, 0)
    for mode, in_flight in (("process", 1), ("process", 4), ("thread", 4)):
        other, m_other = run_module(mode, frames, dones, in_flight)
        for (r1, n1), (r2, n2) in zip(sync, other):
            assert np.array_equal(r1, r2) and np.array_equal(n1, n2), mode
        assert np.array_equal(m_sync._goal_parts.numpy(), m_other._goal_parts.numpy())
        assert m_sync.cache_hits == m_other.cache_hits > 0
    r = np.concatenate([r for r, _ in sync])
    assert len(np.unique(r)) > 5  # the rewards vary: a constant would match trivially
    assert m_other.time_inference_background > 0 and m_other.cpu_inference_background > 0


def test_many_tickets_in_flight_do_not_block_the_pipes():
    """The answers not read yet stay below ``max_answer_bytes``: a caller that submits many tickets before it
    collects is not stuck writing to a child stuck writing its answers.
    Here 40 tickets of 64 new frames each are in flight, about 3.3 KB of answer each: 130 KB in all, twice the
    answer pipe's 64 KiB."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (40, 64, 16, 16, 3), dtype=np.uint8)  # all new: every row embedded and scored
    dones = np.zeros((40, 64), dtype=bool)
    result: dict = {}
    worker = threading.Thread(target=lambda: result.update(out=run_module("process", frames, dones, 40)), daemon=True)
    worker.start()
    worker.join(timeout=120)
    assert not worker.is_alive(), "the caller and the scoring process blocked each other"
    sync, _ = run_module("sync", frames, dones, 0)
    for (r1, n1), (r2, n2) in zip(sync, result["out"][0]):
        assert np.array_equal(r1, r2) and np.array_equal(n1, n2)
    assert result["out"][1]._process._answer_bytes == 0


def test_phi_of_a_ticket_in_flight_is_taken_from_the_process():
    """A state new to the embedding memo, seen again in the next ticket before the first is collected, is
    embedded once (by the first ticket) and the second ticket's phi comes from it."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, scoring_process=True, seed=0)
    module.pretrain()
    frame = np.random.default_rng(5).integers(0, 256, (1, 16, 16, 3), dtype=np.uint8)
    other = np.random.default_rng(6).integers(0, 256, (1, 16, 16, 3), dtype=np.uint8)
    first = module.submit(np.concatenate([frame, other]), np.zeros(2, bool))
    second = module.submit(np.concatenate([other, frame]), np.zeros(2, bool))  # each env sees the other's state
    assert len(second.phi_from) == 2 and len(second.embed_rows) == 0
    module.collect(second)
    expected = module.embed(np.concatenate([frame, other])).numpy()
    assert np.array_equal(first.phi, expected) and np.array_equal(second.phi, expected[::-1])
    assert np.array_equal(second.rewards, module.score_states(np.concatenate([other, frame])))


def chain_run(scoring_process: bool, before_learning=None, **kwargs) -> PPO_GoCu:
    """PPO_GoCu on 2 ChainEnvs, 640 steps (a predictor update every 128), seed 0; ``before_learning(model)`` runs
    just before ``learn``."""
    th.manual_seed(0)
    env = make_vec_env(lambda: ChainEnv(), n_envs=2, seed=0)
    curiosity = {**SMALL_CURIOSITY, "predictor_train_freq": 128, "scoring_process": scoring_process}
    model = PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=2, seed=0, curiosity_kwargs=curiosity, **kwargs)
    if before_learning is not None:
        before_learning(model)
    model.learn(640)
    return model


def assert_same_training(a: PPO_GoCu, b: PPO_GoCu) -> None:
    """The same intrinsic rewards in the last rollout, policy weights and VAE and predictor weights, to the bit."""
    assert np.array_equal(a.rollout_buffer.intrinsic_rewards, b.rollout_buffer.intrinsic_rewards)
    for (k, v), (k2, v2) in zip(a.policy.state_dict().items(), b.policy.state_dict().items()):
        assert k == k2 and th.equal(v, v2), k
    sa, sb = a.curiosity.state_dict(), b.curiosity.state_dict()
    for net in ("vae", "predictor"):
        assert all(th.equal(sa[net][k], sb[net][k]) for k in sa[net]), net


def test_ppo_gocu_with_a_scoring_process_matches_the_synchronous_run():
    """With 1 and with 5 steps in flight (``scoring_lag``), collected in order across the rollout's end."""
    runs = []
    settings = (
        dict(async_scoring=False),
        dict(async_scoring=True, scoring_process=True, scoring_lag=1),
        dict(async_scoring=True, scoring_process=True, scoring_lag=5),
    )
    for kwargs in settings:
        in_flight = []  # tickets outstanding at each collection

        def before_learning(model, in_flight=in_flight):
            collect = model.curiosity.collect
            model.curiosity.collect = lambda ticket: in_flight.append(len(model.curiosity._outstanding)) or collect(ticket)

        model = chain_run(kwargs.pop("scoring_process", False), before_learning, **kwargs)
        model.max_in_flight = max(in_flight, default=0)
        runs.append(model)
    a = runs[0]
    assert a.rollout_buffer.intrinsic_rewards.any()
    for b in runs[1:]:
        assert b.curiosity._process is not None and b.curiosity._scorer is None
        assert_same_training(a, b)
    assert [m.max_in_flight for m in runs[1:]] == [2, 6]  # the step just submitted and up to scoring_lag before it


def test_spilled_tickets_give_the_same_rewards(monkeypatch):
    """spill_scoring: tickets scored in the training thread instead of the process (here every other ticket,
    forced) give the same rewards and networks as the run that sends every ticket to the process."""
    from sb3_gocu.curiosity.scoring import ProcessScorer

    calls = [0]
    unanswered = ProcessScorer.unanswered

    def every_other(self):
        calls[0] += 1
        return 10**6 if calls[0] % 2 else unanswered(self)  # as if the process were far behind

    a = chain_run(True, scoring_lag=2, spill_scoring=False)
    b = chain_run(True, lambda _: monkeypatch.setattr(ProcessScorer, "unanswered", every_other), scoring_lag=2, spill_scoring=True)
    assert a.curiosity.spilled_tickets == 0 and b.curiosity.spilled_tickets > 10
    assert b.curiosity._process.bytes_sent < a.curiosity._process.bytes_sent  # fewer tickets went to the process
    assert b.curiosity.scoring_spill is None  # only during rollouts
    assert a.rollout_buffer.intrinsic_rewards.any()
    assert_same_training(a, b)


@pytest.mark.parametrize("value", [1, None, "yes"])
def test_spill_scoring_is_checked(value):
    with pytest.raises(ValueError, match=f"spill_scoring must be True or False, got {value!r}"):
        PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), spill_scoring=value)


@pytest.mark.parametrize("lag", [0, -1, 1.5, True, "2"])
def test_scoring_lag_is_checked(lag):
    with pytest.raises(ValueError, match=f"scoring_lag must be an int >= 1, got {lag!r}"):
        PPO_GoCu("MlpPolicy", make_vec_env(ChainEnv, n_envs=2, seed=0), scoring_lag=lag)


def test_a_dead_scoring_process_is_a_clear_error():
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, scoring_process=True, seed=0)
    frames = frames_with_repeats(2, 2, seed=2)
    module.collect(module.submit(frames[0], np.zeros(2, bool)))
    module._process._proc.kill()
    module._process._proc.wait()
    with pytest.raises(RuntimeError, match="scoring process ended"):
        module.collect(module.submit(frames_with_repeats(1, 2, seed=9)[0], np.zeros(2, bool)))


def test_scoring_process_default_and_start():
    """None picks a process for a CPU module on this (POSIX) machine; PPO_GoCu starts it at learn's start
    (beside pretraining), and a thread-scoring module refuses to start one."""
    assert GoalCuriosityModule(SPACE, **SMALL_CURIOSITY).scoring_process is True
    env = make_vec_env(lambda: ChainEnv(), n_envs=2, seed=0)
    model = PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, curiosity_kwargs=SMALL_CURIOSITY)
    assert model.curiosity._process is None
    model.learn(64)
    assert model.curiosity._process is not None and model.curiosity._process.bytes_sent > 0
    thread = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, scoring_process=False)
    with pytest.raises(ValueError, match="scores in a thread"):
        thread.start_scoring_process()


def test_scoring_process_rejects_bad_settings():
    with pytest.raises(ValueError, match="scoring_process must be True, False or None"):
        GoalCuriosityModule(SPACE, scoring_process="yes")
    with pytest.raises(ValueError, match="scoring_process needs device='cpu'"):
        GoalCuriosityModule(SPACE, scoring_process=True, device="meta")
    with pytest.raises(ValueError, match="num_threads must be >= 1"):
        ProcessScorer(None, num_threads=0)


def test_a_failure_in_the_scoring_process_is_raised_with_its_traceback():
    """The worker catches the error and sends its traceback; the training process raises it at collect."""
    module = GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, scoring_process=True, seed=0)
    small = GoalCuriosityModule(spaces.Box(0, 255, (8, 8, 3), np.uint8), **SMALL_CURIOSITY, seed=0)
    module._encoder = small._encoder  # built for 8x8 frames: its fully connected layer refuses 16x16 ones
    ticket = module.submit(frames_with_repeats(1, 2, seed=4)[0], np.zeros(2, bool))
    with pytest.raises(RuntimeError, match=r"scoring process failed:\n(.|\n)*Traceback(.|\n)*mat1 and mat2"):
        module.collect(ticket)


def test_bfloat16_scoring_is_the_same_in_a_process_and_close_to_float32():
    """``scoring_dtype="bfloat16"``: the process scores the same bits as the caller (the folded predictor it is
    sent keeps its dtype, also after the predictor update halfway), and r_gc stays within bfloat16 rounding of
    float32's while differing from it (the cast happens in the module, not only in the network's test)."""
    frames = frames_with_repeats(120, 3, seed=0)
    dones = np.random.default_rng(1).random((120, 3)) < 0.08
    sync, m_sync = run_module("sync", frames, dones, 0, scoring_dtype="bfloat16")
    proc, m_proc = run_module("process", frames, dones, 4, scoring_dtype="bfloat16")
    for (r1, n1), (r2, n2) in zip(sync, proc):
        assert np.array_equal(r1, r2) and np.array_equal(n1, n2)
    assert m_sync._folded.dtype == m_proc._folded.dtype == th.bfloat16
    f32, _ = run_module("sync", frames, dones, 0)
    raw_bf16 = np.concatenate([r for r, _ in sync])
    raw_f32 = np.concatenate([r for r, _ in f32])
    diff = np.abs(raw_bf16 - raw_f32)
    # r_gc = (1 - max_k m) / 10: bfloat16's rounding moves m by well under 1e-2 here
    assert 0 < diff.max() < 1e-3
    assert len(np.unique(raw_f32)) > 5


def test_scoring_dtype_is_checked_and_kept_by_a_save(tmp_path):
    with pytest.raises(ValueError, match="scoring_dtype must be one of \\('float32', 'bfloat16'\\), got 'float16'"):
        GoalCuriosityModule(SPACE, **SMALL_CURIOSITY, scoring_dtype="float16")
    env = make_vec_env(ChainEnv, n_envs=2, seed=0)
    curiosity = {**SMALL_CURIOSITY, "scoring_dtype": "bfloat16", "scoring_process": False}
    model = PPO_GoCu("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, curiosity_kwargs=curiosity)
    with th.no_grad():  # weights a fresh module would not have: the loaded fold must come from the saved ones
        for q in model.curiosity.predictor.parameters():
            q.add_(0.5)
    model.curiosity._folded = model.curiosity._fold()
    model.save(tmp_path / "m.zip")
    loaded = PPO_GoCu.load(tmp_path / "m.zip", env=env)
    assert loaded.curiosity.scoring_dtype == "bfloat16"
    for (w1, b1), (w2, b2) in zip(model.curiosity._folded.layers, loaded.curiosity._folded.layers):
        assert w2.dtype == th.bfloat16 and th.equal(w1, w2) and th.equal(b1, b2)


def gated_fits(monkeypatch) -> threading.Event:
    """Predictor fits that start only when the returned event is set (and clear it): a test decides how long an
    update overlapped with PPO's runs."""
    gate = threading.Event()
    fit = GoalCuriosityModule._fit_predictor

    def gated(self, *args, **kwargs):
        assert gate.wait(60), "the test never opened the gate"
        gate.clear()
        return fit(self, *args, **kwargs)

    monkeypatch.setattr(GoalCuriosityModule, "_fit_predictor", gated)
    return gate


def test_steps_queued_behind_an_update_give_the_same_training(monkeypatch):
    """queue_during_update: while a predictor update overlapped with PPO's still runs, the next rollout's steps wait
    in the module's queue and the envs step on; when it ends, the queue is submitted mid-rollout. The same rewards,
    policy and networks as the run whose first step waits for the update. Each fit here runs only after 5 steps
    have been submitted beside it, or when it is waited for."""
    gate = gated_fits(monkeypatch)

    def setup(queue: bool, replays: list):
        def before_learning(model):
            module = model.curiosity
            module.queue_during_update, module.overlap_ppo_update = queue, True
            module.vae_train_freq = 256  # a VAE update too (in the same job as a predictor update)
            submit, submit_queue, finish, beside, opened = module.submit, module._submit_queue, module.finish_background_update, [0], [None]

            def open_gate():  # once per update
                if module._job is not None and opened[0] is not module._job:
                    opened[0] = module._job
                    gate.set()

            def counting_submit(*args, **kwargs):
                beside[0] = beside[0] + 1 if module.update_running else 0
                if beside[0] == 5:
                    open_gate()
                return submit(*args, **kwargs)

            def opening_finish():  # whoever waits for the update opens the gate
                open_gate()
                return finish()

            def recorded_submit_queue():
                replays.append(len(module._queue))
                submit_queue()

            module.submit, module._submit_queue, module.finish_background_update = counting_submit, recorded_submit_queue, opening_finish

        return before_learning

    replays_a, replays_b = [], []
    a = chain_run(True, setup(False, replays_a))
    b = chain_run(True, setup(True, replays_b))
    assert a.curiosity.queued_steps == 0 and not any(replays_a)
    queued = [n for n in replays_b if n]
    assert len(queued) == 4, "each of the 4 updates beside PPO's queued steps"  # rollouts of 64 steps, an update after each
    assert all(5 <= n < 64 for n in queued), queued  # submitted while the rollout went on
    assert b.curiosity.queued_steps == sum(queued)
    assert_same_training(a, b)


def test_a_module_use_takes_the_queued_steps_first(monkeypatch):
    """Queued steps are submitted before anything else the module does: here a reset of env 0
    (``begin_episodes``) while steps wait behind an update, against the module that waits for the update."""
    gate = gated_fits(monkeypatch)
    frames = frames_with_repeats(40, 2, seed=7)
    dones = np.random.default_rng(8).random((40, 2)) < 0.15
    out = []
    for queue in (False, True):
        module = GoalCuriosityModule(SPACE, **{**SMALL_CURIOSITY, "predictor_train_freq": 40, "overlap_ppo_update": True}, revisit_decay="none",
                                     scoring_process=True, queue_during_update=queue, seed=3)
        module.recording = True
        gate.set()
        module.pretrain()
        rewards = [module.step(f, d) for f, d in zip(frames[:10], dones[:10])]
        module.add_finished_episode_goals()  # goals for the episodes begun from here
        rewards += [module.step(f, d) for f, d in zip(frames[10:30], dones[10:30])]
        module.add_finished_episode_goals()
        module.maybe_train()  # a predictor update, overlapped: its fit waits for the gate
        assert module.update_running
        if not queue:
            gate.set()  # the first submission waits for the update
        tickets = [module.submit(f, np.array([False, t == 32])) for t, f in enumerate(frames[30:35], 30)]
        assert [t.queued is not None for t in tickets] == [queue] * 5
        gate.set()
        module.begin_episodes(np.array([0]))
        assert not module._queue and all(t.queued is None for t in tickets)
        tickets += [module.submit(f, d) for f, d in zip(frames[35:], dones[35:])]
        rewards += [module.collect(t) for t in tickets]
        out.append((rewards, module.state_dict()))
    (ra, sa), (rb, sb) = out
    assert all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) for x, y in zip(ra, rb))
    assert len(np.unique(np.concatenate([r for r, _ in rb]))) > 5
    for net in ("vae", "predictor"):
        assert all(th.equal(sa[net][k], sb[net][k]) for k in sa[net]), net
    assert sa["counters"] == sb["counters"]
    # env 1's episode ended in the queue, env 0's by the reset after it: 2 episodes begun, in that order
    assert sa["envs"]["next_episode_id"] == sb["envs"]["next_episode_id"]
    assert th.equal(sa["envs"]["goal_parts"], sb["envs"]["goal_parts"])


@pytest.mark.parametrize("value", [1, None, "yes"])
def test_queue_during_update_is_checked(value):
    with pytest.raises(ValueError, match=f"queue_during_update must be True or False, got {value!r}"):
        GoalCuriosityModule(SPACE, queue_during_update=value)
