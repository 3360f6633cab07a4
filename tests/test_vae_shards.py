"""vae_shards: the VAE's minibatch gradient computed as independent parts, the same to the bit with any thread count."""

import threading

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_gocu import GoalCuriosityModule
from sb3_gocu.curiosity.networks import ConvVAE, MlpVAE, sharded_vae_gradients, vae_loss

from conftest import SMALL_CURIOSITY, ChainEnv

IMAGE_SPACE = spaces.Box(0, 255, (16, 16, 3), np.uint8)


def serially(parts):
    return [part() for part in parts]


@pytest.mark.parametrize("make", [lambda: ConvVAE((3, 8, 8), embed_dim=16, latent_dim=3), lambda: MlpVAE((5,), embed_dim=8, latent_dim=2)])
@pytest.mark.parametrize("shards", [1, 2, 3, 7])
def test_sharded_gradients_are_the_whole_minibatchs(make, shards):
    """Same noise, same loss, same gradient as vae_loss on the whole minibatch (up to the summation order), for
    parts of unequal size too (7 rows); the generator is left where vae_loss leaves it."""
    th.manual_seed(0)
    vae = make().train()
    shape = (7, *vae.input_shape)
    x = th.rand(shape, generator=th.Generator().manual_seed(3))
    w = th.tensor([1.0, 2.0, 0.5, 1.0, 3.0, 1.0, 0.25])

    gen_whole = th.Generator().manual_seed(11)
    loss_whole, _, _ = vae_loss(vae, x, 0.7, w, generator=gen_whole)
    grads_whole = th.autograd.grad(loss_whole, list(vae.parameters()))

    gen_parts = th.Generator().manual_seed(11)
    calls = []

    def run_all(parts):
        calls.append(len(parts))
        return serially(parts)

    loss_parts, grads_parts = sharded_vae_gradients(vae, x, 0.7, w, gen_parts, shards, run_all)
    assert calls == [shards]
    assert th.allclose(loss_parts, loss_whole.detach(), rtol=1e-6, atol=0)
    assert len(grads_parts) == len(grads_whole)
    for a, b in zip(grads_parts, grads_whole):
        assert th.allclose(a, b, rtol=1e-4, atol=1e-6)
    assert th.equal(th.randn(4, generator=gen_whole), th.randn(4, generator=gen_parts)), "the same noise was drawn"


def test_sharded_gradients_change_with_the_noise():
    """The noise reaches the loss (a part does not draw its own): another generator seed, another loss."""
    th.manual_seed(0)
    vae = ConvVAE((3, 8, 8), embed_dim=16, latent_dim=3).train()
    x, w = th.rand(6, 3, 8, 8, generator=th.Generator().manual_seed(3)), th.ones(6)
    a, _ = sharded_vae_gradients(vae, x, 1.0, w, th.Generator().manual_seed(1), 2, serially)
    b, _ = sharded_vae_gradients(vae, x, 1.0, w, th.Generator().manual_seed(2), 2, serially)
    assert not th.equal(a, b)


def image_module(**kwargs) -> GoalCuriosityModule:
    kwargs = {"vae_shards": 2, **kwargs}
    return GoalCuriosityModule(
        IMAGE_SPACE, n_goals=4, goal_buffer_size=32, predictor_hidden=(32,), embed_dim=32, latent_dim=4,
        vae_batch_size=32, vae_epochs=2, vae_patience=1, overlap_ppo_update=False, seed=0, **kwargs
    )


def fit(threads: int, **kwargs) -> tuple[dict[str, th.Tensor], dict]:
    """A VAE fit on 200 fixed images (with early stopping's held-out loss) with ``threads`` torch threads in the
    caller; the VAE's weights and the fit's figures."""
    th.set_num_threads(threads)
    module = image_module(**kwargs)
    data = np.random.default_rng(0).integers(0, 256, size=(200, 16, 16, 3), dtype=np.uint8)
    out = module._fit_vae(data[:180], np.ones(180, np.float32), 2, val_data=data[180:], val_weights=np.ones(20, np.float32))
    return {k: v.clone() for k, v in module.vae.state_dict().items()}, out


