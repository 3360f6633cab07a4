"""The revisit key: a state's cell (sb3_gocu/curiosity/revisits.py), chosen from the random-policy episodes."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces

from sb3_gocu.curiosity import GoalCuriosityModule
from sb3_gocu.curiosity.revisits import (
    MIN_CALIBRATION_STEPS,
    TARGET_SHARE,
    SIMHASH_BITS,
    ImageCell,
    SimHashCell,
    cell_from_state,
    choose_cell,
    first_visit_mask,
    first_visit_share,
)

from conftest import SMALL_CURIOSITY


def walk_frames(n: int, seed: int, episode_length: int = 200, noise: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """32x32 grey frames of a bright 4x4 square doing a random walk on an 8x8 grid of places, over a dark background
    with per-pixel noise (so that no two frames repeat byte for byte), in episodes of ``episode_length`` steps."""
    rng = np.random.default_rng(seed)
    frames = np.empty((n, 32, 32, 1), dtype=np.uint8)
    ids = np.arange(n) // episode_length
    x = y = 0
    for t in range(n):
        if t % episode_length == 0:
            x = y = 0
        dx, dy = [(0, 1), (0, -1), (1, 0), (-1, 0)][rng.integers(4)]
        x, y = min(max(x + dx, 0), 7), min(max(y + dy, 0), 7)
        frame = 40 + rng.integers(0, noise, (32, 32))
        frame[4 * y : 4 * y + 4, 4 * x : 4 * x + 4] = 220
        frames[t, :, :, 0] = frame
    return frames, ids


def test_an_image_cell_by_hand():
    """Grey by luma, area means (a 3-pixel side to 2 weighs the middle pixel half to each), then L levels."""
    rgb = np.zeros((1, 3, 3, 3), dtype=np.uint8)
    rgb[0, :, :, 0] = 255  # red: luma 0.299
    rgb[0, :, 2, :] = 255  # right column white
    cell = ImageCell("hwc", 255.0, (3, 3), width=2, height=1, levels=4)
    # left output pixel: columns 0 and half of 1, all red (0.299); right: half of column 1 red, column 2 white:
    # (0.5 * 0.299 + 1.0) / 1.5 = 0.766
    assert cell.cells(rgb).tolist() == [[[1, 3]]]
    # a grey frame stack (C, H, W): the newest (last) frame alone
    stack = np.zeros((1, 4, 2, 2), dtype=np.uint8)
    stack[0, :3] = 255
    assert ImageCell("chw", 255.0, (2, 2), 1, 1, 8).cells(stack).tolist() == [[[0]]]
    stack[0, 3] = 255
    assert ImageCell("chw", 255.0, (2, 2), 1, 1, 8).cells(stack).tolist() == [[[7]]]
    with pytest.raises(ValueError, match=r"1\.\.3 pixels across, 1\.\.3 down and have 2\.\.256 levels, got 4 x 1"):
        ImageCell("hwc", 255.0, (3, 3), width=4, height=1, levels=4)


def test_a_simhash_cell_by_hand():
    """The sides of the hyperplanes a . z + b = 0, z the standardised vector; a 1-entry vector is cut by size too."""
    cell = SimHashCell(np.array([1.0, 0.0]), np.array([2.0, 1.0]), bits=3)
    a, b = cell._projection[:-1], cell._projection[-1]
    x = np.array([[1.0, 0.0], [3.0, -1.0], [-5.0, 2.0]])
    z = (x - [1.0, 0.0]) / [2.0, 1.0]
    assert cell.cells(x).tolist() == np.packbits(z @ a + b > 0, axis=1).tolist()
    assert cell.cells(x).shape == (3, 1)
    line = np.linspace(-3, 3, 601)[:, None]
    assert len(set(SimHashCell(np.zeros(1), np.ones(1), bits=8)(line))) > 2  # more than the two signs of x
    with pytest.raises(ValueError, match=r"a SimHash cell needs 1\.\.64 bits, got 65"):
        SimHashCell(np.zeros(1), np.ones(1), bits=65)


def test_the_first_visit_share_by_hand():
    keys = [b"a", b"b", b"a", b"a", b"c", b"a"]
    ids = np.array([0, 0, 0, 1, 1, 1])  # episode 1 sees "a" anew
    assert first_visit_share(keys, ids) == pytest.approx(4 / 6)
    interleaved = np.array([0, 1, 0, 1, 0, 1])  # two envs' episodes in step order: a b a | a c a
    assert first_visit_share(keys, interleaved) == pytest.approx(4 / 6)
    assert first_visit_share([b"a", b"a", b"a", b"a"], np.array([0, 1, 0, 1])) == pytest.approx(2 / 4)
    assert first_visit_mask(keys, ids).tolist() == [True, True, False, True, True, False]
    assert first_visit_mask(keys, interleaved).tolist() == [True, True, False, True, True, False]
    assert first_visit_mask([], np.zeros(0)).shape == (0,) and np.isnan(first_visit_share([], np.zeros(0)))


def test_the_chosen_cell_fires_where_bytes_never_repeat():
    """Noisy frames never repeat byte for byte (share 1.0); the chosen cell sees the walk's revisits, with a share
    near the target, and a frame that stands still in its noise keeps its cell."""
    frames, ids = walk_frames(4000, seed=0)
    assert first_visit_share([f.tobytes() for f in frames], ids) == 1.0
    cell, stats = choose_cell(frames, ids, "hwc", 255.0)
    assert 0.05 <= stats["revisit_share"] <= 0.25
    assert stats["revisit_share"] == pytest.approx(first_visit_share(cell(frames), ids))
    # the walk's places are told apart in groups (a walk of 200 steps on 64 places comes back too often for all 64 to
    # keep the share near the target): new cells arrive only when the square moves
    assert len(set(cell(frames))) >= 16
    still = np.repeat(frames[:1], 50, axis=0)
    still[:, :, :, 0] = np.where(still[:, :, :, 0] > 100, 220, 40 + np.random.default_rng(1).integers(0, 6, (50, 32, 32)))
    assert len(set(cell(still))) == 1


def test_too_few_observations_keep_the_default_cell():
    frames, ids = walk_frames(MIN_CALIBRATION_STEPS - 1, seed=0)
    cell, stats = choose_cell(frames, ids, "hwc", 255.0)
    assert (cell.width, cell.height, cell.levels) == (11, 8, 8)
    assert stats["revisit_calibration_steps"] == MIN_CALIBRATION_STEPS - 1
    for raw, layout in ((np.zeros((0, 32, 32, 1), np.uint8), "hwc"), (np.zeros((0, 3)), "vector")):  # none at all
        cell, stats = choose_cell(raw, np.zeros(0, np.int64), layout, 1.0)
        assert cell(raw) == [] and stats["revisit_calibration_steps"] == 0


def test_a_vector_walk_gets_a_cell_near_the_target():
    rng = np.random.default_rng(0)
    steps = rng.normal(0, 0.05, (3000, 2)).astype(np.float32)
    ids = np.arange(3000) // 300
    walk = np.concatenate([np.cumsum(s, axis=0) for s in np.split(steps, 10)])
    cell, stats = choose_cell(walk, ids, "vector", 1.0)
    assert isinstance(cell, SimHashCell) and 0.05 <= stats["revisit_share"] <= 0.25
    mean, std = walk.astype(np.float64).mean(axis=0), walk.astype(np.float64).std(axis=0)
    distance = {bits: abs(np.log(first_visit_share(SimHashCell(mean, std, bits)(walk), ids) / TARGET_SHARE)) for bits in SIMHASH_BITS}
    assert cell.bits == min(distance, key=lambda bits: (round(distance[bits], 6), -bits))
    restored = cell_from_state(cell.state_dict(), "vector", 1.0, (2,))
    assert restored(walk) == cell(walk)


def test_the_module_chooses_its_cell_at_the_pretraining_saves_it_and_pays_standing_still_once():
    """The module records the random-policy episodes while not pretrained, chooses the cell in pretrain(), keeps it
    through a save and a load; afterwards a state standing still in its noise pays r_gc once per episode."""
    space = spaces.Box(0, 255, (32, 32, 1), np.uint8)
    module = GoalCuriosityModule(space, **{**SMALL_CURIOSITY, "pretrain_steps": 2000}, seed=0)
    module.recording = True
    frames, ids = walk_frames(2000, seed=3, episode_length=100)
    for t in range(0, 2000, 2):  # two envs, each walking its own episodes
        module.step(frames[t : t + 2], np.array([t % 100 == 98] * 2))
    stats = module.pretrain()
    assert 0.05 <= stats["revisit_share"] <= 0.25 and stats["revisit_calibration_steps"] == 2000
    chosen = module.revisit_key
    assert (chosen.width, chosen.height, chosen.levels) != (11, 8, 8)

    module.pretrain()  # a second pretraining keeps the cell
    assert module.revisit_key == chosen
    loaded = GoalCuriosityModule(space, **{**SMALL_CURIOSITY, "pretrain_steps": 2000}, seed=1)
    loaded.load_state_dict(module.state_dict())
    assert loaded.revisit_key == chosen

    module.pop_reward_stats()
    module.begin_episodes(np.arange(2))
    still = np.repeat(frames[:2], 20, axis=0)
    still[..., 0] = np.where(still[..., 0] > 100, 220, 40 + np.random.default_rng(2).integers(0, 6, (40, 32, 32)))
    paid = np.array([module.step(still[t : t + 2], np.zeros(2, bool))[0] for t in range(0, 40, 2)])
    assert (paid[0] > 0).all() and (paid[1:] == 0).all()
    assert module.pop_reward_stats()["first_visit_share"] == pytest.approx(2 / 40)


def test_a_state_saved_before_the_cell_key_loads_with_the_default_cell():
    space = spaces.Box(0, 255, (16, 16, 3), np.uint8)
    module = GoalCuriosityModule(space, **SMALL_CURIOSITY, seed=0)
    state = module.state_dict()
    del state["revisit_key"]
    loaded = GoalCuriosityModule(space, **SMALL_CURIOSITY, seed=0)
    loaded.revisit_key = ImageCell("hwc", 255.0, (16, 16), 16, 16, 16)
    loaded.load_state_dict(state)
    assert (loaded.revisit_key.width, loaded.revisit_key.height, loaded.revisit_key.levels) == (11, 8, 8)
    assert cell_from_state(module.revisit_key.state_dict(), "hwc", 255.0, (16, 16, 3)) == module.revisit_key
