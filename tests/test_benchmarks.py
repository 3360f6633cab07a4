"""benchmarks/sample_efficiency.py and benchmarks/plot_curves.py with a tiny budget on DoorKey-5x5
(4 envs x 128 steps per rollout, tiny curiosity settings; about 40-60 s on 2 busy cores)."""

import csv
import json
import shutil

import numpy as np
import pytest
import torch as th

from sb3_gocu import PPO_GoCu

from conftest import TINY_IMAGE_CURIOSITY, LivesEnv, load_script

ROLLOUT = 4 * 128


@pytest.fixture(scope="module")
def se():
    return load_script("sample_efficiency", "benchmarks/sample_efficiency.py")


@pytest.fixture(scope="module")
def plot_curves():
    return load_script("plot_curves", "benchmarks/plot_curves.py")


def tiny_args(out, timesteps, *extra):
    return [
        "--env", "GoCu/DoorKey-5x5-v0", "--seeds", "0", "--timesteps", str(timesteps), "--out", str(out),
        "--n-envs", "4", "--n-steps", "128", "--batch-size", "256", "--threads", "1", "--checkpoint-freq", "1024",
        "--curiosity-kwargs", json.dumps(TINY_IMAGE_CURIOSITY), "--quiet", *extra,
    ]


def read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def two_runs(se, tmp_path_factory):
    """PPO and PPO_GoCu, seed 0, 2048 steps each."""
    th.set_num_threads(1)
    out = tmp_path_factory.mktemp("se")
    summary = se.main(tiny_args(out, 2048))
    return out, summary


def test_csvs_and_summary(se, two_runs):
    out, summary = two_runs
    for algo in ("ppo", "ppo_gocu"):
        path = out / f"{algo}_seed0.csv"
        rows = read(path)
        assert tuple(rows[0].keys()) == se.COLUMNS
        steps = [int(r["steps"]) for r in rows]
        assert steps == list(range(ROLLOUT, 2048 + 1, ROLLOUT)), steps
        assert all(r["algo"] == algo and r["seed"] == "0" for r in rows)
        episodes = [int(r["episodes"]) for r in rows]
        assert episodes == sorted(episodes) and episodes[-1] >= 4  # DoorKey-5x5 episodes end within 250 steps
        wall = [float(r["wall_time_s"]) for r in rows]
        assert wall == sorted(wall)
        last = rows[-1]
        assert 0.0 <= float(last["success_rate"]) <= 1.0 and 0.0 <= float(last["mean_return"]) <= 1.0
        # exploration: episodes that reached the goal also had the key and opened the door
        assert float(last["success_rate"]) <= float(last["door_rate"]) <= float(last["key_rate"]) <= 1.0
        assert float(last["key_rate"]) > 0.0  # a near-random policy picks up the key on DoorKey-5x5
        # DoorKey's last step succeeds exactly when the episode's return is positive; it reports no distance
        assert last["final_success"] == last["success_rate"] and all(r["final_distance"] == "" for r in rows)
        intrinsic = [r["intrinsic_mean"] for r in rows]
        if algo == "ppo":
            assert all(v == "" for v in intrinsic) and all(r["goals"] == "" for r in rows)
        else:
            assert 1 <= int(rows[-1]["goals"]) <= TINY_IMAGE_CURIOSITY["goal_buffer_size"]
            assert all(0.0 <= float(v) <= 0.1 + 1e-6 for v in intrinsic)  # raw r_gc in [0, alpha / delta]
        assert (out / "checkpoints" / f"{algo}_seed0" / "model_2048.zip").is_file()
    md = (out / "summary.md").read_text()
    assert md.strip() in summary
    for text in ("| ppo |", "| ppo_gocu |", "steps to mean return >= 0.9", "command:", "seeds: 0", "machine (runs):", "threads: 1"):
        assert text in md, text
    # a finished run is skipped, and --summary-only rewrites the summary from the CSVs
    before = read(out / "ppo_seed0.csv")
    se.main(tiny_args(out, 2048, "--algos", "ppo"))
    assert read(out / "ppo_seed0.csv") == before
    (out / "summary.md").unlink()
    se.main(["--out", str(out), "--summary-only", "--threads", "1"])
    md = (out / "summary.md").read_text()
    assert "| ppo_gocu |" in md and md.startswith("# Sample efficiency: GoCu/DoorKey-5x5-v0\n")  # from the checkpoints
    # CSVs alone (a results folder): the env is not guessed
    csvs = out.parent / (out.name + "_csvs")
    csvs.mkdir()
    for path in out.glob("*_seed*.csv"):
        shutil.copy(path, csvs / path.name)
    se.main(["--out", str(csvs), "--summary-only", "--threads", "1"])
    assert (csvs / "summary.md").read_text().startswith("# Sample efficiency: env not recorded in --out (pass --env)\n")
    se.main(["--env", "GoCu/DoorKey-5x5-v0", "--out", str(csvs), "--summary-only", "--threads", "1"])
    assert (csvs / "summary.md").read_text().startswith("# Sample efficiency: GoCu/DoorKey-5x5-v0\n")


def test_other_settings_refused(se, two_runs):
    out, _ = two_runs
    with pytest.raises(SystemExit, match="other settings"):
        se.main(tiny_args(out, 4096, "--algos", "ppo_gocu", "--n-goals", "3"))


def test_plot(plot_curves, two_runs, tmp_path):
    out, _ = two_runs
    png = plot_curves.main([str(out), "--out", str(tmp_path / "curves.png")])
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    png2 = plot_curves.plot(out, tmp_path / "sr.png", metric="success_rate", band="std")
    assert png2.stat().st_size > 1000


def test_plot_threshold_line_only_when_asked(plot_curves, two_runs, tmp_path, monkeypatch):
    import matplotlib.axes

    lines = []
    monkeypatch.setattr(matplotlib.axes.Axes, "axhline", lambda ax, y=0, *a, **k: lines.append(y))
    out, _ = two_runs
    plot_curves.main([str(out), "--out", str(tmp_path / "a.png")])
    assert lines == [0.9]  # the DoorKey success threshold, by default
    plot_curves.main([str(out), "--out", str(tmp_path / "b.png"), "--threshold", "none"])  # Atari: no threshold
    assert lines == [0.9]


def test_spread_labels_by_hand(plot_curves):
    """Overlapping labels are stacked one height apart around their anchors' mean, inside the axes; labels apart
    in x, or in y by at least a height, stay where they are."""
    spread = plot_curves.spread_labels
    assert spread([(0.5, 0.5), (0.5, 0.5)], 0.1, 0.1) == pytest.approx([0.45, 0.55])
    assert spread([(0.1, 0.5), (0.5, 0.5), (0.5, 0.7)], 0.1, 0.1) == pytest.approx([0.5, 0.5, 0.7])
    # three at the same end: stacked in the order of their y, the middle one on the mean
    assert spread([(0.5, 0.52), (0.5, 0.48), (0.55, 0.5)], 0.1, 0.1) == pytest.approx([0.6, 0.4, 0.5])
    assert spread([(0.5, 0.0), (0.52, 0.01)], 0.1, 0.1) == pytest.approx([0.05, 0.15])  # moved up into the axes
    assert spread([(0.5, 0.99)] * 3, 0.1, 0.1) == pytest.approx([0.75, 0.85, 0.95])  # moved down into the axes
    # a chain: b overlaps a, and c overlaps the stack of a and b, so all three are stacked
    assert spread([(0.3, 0.5), (0.35, 0.5), (0.42, 0.45)], 0.1, 0.1) == pytest.approx([0.4833333, 0.5833333, 0.3833333])
    with pytest.raises(ValueError, match="width and height"):
        spread([(0.5, 0.5)], 0.0, 0.1)