def test_a_sharded_fit_is_the_same_with_any_thread_count():
    """vae_shards=2: parts one after the other (1 thread) or in parallel (2 threads), with 1 or 2 torch threads
    in the caller: the same weights, losses and held-out losses to the bit."""
    reference, ref_out = fit(1, update_threads=1)
    assert len(ref_out["losses"]) == 2 * 6 and ref_out["epochs_run"] >= 1
    for threads, kwargs in [(1, dict(update_threads=2)), (2, dict()), (2, dict(update_threads=1)), (1, dict())]:
        weights, out = fit(threads, **kwargs)
        assert out["losses"] == ref_out["losses"], (threads, kwargs)
        assert out["val_loss"] == ref_out["val_loss"] and out["val_loss_start"] == ref_out["val_loss_start"]
        for key in reference:
            assert th.equal(weights[key], reference[key]), (threads, kwargs, key)


def test_the_parts_run_in_parallel_threads_with_one_torch_thread_each():
    """_run_parts: results in order; with 2 shard threads the second part runs in another thread; every part
    sees 1 torch thread and the caller's grad mode; the caller's count is left as it was."""
    th.set_num_threads(2)
    module = image_module(update_threads=2)
    seen = []
    barrier = threading.Barrier(2, timeout=10)

    def part(i):
        def run():
            barrier.wait()  # both parts are running at once, or this times out
            seen.append((i, threading.get_ident(), th.get_num_threads(), th.is_grad_enabled()))
            return i * 10
        return run

    assert module._run_parts([part(0), part(1)]) == [0, 10]
    assert len({ident for _, ident, _, _ in seen}) == 2
    assert {(n, grad) for _, _, n, grad in seen} == {(1, True)}
    with th.no_grad():
        seen.clear()
        barrier.reset()
        module._run_parts([part(0), part(1)])
    assert {grad for _, _, _, grad in seen} == {False}
    assert th.get_num_threads() == 2


def test_one_shard_thread_runs_the_parts_in_the_caller():
    module = image_module(update_threads=1)
    idents = module._run_parts([lambda: threading.get_ident(), lambda: threading.get_ident()])
    assert idents == [threading.get_ident()] * 2 and module._shard_pool is None


def test_the_default_shard_threads_are_one_per_part_up_to_the_usable_cores(monkeypatch):
    module = image_module()
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert module._shard_threads() == 2
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0}, raising=False)
    assert module._shard_threads() == 1
    assert image_module(update_threads=3)._shard_threads() == 2, "no more threads than parts"


@pytest.mark.parametrize("value, message", [
    (0, "vae_shards must be in [1, vae_batch_size=32], got 0"),
    (33, "vae_shards must be in [1, vae_batch_size=32], got 33"),
    (2.0, "vae_shards must be an integer, got 2.0"),
])
def test_vae_shards_is_checked(value, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        image_module(vae_shards=value)


def test_one_shard_is_the_whole_minibatch_as_before():
    """vae_shards=1 takes the whole-minibatch path (vae_loss + backward), not the parts."""
    module = GoalCuriosityModule(ChainEnv().observation_space, **{**SMALL_CURIOSITY, "vae_shards": 1})
    module._run_parts = None  # would raise if called
    data = np.random.default_rng(0).random((40, 2), dtype=np.float32)
    out = module._fit_vae(data, np.ones(40, np.float32), 1)
    assert out["losses"] and all(np.isfinite(out["losses"]))


def test_bad_noise_and_shard_counts_are_refused():
    vae = ConvVAE((3, 8, 8), embed_dim=16, latent_dim=3).train()
    x = th.rand(4, 3, 8, 8)
    with pytest.raises(ValueError, match=r"noise must have the latent's shape \(4, 3\), got \(4, 2\)"):
        vae(x, noise=th.zeros(4, 2))
    with pytest.raises(ValueError, match="shards must be >= 1, got 0"):
        sharded_vae_gradients(vae, x, 1.0, th.ones(4), None, 0, serially)