def test_plot_of_several_folders(plot_curves, two_runs, tmp_path):
    """Runs from two folders go on one figure; a seed of one algo in both, or two envs, is refused."""
    out, _ = two_runs
    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir(), second.mkdir()
    shutil.copy(out / "ppo_gocu_seed0.csv", first / "ppo_gocu_seed0.csv")
    shutil.copy(out / "ppo_seed0.csv", second / "ppo_seed1.csv")  # as if seed 1 had run elsewhere
    runs = plot_curves.load_folders([first, second], "mean_return")
    assert {algo: sorted(seeds) for algo, seeds in runs.items()} == {"ppo_gocu": [0], "ppo": [1]}
    png = plot_curves.main([str(first), str(second), "--per-seed"])
    assert png == first / "curves.png" and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    shutil.copy(out / "ppo_gocu_seed0.csv", second / "ppo_gocu_seed0.csv")
    with pytest.raises(SystemExit, match="ppo_gocu seed 0 is in both"):
        plot_curves.plot([first, second])
    (second / "ppo_gocu_seed0.csv").unlink()
    (first / "summary.md").write_text("# Sample efficiency: GoCu/DoorKey-5x5-v0\n")
    (second / "summary.md").write_text("# Sample efficiency: GoCu/DoorKey-8x8-v0\n")
    with pytest.raises(SystemExit, match="different envs"):
        plot_curves.plot([first, second])


def test_plot_draws_folders_as_named_arms(plot_curves, two_runs, tmp_path):
    """NAME=FOLDER draws a folder's runs as the arm NAME (two folders of ppo_gocu runs: two arms); --seeds keeps those."""
    out, _ = two_runs
    first, second = tmp_path / "random", tmp_path / "late"
    first.mkdir(), second.mkdir()
    for folder in (first, second):
        shutil.copy(out / "ppo_gocu_seed0.csv", folder / "ppo_gocu_seed0.csv")
        shutil.copy(out / "ppo_gocu_seed0.csv", folder / "ppo_gocu_seed3.csv")
    runs = plot_curves.load_folders([first, second], "mean_return", ["random", "late"], seeds=[0])
    assert {arm: sorted(seeds) for arm, seeds in runs.items()} == {"random": [0], "late": [0]}
    png = plot_curves.main([f"random={first}", f"late={second}", "--seeds", "0", "--out", str(tmp_path / "arms.png")])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(SystemExit, match="ppo_gocu seed 0 is in both"):  # unnamed, the same algo and seed clash
        plot_curves.plot([first, second])


def test_plot_names_the_env_of_a_results_folder(plot_curves, two_runs, tmp_path):
    """A folder copied to benchmarks/results keeps summary.md but not the checkpoints: the env id comes from the
    summary's heading, and a heading without an id (the run's env not recorded) gives none."""
    out, _ = two_runs
    env = plot_curves.env_name(out)  # from the checkpoints' state files
    assert env == "GoCu/DoorKey-5x5-v0"
    copied = tmp_path / "results"
    copied.mkdir()
    (copied / "summary.md").write_text((out / "summary.md").read_text())
    assert plot_curves.env_name(copied) == env
    (copied / "summary.md").write_text("# Sample efficiency: env not recorded in --out (pass --env)\n")
    assert plot_curves.env_name(copied) is None


def test_resume_after_crash(se, tmp_path, monkeypatch):
    """A run killed after its 2048-step checkpoint continues from there on the same command."""
    out = tmp_path / "crash"
    original = se.SampleEfficiencyCallback._on_rollout_end

    def crash(self):
        original(self)
        if self.num_timesteps >= 2048 + ROLLOUT:
            raise RuntimeError("simulated crash")

    monkeypatch.setattr(se.SampleEfficiencyCallback, "_on_rollout_end", crash)
    with pytest.raises(RuntimeError, match="simulated crash"):
        se.main(tiny_args(out, 3072, "--algos", "ppo_gocu"))
    ckpt = out / "checkpoints" / "ppo_gocu_seed0"
    assert sorted(p.name for p in ckpt.glob("state_*.json")) == ["state_1024.json", "state_2048.json"]
    assert [int(r["steps"]) for r in read(out / "ppo_gocu_seed0.csv")][-1] == 2048 + ROLLOUT  # the live CSV ran ahead
    episodes_at_ckpt = json.loads((ckpt / "state_2048.json").read_text())["episodes"]

    monkeypatch.setattr(se.SampleEfficiencyCallback, "_on_rollout_end", original)
    se.main(tiny_args(out, 3072, "--algos", "ppo_gocu"))
    rows = read(out / "ppo_gocu_seed0.csv")
    steps = [int(r["steps"]) for r in rows]
    assert steps == list(range(ROLLOUT, 3072 + 1, ROLLOUT)), steps  # continued past 2048, no restart, no repeat
    state = json.loads((ckpt / "state_3072.json").read_text())
    assert state["resumed_from"] == [2048] and state["done"]
    assert int(rows[-1]["episodes"]) >= episodes_at_ckpt
    wall = [float(r["wall_time_s"]) for r in rows]
    assert wall == sorted(wall)
    assert not list(ckpt.glob(".*tmp"))  # no temporary files left behind
    # a truncated model file is not taken for a checkpoint (the resumption falls back to an older one)
    good = ckpt / "model_3072.zip"
    bad = tmp_path / "truncated.zip"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    assert se.model_readable(good) and not se.model_readable(bad)


def test_stop_at_threshold(se, tmp_path):
    """--stop-at-threshold ends a PPO_GoCu run at the first rollout end that reaches the threshold (here 0.0 over
    a window of 1 episode: the first row with an episode), checkpointed there; the flag then skips the run, and a
    command without it continues the run to --timesteps."""
    from sb3_gocu import PPO_GoCu

    out = tmp_path / "stop"
    args = tiny_args(out, 3072, "--algos", "ppo_gocu", "--threshold", "0.0", "--min-window", "1")
    se.main(args + ["--stop-at-threshold"])
    rows = read(out / "ppo_gocu_seed0.csv")
    first = next(int(r["steps"]) for r in rows if int(r["window_episodes"]) >= 1)
    assert int(rows[-1]["steps"]) == first < 3072, "the CSV ends at the row that reached the threshold"
    ckpt = out / "checkpoints" / "ppo_gocu_seed0"
    steps, state_path = se.list_checkpoints(ckpt)[-1]
    state = json.loads(state_path.read_text())
    assert steps == first and state["stopped_at_threshold"] == first and not state["done"]
    assert PPO_GoCu.load(ckpt / f"model_{first}.zip", device="cpu").num_timesteps == first, "no step after the checkpoint"
    # with the flag again: skipped, nothing rewritten
    se.main(args + ["--stop-at-threshold"])
    assert read(out / "ppo_gocu_seed0.csv") == rows and se.list_checkpoints(ckpt)[-1][0] == first
    # without it: continued from that checkpoint to the budget
    se.main(args)
    continued = read(out / "ppo_gocu_seed0.csv")
    assert continued[: len(rows)] == rows
    assert [int(r["steps"]) for r in continued] == list(range(ROLLOUT, 3072 + 1, ROLLOUT))
    state = json.loads((ckpt / "state_3072.json").read_text())
    assert state["done"] and state["stopped_at_threshold"] is None and state["resumed_from"] == [first]


def test_steps_to_threshold(se):
    rows = [
        {"steps": 100, "window_episodes": 50, "mean_return": 0.95},  # window not full yet: does not count
        {"steps": 200, "window_episodes": 100, "mean_return": 0.85},
        {"steps": 300, "window_episodes": 100, "mean_return": 0.91},
        {"steps": 400, "window_episodes": 100, "mean_return": 0.80},
    ]
    assert se.steps_to_threshold(rows, 0.9, 100) == 300
    assert se.steps_to_threshold(rows, 0.9, 10) == 100
    assert se.steps_to_threshold(rows, 0.99, 100) is None
    for r, wall in zip(rows, (10.0, 20.0, 30.0, 40.0)):
        r["wall_time_s"] = wall
    assert se.wall_time_to_threshold(rows, 0.9, 100) == 30.0  # the wall time at the row that reached it
    assert se.wall_time_to_threshold(rows, 0.99, 100) is None


def test_behaviour_compares_agent_and_random_policy(two_runs):
    behaviour = load_script("behaviour", "benchmarks/probes/behaviour.py")
    out, _ = two_runs
    model = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    result = behaviour.main([str(model), "--env", "GoCu/DoorKey-5x5-v0", "--episodes", "2", "--seed", "3"])
    for policy in ("agent", "random"):
        r = result[policy]
        assert abs(sum(r["action_share"].values()) - 1.0) < 1e-9
        assert len(r["cells_per_episode"]) == 2 and all(1 <= c <= 9 for c in r["cells_per_episode"])  # 3x3 floor
        assert all(0 <= ph <= 3 for ph in r["phases"])
        assert 0.0 <= r["mean_raw_r_gc"] <= 0.1 + 1e-6  # raw r_gc in [0, alpha / delta]
    assert len(result["random"]["action_share"]) == 7  # 2 x 250 uniform draws hit every action
    assert result["agent"]["action_share"] != result["random"]["action_share"]  # two policies, two behaviours
    again = behaviour.main([str(model), "--env", "GoCu/DoorKey-5x5-v0", "--episodes", "2", "--seed", "3"])
    assert again["random"]["cells_per_episode"] == result["random"]["cells_per_episode"]  # seeded: replayed the same


def test_predictor_epochs_probe_replays_the_update_per_budget(two_runs):
    """Every budget starts from the checkpoint's predictor; the largest budget's last epoch is the reference."""
    probe = load_script("predictor_epochs", "benchmarks/probes/predictor_epochs.py")
    out, _ = two_runs
    model = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    result = probe.main([str(model), "--pairs", "64", "256", "--epochs", "3", "--val-pairs", "128", "--threads", "1"])
    curves = result["curves"]
    assert sorted(curves) == [64, 256]
    for budget, rows in curves.items():
        assert [r["epoch"] for r in rows] == [1, 2, 3]
        assert all(0 < r["distinct_pairs"] <= budget for r in rows)
        assert [r["train_s"] for r in rows] == sorted(r["train_s"] for r in rows)
        assert all(0.0 <= r["val_acc"] <= 1.0 and r["val_loss"] > 0 for r in rows)
    assert curves[256][-1]["mean_abs_diff_ref"] == 0.0  # the reference against itself
    assert curves[64][-1]["mean_abs_diff_ref"] > 0.0  # trained on other pairs: another predictor
    # the same budget replayed twice gives the same predictor (same draws, same generator)
    again = probe.main([str(model), "--pairs", "64", "256", "--epochs", "3", "--val-pairs", "128", "--threads", "1"])
    assert again["curves"][64][-1]["val_loss"] == curves[64][-1]["val_loss"]


def test_pixel_weights_cost_times_the_fit_and_both_steps_on_a_saved_models_bank(two_runs):
    bench = load_script("pixel_weights_cost", "benchmarks/probes/pixel_weights_cost.py")
    out, _ = two_runs
    model_path = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    r = bench.main(["--model", str(model_path), "--batch", "8", "--steps", "2", "--repeats", "1"])
    memory = PPO_GoCu.load(model_path).curiosity.memory
    bank = memory.observations[: memory.size]
    # the bank is the saved model's observation memory, fitted on its distinct frames
    assert r["bank"] == len(bank) and r["distinct"] == len(np.unique(bank.reshape(len(bank), -1), axis=0)) < r["bank"]
    assert r["weight_min"] < 1 < r["weight_max"], "common colours weigh less than 1, rare ones more"
    assert set(r["step_s"]) == {"unweighted", "weighted"}


def test_view_aliasing_renders_every_standable_cell_of_each_phase():
    """DoorKey-5x5, layout 0: the key phase covers the left room (the key's cell too: it is carried), the door
    phase adds the door's cell and the right room; 4 directions each. A right-room view counts as aliased
    exactly when it is one of the left room's views."""
    import gymnasium as gym

    va = load_script("view_aliasing", "benchmarks/probes/view_aliasing.py")
    env = gym.make("GoCu/DoorKey-5x5-v0")
    env.reset(seed=0)
    base = env.unwrapped
    objects = va.curiosity_map.find_objects(base)
    door_x = objects[3][0]
    inner_h = base.height - 2
    left = va.phase_views(env, "key", objects)
    both = va.phase_views(env, "door_open", objects)
    assert len(left) == 4 * (door_x - 1) * inner_h
    assert len(both) == 4 * ((base.width - 3) * inner_h + 1)
    assert {k for k in both if k[0] < door_x} == set(left)
    right = [v for k, v in both.items() if k[0] > door_x]
    expected = sum(v in set(left.values()) for v in right) / len(right)
    r = va.aliasing("GoCu/DoorKey-5x5-v0", 1)
    assert r["same_layout_mean"] == pytest.approx(expected) and r["any_layout"] == pytest.approx(expected)
    assert r["right_views_per_layout"] == len(right)
    env.close()


def test_mean_curve_of_runs_of_different_lengths(plot_curves):
    """Two seeds, one stopped at 3,000 steps: the plain mean rests on the longer run alone after 3,000 steps;
    with all_seeds it stops at 3,000, and its values are the mean of both seeds."""
    short = (np.array([1000.0, 2000.0, 3000.0]), np.array([0.0, 0.5, 1.0]))
    long = (np.array([1000.0, 2000.0, 3000.0, 4000.0, 5000.0]), np.array([0.0, 0.1, 0.2, 0.3, 0.4]))
    x, mean, lo, hi = plot_curves.mean_curve([short, long], "minmax")
    assert x[-1] == 5000.0 and mean[-1] == pytest.approx(0.4)  # the tail: one seed
    x, mean, lo, hi = plot_curves.mean_curve([short, long], "minmax", all_seeds=True)
    np.testing.assert_allclose(x, [1000.0, 2000.0, 3000.0])
    np.testing.assert_allclose(mean, [0.0, 0.3, 0.6])
    np.testing.assert_allclose(lo, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(hi, [0.0, 0.5, 1.0])


def test_compare_runs_finds_the_first_differing_row(two_runs, tmp_path, capsys):
    compare = load_script("compare_runs", "benchmarks/compare_runs.py")
    out, _ = two_runs
    original = out / "ppo_gocu_seed0.csv"
    rows = read(original)
    assert len(rows) >= 3
    compare.main([str(original), str(original)])
    assert f"rows compared: {len(rows)} (to {rows[-1]['steps']} steps); rows differing: 0" in capsys.readouterr().out
    rows[2]["intrinsic_mean"] = str(float(rows[2]["intrinsic_mean"]) + 1e-6)
    changed = tmp_path / "changed.csv"
    with open(changed, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with pytest.raises(SystemExit) as exit_info:
        compare.main([str(original), str(changed)])
    assert exit_info.value.code == 1
    printed = capsys.readouterr().out
    assert "rows differing: 1" in printed and f"first at {rows[2]['steps']} steps: intrinsic_mean" in printed


@pytest.fixture(scope="module")
def ep():
    return load_script("embedding_phases", "benchmarks/probes/embedding_phases.py")


def test_embedding_phases_views_change_only_where_the_state_does(ep):
    """DoorKey-8x8, layout 0: the carried key changes every pose's view, and only in the bottom row of cells (the
    agent's own cell); the key on the floor and the open door change only the poses that see them; one step's
    pixel distance is the direct computation."""
    views = ep.layout_views("GoCu/DoorKey-8x8-v0", 0)
    assert set(views) == set(ep.STATES) and all(set(v) == set(views["bare"]) for v in views.values())
    cell = 32 // 7 + 1  # the 7x7 view resized to 32x32: the agent's row is within the bottom 5 pixel rows
    for pose in views["bare"]:
        diff = np.abs(views["carried"][pose].astype(int) - views["bare"][pose]).sum(-1)
        assert diff.any() and not diff[: 32 - cell].any()
    seen = [not np.array_equal(views["floor_key"][p], views["bare"][p]) for p in views["bare"]]
    opened = [not np.array_equal(views["door_open"][p], views["carried"][p]) for p in views["bare"]]
    assert 0 < sum(seen) < len(seen) and 0 < sum(opened) < len(opened)
    d = ep.distances(views, ep.pixels)
    assert len(d["carried"]) == len(views["bare"]) and len(d["floor_key"]) == sum(seen) and len(d["door_open"]) == sum(opened)
    first, nxt = next((p, q) for p in views["bare"] for q in ((p[0] + 1, p[1], p[2]), (p[0], p[1] + 1, p[2])) if q in views["bare"])
    a, b = views["bare"][first], views["bare"][nxt]
    assert np.linalg.norm(ep.pixels(a[None]) - ep.pixels(b[None])) == pytest.approx(d["step"][0])
    s = ep.summarise([d])
    assert s["carried/step"] == pytest.approx(np.median(d["carried"]) / np.median(d["step"]))


def test_embedding_phases_refit_leaves_the_model_as_it_was(ep, two_runs):
    """A refit retrains a copy on the memory bank (another phi), a fresh one takes the asked latent size, and the
    model's VAE, optimiser and settings are the ones it had."""
    out, _ = two_runs
    model = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    from sb3_gocu import PPO_GoCu

    module = PPO_GoCu.load(model, device="cpu").curiosity
    before = {k: v.clone() for k, v in module.vae.state_dict().items()}
    optimiser, beta, last = module.trainer.vae_optimizer, module.vae_beta, module.last_vae_update
    vae, fit = ep.refit_vae(module, {"vae_epochs": 2, "vae_beta": 0.5})
    assert fit["epochs_run"] == 2 and vae is not module.vae
    assert any(not th.equal(before[k], v) for k, v in vae.state_dict().items())
    assert all(th.equal(before[k], v) for k, v in module.vae.state_dict().items())
    assert module.trainer.vae_optimizer is optimiser and module.vae_beta == beta and module.last_vae_update == last
    fresh, _ = ep.refit_vae(module, {"vae_epochs": 1, "latent_dim": 3})
    assert fresh.mu.out_features == 3
    with pytest.raises(ValueError, match="vae_lr"):
        ep.refit_vae(module, {"vae_lr": 1e-3})
    r = ep.measure(str(model), "GoCu/DoorKey-8x8-v0", 1, [{"vae_epochs": 1}])  # same 32x32 views, more cells than 5x5
    assert r["steps"] == 2048 and len(r["refits"]) == 1
    for key in ("pixels", "phi"):
        assert r[key]["step"] > 0 and r[key]["carried/step"] == pytest.approx(r[key]["carried"] / r[key]["step"])
    assert r["refits"][0]["step"] != r["phi"]["step"]


def test_throughput_benchmark_times_each_arm_and_shows_equal_weights_for_wall_time_options(tmp_path, capsys):
    """benchmarks/throughput.py, tiny (DoorKey-5x5, 4,096 steps, tiny curiosity): a second arm with the defaults
    trains the same weights, an arm that changes
    the training (another ``predictor_lr``) does not, and each arm's time is split into its parts; ``--reverse``
    runs the arms in the other order; ``--past 2048`` times the second rollout on, and the summary line gives both
    ratios; ``--also-sum`` adds the drop-in pipeline (plain PPO on the sum-mode wrapper)."""
    bench = load_script("throughput", "benchmarks/throughput.py")
    threads = th.get_num_threads()
    curiosity = TINY_IMAGE_CURIOSITY
    try:
        results = bench.main([
            "--env", "GoCu/DoorKey-5x5-v0", "--timesteps", "4096", "--threads", "1", "--malloc", "default",
            "--curiosity-kwargs", json.dumps(curiosity), "--json", str(tmp_path / "t.json"), "--past", "2048",
            "--reverse", "--also-arm", json.dumps({}),
            "--also-arm", json.dumps({"curiosity": {"predictor_lr": 1e-2}}), "--also-sum",
        ])
    finally:
        th.set_num_threads(threads)
    assert list(results) == ["ppo_sum", "ppo_gocu_arm_1", "ppo_gocu_arm_0", "ppo_gocu", "ppo"], "--reverse: the last arm first"
    dropin = results["ppo_sum"]  # plain PPO on the sum-mode wrapper: the module scores, pretrains and trains
    assert dropin["steps"] == 4096 and dropin["curiosity_inference_s"] > 0 and dropin["pretrain_s"] > 0 and dropin["predictor_training_s"] > 0
    ppo, gocu, again, other_lr = (results[k] for k in ("ppo", "ppo_gocu", "ppo_gocu_arm_0", "ppo_gocu_arm_1"))
    assert gocu["weights_sha256"] == again["weights_sha256"]
    assert len({ppo["weights_sha256"], gocu["weights_sha256"], other_lr["weights_sha256"]}) == 3
    for r in (ppo, gocu, again, other_lr):
        assert r["steps"] == 4096 and r["steps_per_s"] > 0 and r["env_s"] > 0 and r["ppo_update_s"] > 0
        assert r["past_from_step"] == 2048 and r["past_steps_per_s"] > 0  # the second rollout of 16 x 128 steps on
    for r in (gocu, again, other_lr):
        assert r["pretrain_s"] > 0 and r["curiosity_inference_s"] > 0 and r["predictor_training_s"] > 0
    saved = json.loads((tmp_path / "t.json").read_text())
    assert saved["ppo_gocu"]["weights_sha256"] == gocu["weights_sha256"] and saved["command"][1:3] == ["--env", "GoCu/DoorKey-5x5-v0"]
    last = capsys.readouterr().out.strip().splitlines()[-1]
    ratio, past_ratio = ppo["steps_per_s"] / gocu["steps_per_s"], ppo["past_steps_per_s"] / gocu["past_steps_per_s"]
    assert last.startswith(f"summary: a PPO_GoCu step costs {ratio:.2f}x plain PPO's time (4,096 steps, from scratch")
    assert f"; {past_ratio:.2f}x past step 2,048)" in last




def test_ppo_sum_resumes_with_its_module(se, tmp_path):
    """ppo_sum (plain PPO on the sum-mode wrapper) checkpoints its curiosity module beside the model and resumes it."""
    out = tmp_path / "sum"
    se.main(tiny_args(out, 2048, "--algos", "ppo_sum"))
    rows = read(out / "ppo_sum_seed0.csv")
    assert [int(r["steps"]) for r in rows][-1] == 2048
    assert all(r["intrinsic_mean"] != "" and float(r["goals"]) > 0 for r in rows)  # the wrapper's r_gc and goals
    ckpt = out / "checkpoints" / "ppo_sum_seed0"
    state = th.load(ckpt / "curiosity_2048.pth", weights_only=True)
    assert state["counters"]["pretrained"]
    se.main(tiny_args(out, 3072, "--algos", "ppo_sum"))
    rows = read(out / "ppo_sum_seed0.csv")
    assert [int(r["steps"]) for r in rows][-1] == 3072 and len(rows) == 6
    assert sorted(p.name for p in ckpt.glob("curiosity_*.pth")) == ["curiosity_2048.pth", "curiosity_3072.pth"]
    resumed = th.load(ckpt / "curiosity_3072.pth", weights_only=True)["counters"]
    # the module continued from the checkpoint's counts (a fresh one would hold 1,024 recorded steps, not 2,048 more)
    assert resumed["n_recorded_steps"] == state["counters"]["n_recorded_steps"] + 1024
    # the replay-age probe scores the newer module's states with both checkpoints' curiosity
    probe = load_script("replay_age", "benchmarks/probes/replay_age.py")
    r = probe.main([str(ckpt), "--states", "64"])
    assert (r["older"], r["newer"], r["states"]) == (2048, 3072, 64)
    assert probe.load_module(ckpt, 3072).n_recorded_steps == resumed["n_recorded_steps"]
    assert r["mean_newer"] > 0 and r["mean_abs_change_rel"] > 0, "1,024 steps of updates and new goals change the scores"
    assert probe.ranks(np.array([0.3, 0.1, 0.2])).tolist() == [2, 0, 1]
    with pytest.raises(SystemExit):
        probe.main([str(ckpt), "--older", "3072", "--newer", "2048"])


@pytest.mark.parametrize("algo", ["a2c_sum", "dqn_sum"])
def test_other_learners_run_with_their_zoo_settings_and_resume(se, tmp_path, algo, capsys):
    """a2c_sum / dqn_sum (the paper's Fig. 6): SB3's A2C / DQN with the settings of sb3_gocu/hyperparams/<a2c|dqn>.yml on
    the sum-mode wrapper; one CSV row per PPO rollout's steps although their rollouts are shorter; a resumed DQN waits
    for its emptied replay buffer to refill before its next gradient step."""
    from stable_baselines3 import A2C, DQN

    from sb3_gocu import PaperCNN

    out = tmp_path / algo
    dqn = algo.startswith("dqn")
    extra = ["--algos", algo, "--model-kwargs", json.dumps({"learning_starts": 256, "buffer_size": 4096} if dqn else {})]
    se.main(tiny_args(out, 2048, *extra))
    steps = [int(r["steps"]) for r in read(out / f"{algo}_seed0.csv")]
    rollout = 4 if dqn else 4 * 5  # n_envs x (train_freq 1 | n_steps 5)
    # a row at the first rollout end at or past each multiple of 4 x 128 = 512 steps
    assert steps == [-(-m // rollout) * rollout for m in (512, 1024, 1536, 2048)]
    rows = read(out / f"{algo}_seed0.csv")
    assert all(r["intrinsic_mean"] != "" and float(r["goals"]) > 0 for r in rows)  # the wrapper's r_gc and goals
    ckpt = out / "checkpoints" / f"{algo}_seed0"
    (last,) = [p for p in ckpt.glob("model_*.zip") if int(p.stem.split("_")[1]) >= 2048]
    model = (DQN if dqn else A2C).load(last)
    assert isinstance(model.policy.features_extractor if not dqn else model.q_net.features_extractor, PaperCNN)
    if dqn:
        assert (model.gradient_steps, model.batch_size, model.learning_starts) == (4, 32, 256)
    else:
        assert (model.n_steps, model.gae_lambda, model.learning_rate) == (5, 0.95, 1e-3)
    first = th.load(ckpt / f"curiosity_{last.stem.split('_')[1]}.pth", weights_only=True)["counters"]
    assert first["pretrained"]
    se.main(tiny_args(out, 3072, *extra))
    rows = read(out / f"{algo}_seed0.csv")
    assert int(rows[-1]["steps"]) >= 3072 and len(rows) == 6
    (end,) = [p for p in ckpt.glob("model_*.zip") if int(p.stem.split("_")[1]) >= 3072]
    resumed = th.load(ckpt / f"curiosity_{end.stem.split('_')[1]}.pth", weights_only=True)["counters"]
    # the module continued from the checkpoint's counts: one recorded step per env step since it
    steps_between = int(end.stem.split("_")[1]) - int(last.stem.split("_")[1])
    assert resumed["n_recorded_steps"] == first["n_recorded_steps"] + steps_between
    if dqn:  # the resumed run refilled its buffer before its next gradient step
        assert "the replay buffer starts empty" in capsys.readouterr().out


def test_refill_before_training_holds_the_gradient_steps(se):
    """A resumed DQN trains only once its emptied replay buffer holds learning_starts transitions again."""
    from stable_baselines3 import DQN
    from stable_baselines3.common.env_util import make_vec_env

    model = DQN("MlpPolicy", make_vec_env("CartPole-v1", n_envs=2, seed=0), learning_starts=64, buffer_size=1000, seed=0)
    calls = []
    model.train = lambda gradient_steps, batch_size=100: calls.append(model.replay_buffer.size() * model.n_envs)
    se.refill_before_training(model)
    model.num_timesteps = 10_000  # as after a resumption: past learning_starts, the buffer empty
    model.learn(200, reset_num_timesteps=False)
    assert calls and min(calls) >= 64


def test_ppo_rnd_runs_and_resumes_with_its_rnd_state(se, tmp_path):
    """ppo_rnd (the RND peer, benchmarks/peers/rnd.py): its intrinsic columns are RND's, and a resumed run continues
    from the checkpoint's RND statistics and predictor."""
    out = tmp_path / "rnd"
    se.main(tiny_args(out, 2048, "--algos", "ppo_rnd"))
    rows = read(out / "ppo_rnd_seed0.csv")
    assert [int(r["steps"]) for r in rows][-1] == 2048
    assert all(float(r["intrinsic_mean"]) > 0 and float(r["intrinsic_norm_mean"]) > 0 and r["goals"] == "" for r in rows)
    model = se.PPO_RND.load(out / "checkpoints" / "ppo_rnd_seed0" / "model_2048.zip")
    assert model.rnd.obs_stats.count.item() == 2048  # every reached state updated the observation statistics
    se.main(tiny_args(out, 3072, "--algos", "ppo_rnd"))
    rows = read(out / "ppo_rnd_seed0.csv")
    assert [int(r["steps"]) for r in rows][-1] == 3072 and len(rows) == 6
    resumed = se.PPO_RND.load(out / "checkpoints" / "ppo_rnd_seed0" / "model_3072.zip")
    assert resumed.rnd.obs_stats.count.item() == 3072  # continued from the checkpoint's statistics, not from zero


def record_scores(scorer, into: list) -> None:
    """Wrap ``scorer.score`` (as it is now) so that a copy of every batch of rewards it returns lands in ``into``."""
    score = scorer.score

    def recording(*args):
        rewards, phi = score(*args)
        into.append(rewards.copy())
        return rewards, phi

    scorer.score = recording


def test_constant_curiosity_pays_one_value(se, tmp_path):
    """--constant-curiosity: every paid r_gc of a rollout is one value (the running mean), unpaid revisits 0."""
    out = tmp_path / "constant"
    seen = []
    original = se.replace_curiosity

    def spy(module, how):
        original(module, how)
        record_scores(module.scorer, seen)

    se.replace_curiosity = spy
    try:
        se.main(tiny_args(out, 1024, "--algos", "ppo_gocu", "--constant-curiosity"))
    finally:
        se.replace_curiosity = original
    assert len(seen) > 100
    assert all(len(np.unique(r)) == 1 for r in seen)  # one value per batch
    values = np.array([r[0] for r in seen])
    assert len(np.unique(values)) > 1 and np.all(values > 0)  # the running mean moves, and stays positive
    rows = read(out / "ppo_gocu_seed0.csv")
    config = json.loads(sorted((out / "checkpoints" / "ppo_gocu_seed0").glob("state_*.json"))[-1].read_text())["config"]
    assert config["constant_curiosity"] is True and rows
    with pytest.raises(SystemExit, match="other settings"):  # a constant run is not resumed as a normal one
        se.main(tiny_args(out, 2048, "--algos", "ppo_gocu"))


@pytest.mark.parametrize("how", ["zero", "negative"])
def test_replace_curiosity_zero_and_negative(se, how):
    """replace_curiosity (the learning test's broken variants): every committed r_gc is 0, or the negative of what
    the module computed (the episode memos keep the true values, so a revisit's reward is negated once, not twice)."""
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_gocu import PPO_GoCu

    model = PPO_GoCu("CnnPolicy", make_vec_env("GoCu/DoorKey-5x5-v0", n_envs=4, seed=0), n_steps=128, seed=0, curiosity_kwargs=TINY_IMAGE_CURIOSITY)
    true, seen = [], []
    record_scores(model.curiosity.scorer, true)
    se.replace_curiosity(model.curiosity, how)
    record_scores(model.curiosity.scorer, seen)
    model.learn(1024)
    assert len(seen) > 100 and len(seen) == len(true)
    true_all, seen_all = np.concatenate(true), np.concatenate(seen)
    assert np.any(true_all > 0)  # the module computed rewards that vary
    expected = np.zeros_like(true_all) if how == "zero" else -true_all
    np.testing.assert_array_equal(seen_all, expected)
    with pytest.raises(ValueError, match="how must be one of"):
        se.replace_curiosity(model.curiosity, "noise")


def test_ablations_summary_counts_a_miss_at_the_budget(tmp_path):
    """benchmarks/ablations.py summary: steps to 0.9 per seed, a miss counted as the budget, running seeds marked, a
    partial arm compared with the defaults on the seeds both have finished."""
    ablations = load_script("ablations", "benchmarks/ablations.py")
    se_mod = ablations.se

    def write(folder, algo, seed, returns):
        rows = [dict(algo=algo, seed=seed, steps=1000 * (i + 1), episodes=100 + i, window_episodes=100, mean_return=r, success_rate=r,
                     key_rate=1.0, door_rate=1.0, intrinsic_mean=0.01, intrinsic_std=0.0, intrinsic_norm_mean=0.1, goals=10,
                     wall_time_s=1.0, fps=1.0) for i, r in enumerate(returns)]
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"{algo}_seed{seed}.csv").write_bytes(se_mod.csv_bytes(rows))

    defaults, out = tmp_path / "defaults", tmp_path / "out"
    write(defaults, "ppo_gocu", 0, [0.1, 0.95])           # 2,000
    write(defaults, "ppo_gocu", 1, [0.1, 0.2, 0.3])        # not within 3,000
    write(defaults, "ppo", 0, [0.1, 0.2, 0.3])             # plain PPO beside the defaults: not an arm, not read
    write(out / "predictor_untrained", "ppo_gocu", 0, [0.1, 0.2, 0.91])   # 3,000
    write(out / "predictor_untrained", "ppo_gocu", 1, [0.1, 0.2, 0.95])   # 3,000
    write(out / "one_value_head", "ppo_sum", 0, [0.1])     # running: 1,000 of 3,000
    write(out / "vae_untrained", "ppo_gocu", 0, [0.1, 0.2, 0.3])          # not within 3,000: counted 3,000
    write(out / "vae_untrained", "ppo_gocu", 1, [0.1])                    # running
    text = ablations.main(["summary", "--out", str(out), "--timesteps", "3000", "--defaults", str(defaults)]) or (out / "summary.md").read_text()
    lines = {line.split("|")[1].strip(): line for line in text.splitlines() if line.startswith("| ") and "---" not in line}
    assert "| 2,000 | not | 1 of 2 | 5,000 |" in lines["defaults"]
    assert "| 3,000 | 3,000 | 2 of 2 | 6,000 | +20.0% steps |" in lines["predictor_untrained"]
    assert "running (1,000)" in lines["one_value_head"] and "(0 so far)" in lines["one_value_head"]
    assert "| 0 of 1 | (3,000 so far) | +50.0% steps on seed 0 |" in lines["vae_untrained"]  # against the defaults' 2,000 on seed 0
    assert (out / "curves.png").stat().st_size > 0


def test_final_distance_and_success_on_a_sawyer_task(se, tmp_path):
    """On a task that reports info['distance'] (the Sawyer ids), the CSV's final_distance is the mean distance at the
    episodes' last steps, and the summary shows it (Table 2's measure)."""
    out = tmp_path / "sawyer"
    args = tiny_args(out, 1024, "--algos", "ppo")
    args[args.index("GoCu/DoorKey-5x5-v0")] = "GoCu/VisualSawyerReacher-v1"
    summary = se.main(args)
    rows = read(out / "ppo_seed0.csv")
    last = rows[-1]
    assert int(last["window_episodes"]) == 4 * (1024 // 4 // 50)  # 4 envs of 256 steps, 50-step episodes
    assert 0.06 < float(last["final_distance"]) < 0.5 and float(last["final_success"]) <= 0.25  # a random policy
    assert "final distance" in summary and f"{float(last['final_distance']):.3f}" in summary


def test_atari_runs_take_the_zoo_settings_and_count_rooms(se, tmp_path):
    """On an ALE id the runs are built as the zoo launcher builds them (8 envs, 4 stacked frames, the file's curiosity
    settings with the command's merged in), the CSV counts the rooms of Montezuma's Revenge and the best episode, a
    resumed run continues those counts, and the summary shows Table 3's measures."""
    out = tmp_path / "atari"
    args = ["--env", "ALE/MontezumaRevenge-v5", "--algos", "ppo_gocu", "--seeds", "0", "--out", str(out),
            "--checkpoint-freq", "1024", "--curiosity-kwargs", '{"pretrain_steps": 256, "vae_epochs": 1}', "--quiet",
            "--model-kwargs", '{"intrinsic_episodic": false}']
    se.main([*args, "--timesteps", "2048"])
    state = json.loads(sorted((out / "checkpoints" / "ppo_gocu_seed0").glob("state_*.json"))[-1].read_text())
    zoo = state["config"]["zoo"]
    assert zoo["n_envs"] == 8 and zoo["frame_stack"] == 4 and zoo["curiosity_kwargs"]["image_channels"] == 1
    assert zoo["curiosity_kwargs"]["pretrain_steps"] == 256  # the command's setting merged into the file's
    assert zoo["intrinsic_episodic"] is False  # and the model's, as the zoo's --hyperparams (the file's is True)
    assert not PPO_GoCu.load(out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip", device="cpu").intrinsic_episodic
    rows = read(out / "ppo_gocu_seed0.csv")
    assert [int(r["steps"]) for r in rows] == [1024, 2048]  # 8 envs x 128 steps per rollout
    summary = se.main([*args, "--timesteps", "3072"])  # resumed from the 2048-step checkpoint
    rows = read(out / "ppo_gocu_seed0.csv")
    assert [int(r["steps"]) for r in rows] == [1024, 2048, 3072]
    assert int(rows[-1]["episodes"]) >= 1  # a random agent loses its 5 lives within 3,072 steps of 8 envs
    assert float(rows[-1]["rooms_total"]) >= 1 and float(rows[-1]["rooms_mean"]) >= 1
    resumed = json.loads((out / "checkpoints" / "ppo_gocu_seed0" / "state_3072.json").read_text())
    # the resumed run continued the checkpoint's counts: its rooms and episodes extend those at 2,048 steps
    assert set(state["rooms"]) <= set(resumed["rooms"]) and float(rows[-1]["rooms_total"]) == len(resumed["rooms"])
    assert resumed["episode_rooms"][: len(state["episode_rooms"])] == state["episode_rooms"]
    assert float(rows[-1]["max_return"]) == resumed["max_return"]
    assert "rooms visited" in summary and "best episode return" in summary
    with pytest.raises(SystemExit):  # --zoo builds the zoo files' algorithms only
        se.main([*args, "--algos", "a2c"])


def test_encoder_alive_probe_tells_a_live_encoder_from_a_dead_one(two_runs, tmp_path):
    """The dead-encoder check of benchmarks/probes/encoder_alive.py: a trained checkpoint's encoder has live units and
    distinct goal embeddings; the same checkpoint with every embedding unit's bias pushed far below zero has none."""
    probe = load_script("encoder_alive", "benchmarks/probes/encoder_alive.py")
    out, _ = two_runs
    ckpts = out / "checkpoints" / "ppo_gocu_seed0"
    rows = probe.main([str(ckpts), "--frames", "256"])
    assert [r["steps"] for r in rows] == [1024, 2048]
    for r in rows:
        assert 0 < r["alive"] <= r["units"] and r["spread"] > 0 and not r["one_point"]
        assert 1 < r["goal_embeddings"] <= r["goals"]
    model = PPO_GoCu.load(ckpts / "model_2048.zip", device="cpu")
    with th.no_grad():
        model.curiosity.vae.fc.bias.fill_(-1e6)  # every unit of phi negative before its ReLU: a dead encoder
    (tmp_path / "dead").mkdir()
    model.save(tmp_path / "dead" / "model_2048.zip")
    dead = probe.main([str(tmp_path / "dead"), "--frames", "256"])[0]
    assert dead["alive"] == 0 and dead["spread"] == 0.0 and dead["one_point"] and dead["goal_embeddings"] == 1
    fresh = probe.fresh_units(ckpts / "model_1024.zip", 256, 0, 2)  # freshly initialised VAEs are alive
    assert len(fresh) == 2 and all(alive > 0 for alive, _ in fresh) and fresh[0] != fresh[1]


def test_atari_behaviour_probe_plays_the_agent_and_a_random_policy(tmp_path):
    """benchmarks/probes/atari_behaviour.py on an untrained PPO for Montezuma's Revenge: both policies play the steps
    asked, in the first room, with at most one new frame, cell and place a step; the random policy replays the same."""
    ale_py = pytest.importorskip("ale_py")
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_atari_env
    from stable_baselines3.common.vec_env import VecFrameStack, VecTransposeImage

    gym.register_envs(ale_py)
    env = VecTransposeImage(VecFrameStack(make_atari_env("ALE/MontezumaRevenge-v5", n_envs=1, seed=0), 4))
    path = tmp_path / "ppo_seed0" / "model_0.zip"
    path.parent.mkdir()
    PPO("CnnPolicy", env, n_steps=64, seed=0).save(path)
    probe = load_script("atari_behaviour", "benchmarks/probes/atari_behaviour.py")
    result = probe.main([str(path), "--steps", "64", "--seed", "3"])
    for name in ("agent", "random"):
        r = result[name]
        assert sum(r["actions"].values()) == 64 and r["rooms"] == [1]
        assert 1 <= r["cells"] <= r["frames"] <= 64 and 1 <= r["places"] <= 64
    assert len(result["random"]["actions"]) > 1
    again = probe.main([str(path), "--steps", "64", "--seed", "3"])
    assert again["random"] == result["random"]  # seeded: the same random play


def test_revisit_share_probe_measures_each_key_on_both_policies(two_runs):
    """benchmarks/probes/revisit_share.py on DoorKey-5x5: the cell is chosen from the calibration episodes; a cell is
    a function of the bytes, so its first-visit share never exceeds the bytes'; the agent's rollouts are measured too."""
    probe = load_script("revisit_share", "benchmarks/probes/revisit_share.py")
    out, _ = two_runs
    model = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    env = "GoCu/DoorKey-5x5-v0"
    result = probe.main(["--envs", env, "--steps", "300", "--calibration-steps", "1200", "--seed", "3", "--model", f"{env}={model}"])[env]
    assert result["cell"].endswith("grey levels") and 0 < result["calibration_share"] < 1 and result["key_ms"] > 0
    for policy in ("random", "agent"):
        shares = result[policy]
        assert 0 < shares["go-explore 11x8x8"] <= shares["bytes"] <= 1 and 0 < shares["cell"] <= shares["bytes"]
        assert shares["episodes"] >= 1
    with pytest.raises(SystemExit):
        probe.main(["--envs", env, "--model", f"GoCu/DoorKey-8x8-v0={model}"])  # a model of an env not probed


def test_revisit_share_probe_counts_a_game_as_one_episode():
    """benchmarks/probes/revisit_share.py measures the curiosity's episodes: under EpisodicLifeEnv a lost life is a done
    but not a new episode; the ids change where the Monitor beneath ends a game, and only there."""
    from stable_baselines3.common.atari_wrappers import EpisodicLifeEnv
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_gocu.curiosity.observations import ObservationAdapter

    probe = load_script("revisit_share", "benchmarks/probes/revisit_share.py")
    venv = DummyVecEnv([lambda: EpisodicLifeEnv(Monitor(LivesEnv()))])
    _, ids, _ = probe.rollout(venv, ObservationAdapter(venv.observation_space), 30)
    # a game is 10 agent steps (lives of 4, 4 and 2 steps, the 2 no-op steps of EpisodicLifeEnv's resets besides)
    assert ids.tolist() == [0] * 10 + [1] * 10 + [2] * 10


def test_atari_behaviour_probe_reports_what_a_ppo_gocu_agents_curiosity_pays(tmp_path):
    """With a PPO_GoCu model, the probe steps its curiosity module on both policies' steps: its revisit cells (at most
    one new a step) and the raw r_gc of the steps where the player stood still and where it moved, which together are
    every step but the first of each life."""
    ale_py = pytest.importorskip("ale_py")
    import gymnasium as gym
    from stable_baselines3.common.env_util import make_atari_env
    from stable_baselines3.common.vec_env import VecFrameStack, VecTransposeImage

    from sb3_gocu import PPO_GoCu

    gym.register_envs(ale_py)
    env = VecTransposeImage(VecFrameStack(make_atari_env("ALE/MontezumaRevenge-v5", n_envs=1, seed=0), 4))
    path = tmp_path / "ppo_gocu_seed0" / "model_0.zip"
    path.parent.mkdir()
    PPO_GoCu("CnnPolicy", env, n_steps=64, seed=0, curiosity_kwargs={**TINY_IMAGE_CURIOSITY, "image_channels": 1}).save(path)
    probe = load_script("atari_behaviour", "benchmarks/probes/atari_behaviour.py")
    result = probe.main([str(path), "--steps", "64", "--seed", "3"])
    for name in ("agent", "random"):
        r = result[name]
        assert 1 <= r["module_cells"] <= 64
        # a cell new in its game is new in its life; within one game the cells new in it are the distinct cells
        assert r["first_visit_share_game"] <= r["first_visit_share_life"] <= 1
        if r["games"] == 0:
            assert round(r["first_visit_share_game"] * 64) == r["module_cells"]
        (still, n_still), (moving, n_moving) = r["r_gc_still"], r["r_gc_moving"]
        assert n_still + n_moving == 64 - 1 - r["lives_lost"]
        assert all(0.0 <= value <= 0.1 + 1e-6 for value, n in ((still, n_still), (moving, n_moving)) if n)  # [0, alpha / delta]
    # the agent's curiosity value, read at every step: where a game began (the first step at least), a life, or neither
    v_gc = result["agent"]["v_gc"]
    assert sum(n for _, n in v_gc.values()) == 64 and 1 <= v_gc["game"][1] <= 1 + result["agent"]["games"]
    assert v_gc["life"][1] <= result["agent"]["lives_lost"] and "v_gc" not in result["random"]


def test_skill_signal_phase_mastery_worked_out_by_hand():
    """benchmarks/probes/skill_signal.py: a phase's mastery is the share of the episodes reaching it that go on; the
    least mastered is the lowest of those reached often enough (ties: the later phase)."""
    probe = load_script("skill_signal", "benchmarks/probes/skill_signal.py")
    obs = np.zeros((2, 1), dtype=np.uint8)
    episodes = [(obs, np.array([0, 0]), False), (obs, np.array([0, 1]), False),
                (obs, np.array([2, 3]), True), (obs, np.array([1, 3]), False)]
    mastery = probe.phase_mastery(episodes)
    assert mastery[0] == {"reached": 1.0, "mastery": 0.75}
    assert mastery[1] == {"reached": 0.75, "mastery": pytest.approx(2 / 3)}
    assert mastery[2] == {"reached": 0.5, "mastery": 1.0}
    assert mastery[3] == {"reached": 0.5, "mastery": 0.5}  # one of the two in the goal room reached the goal
    assert probe.least_mastered(mastery) == 3
    assert probe.least_mastered({0: {"reached": 1.0, "mastery": 0.5}, 1: {"reached": 0.05, "mastery": 0.0}}) == 0
    assert probe.least_mastered({0: {"reached": 1.0, "mastery": 0.5}, 1: {"reached": 0.5, "mastery": 0.5}}) == 1
    assert probe.least_mastered({0: {"reached": 1.0, "mastery": 1.0}, 1: {"reached": 1.0, "mastery": 0.96}}) is None


def test_skill_signal_probe_pays_each_h_on_the_same_steps(two_runs):
    """benchmarks/probes/skill_signal.py on the tiny run's model: every h is measured on the same paid steps (those
    whose revisit cell is new in the episode), r_gc stays within eq 13's range, and h = max is the module's own."""
    probe = load_script("skill_signal", "benchmarks/probes/skill_signal.py")
    out, _ = two_runs
    model_path = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    res = probe.main([str(model_path), "--env", "GoCu/DoorKey-5x5-v0", "--episodes", "4", "--pairs", "64"])["model_2048.zip"]
    assert res["episodes"] == 4 and set(res["phases"]) == set(probe.GOAL_DESIGNS)
    assert all(set(ph["aggregates"]) == set(probe.AGGREGATES) for ph in res["phases"].values())
    model = PPO_GoCu.load(model_path, device="cpu")
    cfg = model.curiosity.config
    episodes = probe.play(model, "GoCu/DoorKey-5x5-v0", 4, 1000)
    signal = probe.phase_signal(model, episodes, np.random.default_rng(0))
    paid = sum(len(set(model.curiosity.revisit_key(o))) for o, _, _ in episodes)
    for agg in signal["aggregates"].values():
        assert sum(f["steps"] for f in agg["phases"].values()) == paid
        for f in agg["phases"].values():
            assert (cfg.alpha - 1) / cfg.reward_scale <= f["r_gc_mean"] <= cfg.alpha / cfg.reward_scale and 0 <= f["saturated"] <= 1
    # h = max and h = mean are eq 13's own (sb3_gocu.curiosity.reward.curiosity_reward)
    from sb3_gocu.curiosity.reward import curiosity_reward

    obs = episodes[0][0]
    goals = model.curiosity.goal_buffer.observations[model.curiosity.goal_buffer.sample(1, cfg.n_goals, np.random.default_rng(0))[0]]
    mastery = model.curiosity.mastery(obs, goals)
    for name, aggregation in (("max (the defaults)", "max"), ("mean", "mean")):
        r_gc = (cfg.alpha - probe.AGGREGATES[name](mastery)) / cfg.reward_scale
        assert th.allclose(r_gc, curiosity_reward(mastery, cfg.alpha, aggregation, cfg.reward_scale))
    reached = [m["reached"] for m in signal["mastery"].values()]
    assert reached[0] == 1.0 and reached == sorted(reached, reverse=True)


def test_skill_signal_goal_designs_draw_where_they_say():
    """benchmarks/probes/skill_signal.py's goal designs: the spread-out goals include an extreme of the buffer in phi and
    lie at least 3 apart (farthest-point picks from any start on a line of 9);
    recent goals come only from the RECENT episodes before the paid one (wrapping round), ends only from their last
    END_STEPS steps."""
    from types import SimpleNamespace

    probe = load_script("skill_signal", "benchmarks/probes/skill_signal.py")
    rng = np.random.default_rng(0)
    # a buffer of 9 goals on a line in phi, the goal's observation holding its index
    buffer = SimpleNamespace(size=9, embeddings=th.arange(9, dtype=th.float32)[:, None], observations=np.arange(9)[:, None])
    model = SimpleNamespace(curiosity=SimpleNamespace(goal_buffer=buffer))
    for _ in range(5):
        goals = probe.distinct_goals(model, [], 0, 3, rng)[:, 0]
        assert {0, 8} & set(goals.tolist()) and np.diff(np.sort(goals)).min() >= 3
    # 40 episodes of 100 steps; a frame holds (episode, step)
    episodes = [(np.stack([np.full(100, e), np.arange(100)], axis=1), np.zeros(100, dtype=np.int64), False) for e in range(40)]
    for i, before in ((30, set(range(14, 30))), (3, {0, 1, 2} | set(range(27, 40)))):
        goals = probe.recent_goals(ends_only=False)(model, episodes, i, 500, rng)
        assert set(goals[:, 0].tolist()) == before and goals[:, 1].min() < 50
        goals = probe.recent_goals(ends_only=True)(model, episodes, i, 500, rng)
        assert set(goals[:, 0].tolist()) == before and goals[:, 1].min() >= 100 - probe.END_STEPS


def test_rnetwork_probe_draws_the_modules_reachability_pairs():
    """benchmarks/probes/rnetwork.py: near pairs lie 1..5 steps apart in one episode; a far pair's goal is not seen in
    the d_max steps after its state, in the same episode."""
    probe = load_script("rnetwork", "benchmarks/probes/rnetwork.py")
    rng = np.random.default_rng(0)
    # two episodes of 1-pixel frames: the first walks 0..59 and back to 0 at step 60, the second stands still
    walk = np.concatenate([np.arange(60), [0]]).astype(np.uint8)[:, None]
    episodes = [(walk, np.zeros(61, dtype=np.int64), False), (np.zeros((40, 1), dtype=np.uint8), np.zeros(40, dtype=np.int64), False)]
    pairs = probe.Pairs(episodes, far=30)
    episode_of = np.searchsorted(pairs.starts, np.arange(len(pairs.frames)), side="right") - 1
    s, g = pairs.near(500, rng)
    assert np.all(episode_of[s] == episode_of[g]) and np.all((g - s >= 1) & (g - s <= 5))
    s, g = pairs.far_pairs(200, rng)
    assert len(s) > 0 and np.all(episode_of[s] == 0) and np.all(episode_of[g] == 0)  # the still episode has none
    assert np.all(g - s >= 30)
    for t, u in zip(s, g):  # the goal's frame is not among the 30 after the state (step 60 repeats step 0)
        assert pairs.frames[u, 0] not in pairs.frames[t : t + 30, 0]
    assert not np.any((s == 0) & (g == 60))


def test_rnetwork_probe_scores_each_arm(two_runs):
    """benchmarks/probes/rnetwork.py end to end on the tiny run's model: the module's own predictor is scored as saved,
    the fresh ones after their Adam steps; AUCs are probabilities; r_gc by phase comes for the module and the R-network."""
    probe = load_script("rnetwork", "benchmarks/probes/rnetwork.py")
    out, _ = two_runs
    model = out / "checkpoints" / "ppo_gocu_seed0" / "model_2048.zip"
    threads = th.get_num_threads()
    res = probe.main([str(model), "--env", "GoCu/DoorKey-5x5-v0", "--episodes", "6", "--adam", "3", "--batch", "16", "--test-pairs", "32"])
    assert th.get_num_threads() == threads
    assert res["module"]["adam_steps"] == 0 and res["phi"]["adam_steps"] == res["r-network"]["adam_steps"] == 3
    for arm in ("module", "phi", "r-network"):
        assert np.isnan(res[arm]["auc_far"]) or 0 <= res[arm]["auc_far"] <= 1
        assert 0 <= res[arm]["auc_goals"] <= 1
    assert res["module"]["phases"]["aggregates"] and res["r-network"]["phases"]["aggregates"]


def test_rnetwork_probe_scores_a_batch_norm_net_pair_by_pair():
    """benchmarks/probes/rnetwork.py scores in eval mode: a pair's score does not depend on the other pairs of its
    test batch (in train mode batch norm would normalise a batch of near pairs apart from one of far pairs)."""
    import argparse

    from sb3_gocu.curiosity.networks import MasteryPredictor

    probe = load_script("rnetwork", "benchmarks/probes/rnetwork.py")
    rng = np.random.default_rng(0)
    frames = rng.normal(size=(80, 4)).astype(np.float32)
    episodes = [(frames, np.zeros(80, dtype=np.int64), False)]
    net = MasteryPredictor(4, (8,))

    def logits(s, g):
        out = net(th.as_tensor(s), th.as_tensor(g))
        return out[:, 1] - out[:, 0]

    args = argparse.Namespace(adam=2, batch=16, lr=1e-3)
    # the "far" batch is the near batch's first pair alone: pair by pair, the two score it alike (AUC of ties 0.5 at it)
    test = {"near": (frames[:8], frames[1:9]), "far": (frames[:1], frames[1:2]), "goals": (frames[:8], frames[40:48])}
    res = probe.train_and_score(logits, net, True, probe.Pairs(episodes, far=30), frames[60:], test, args, rng)
    assert not net.training and res["adam_steps"] == 2
    with th.no_grad():
        alone, among = logits(frames[:1], frames[1:2]), logits(frames[:8], frames[1:9])[:1]
    assert th.allclose(alone, among)
