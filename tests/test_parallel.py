"""Column-split products (``split_updates``): the same values to the bit as the whole products, whoever
computes the halves, and a helping thread really takes halves."""

from __future__ import annotations

import threading

import pytest
import torch as th
from torch import nn

from sb3_gocu.curiosity.training import torch_threads
from sb3_gocu.curiosity.networks import ConvVAE, MasteryPredictor, MlpVAE, mastery_loss, vae_loss
from sb3_gocu.curiosity.parallel import SplitConv2d, SplitConvTranspose2d, SplitLinear, SplitWork, splitting


def _params(net: nn.Module) -> th.Tensor:
    return th.cat([t.detach().flatten().float() for t in [*net.parameters(), *net.buffers()]])


def _train_predictor(steps: int = 6, embed: int = 16, hidden: tuple[int, ...] = (64, 64, 32), batch: int = 32) -> tuple[th.Tensor, th.Tensor]:
    th.manual_seed(0)
    net = MasteryPredictor(embed, hidden)
    opt = th.optim.Adam(net.parameters(), lr=1e-3)
    g = th.Generator().manual_seed(1)
    for _ in range(steps):
        s, goal, t = th.randn(batch, embed, generator=g), th.randn(batch, embed, generator=g), th.rand(batch, generator=g)
        loss = mastery_loss(net(s, goal), t)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with th.no_grad():
        probe = net.mastery(th.randn(50, embed, generator=g), th.randn(50, embed, generator=g))
    return _params(net), probe


def _train_vae(image: bool, steps: int = 4, side: int = 12, embed: int = 32, latent: int = 4, batch: int = 16) -> th.Tensor:
    th.manual_seed(0)
    vae = ConvVAE((3, side, side), embed_dim=embed, latent_dim=latent) if image else MlpVAE((20,), embed_dim=embed, latent_dim=latent)
    opt = th.optim.Adam(vae.parameters(), lr=1e-3)
    g, noise = th.Generator().manual_seed(2), th.Generator().manual_seed(3)
    vae.train()
    for _ in range(steps):
        x = th.rand(batch, 3, side, side, generator=g) if image else th.randn(batch, 20, generator=g)
        loss, _, _ = vae_loss(vae, x, 1.0, th.rand(batch, generator=g) + 0.5, generator=noise)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return _params(vae)


def _in_thread(fn, work: SplitWork, help: bool):
    """fn() in a thread of its own inside ``splitting(work)``; with ``help``, this thread helps until it ends."""
    out: dict = {}
    finished = threading.Event()

    def body() -> None:
        try:
            with torch_threads(1), splitting(work):
                out["value"] = fn()
        finally:
            finished.set()
            work.wake()

    t = threading.Thread(target=body)
    t.start()
    if help:
        work.help(finished)
    t.join()
    return out["value"]


CASES = {
    "predictor": _train_predictor,
    "conv_vae": lambda: _train_vae(True),
    "mlp_vae": lambda: _train_vae(False),
    # the defaults' networks and minibatches: 5x512 predictor on 128-wide embeddings, the 32x32 image VAE
    "paper_predictor": lambda: _train_predictor(steps=3, embed=128, hidden=(512,) * 5, batch=128),
    "paper_vae": lambda: _train_vae(True, steps=2, side=32, embed=128, latent=10, batch=128),
}


@pytest.mark.parametrize("train", list(CASES.values()), ids=list(CASES))
def test_split_updates_give_the_whole_products_values(train) -> None:
    with torch_threads(1):
        whole = train()
    alone = _in_thread(train, SplitWork(), help=False)  # the update's thread computes both halves
    helped = _in_thread(train, SplitWork(), help=True)  # this thread takes the halves it can
    flat = lambda v: th.cat([t.flatten() for t in v]) if isinstance(v, tuple) else v  # noqa: E731
    assert th.equal(flat(whole), flat(alone))
    assert th.equal(flat(whole), flat(helped))


def _helper_thread(work: SplitWork) -> tuple[threading.Thread, threading.Event]:
    """A thread inside ``work.help`` (returned once it is there) and the event that ends its help."""
    finished = threading.Event()
    helper = threading.Thread(target=work.help, args=(finished,))
    helper.start()
    for _ in range(500):
        if work.helpers == 1:
            break
        threading.Event().wait(0.01)
    assert work.helpers == 1
    return helper, finished


def test_a_waiting_thread_takes_halves() -> None:
    work = SplitWork()
    helper, finished = _helper_thread(work)
    ran_in, release = [], threading.Event()

    def first() -> str:
        release.wait(5)  # returns once the helper has run the second half
        ran_in.append(threading.current_thread())
        return "a"

    def second() -> str:
        ran_in.append(threading.current_thread())
        release.set()
        return "b"

    assert work.run2(first, second) == ("a", "b")
    finished.set()
    work.wake()
    helper.join(5)
    assert ran_in == [helper, threading.current_thread()]  # the helper ran the second half, here the first
    assert work.helpers == 0
    # with nobody helping, both halves run here, in order
    order: list[str] = []
    assert work.run2(lambda: order.append("a") or 1, lambda: order.append("b") or 2) == (1, 2) and order == ["a", "b"]


def test_a_helpers_error_reaches_the_update() -> None:
    work = SplitWork()
    helper, finished = _helper_thread(work)

    def bad() -> None:
        raise ValueError("half failed")

    with pytest.raises(ValueError, match="half failed"):
        work.run2(lambda: threading.Event().wait(0.5), bad)
    finished.set()
    work.wake()
    helper.join(5)
    assert not helper.is_alive()


def test_an_interrupt_in_a_helped_half_stops_both_threads() -> None:
    """Ctrl-C while the waiting thread computes a half: it reaches that thread (which stops helping) and the
    update's thread, which re-raises it from run2."""
    work = SplitWork()
    finished, seen = threading.Event(), []

    def interrupted() -> None:
        raise KeyboardInterrupt

    def update() -> None:
        for _ in range(500):  # post once this thread's help below has begun
            if work.helpers:
                break
            threading.Event().wait(0.01)
        try:
            work.run2(lambda: threading.Event().wait(0.5), interrupted)
        except KeyboardInterrupt:
            seen.append("update")
        finished.set()
        work.wake()

    t = threading.Thread(target=update)
    t.start()
    with pytest.raises(KeyboardInterrupt):
        work.help(finished)
    seen.append("helper")
    t.join(5)
    assert seen == ["helper", "update"] and work.helpers == 0


def test_split_layers_are_the_plain_layers_outside_splitting() -> None:
    th.manual_seed(0)
    lin = SplitLinear(32, 64)
    th.manual_seed(0)
    ref = nn.Linear(32, 64)
    assert th.equal(lin.weight, ref.weight) and th.equal(lin.bias, ref.bias)  # same initialisation draws
    assert set(lin.state_dict()) == set(ref.state_dict())
    conv = SplitConv2d(3, 32, 3, padding=1)
    x = th.randn(2, 3, 5, 5)
    assert th.equal(conv(x), nn.functional.conv2d(x, conv.weight, conv.bias, padding=1))
    assert lin(th.randn(4, 32)).grad_fn.name() != "_SplitLinearFnBackward"
    with splitting(SplitWork()):
        assert lin(th.randn(4, 32)).grad_fn.name() == "_SplitLinearFnBackward"
        assert conv(x).grad_fn.name() == "_SplitConvFnBackward"
        for narrow in (SplitLinear(32, 20), SplitLinear(10, 64)):  # widths not multiples of SPLIT_MULTIPLE: whole
            assert narrow(th.randn(4, narrow.in_features)).grad_fn.name() != "_SplitLinearFnBackward"


@pytest.mark.parametrize("make", [
    lambda: SplitConv2d(3, 32, 3, stride=2, padding=1),  # output channels split for the weight gradient
    lambda: SplitConv2d(8, 16, 3, padding=1),  # 16 output channels: weight gradient whole
    lambda: SplitConvTranspose2d(32, 3, 4, stride=2, padding=1),  # weight gradient whole
], ids=["conv_32", "conv_16", "conv_transpose"])
@pytest.mark.parametrize("batch", [6, 7])
def test_split_convolutions_match_the_plain_layer(make, batch) -> None:
    """Output, input, weight and bias gradients of a split convolution (minibatch halves of 3 and 3, or 3 and 4
    samples) equal the plain layer's, helped or not."""
    th.manual_seed(0)
    conv = make()
    x = th.randn(batch, conv.in_channels, 9, 9, generator=th.Generator().manual_seed(1))
    grad = None

    def run() -> tuple[th.Tensor, ...]:
        nonlocal grad
        xx = x.clone().requires_grad_(True)
        conv.zero_grad(set_to_none=True)
        y = conv(xx)
        grad = th.randn(y.shape, generator=th.Generator().manual_seed(2)) if grad is None else grad
        y.backward(grad)
        return y.detach(), xx.grad, conv.weight.grad.clone(), conv.bias.grad.clone()

    with torch_threads(1):
        plain = run()
    for help in (False, True):
        split = _in_thread(run, SplitWork(), help=help)
        assert all(th.equal(a, b) for a, b in zip(plain, split)), help


def test_the_modules_updates_split_their_products_and_train_the_same_networks(monkeypatch) -> None:
    """With one torch thread, a module's VAE and predictor fits post halves of their products that the thread waiting
    for them computes, and train the same networks to the bit as the same fits with every product whole."""
    import contextlib

    import numpy as np
    from gymnasium import spaces

    from sb3_gocu import GoalCuriosityModule
    from sb3_gocu.curiosity.training import Trainer

    th.set_num_threads(1)
    space = spaces.Box(0, 255, (16, 16, 3), np.uint8)
    settings = dict(n_goals=4, goal_buffer_size=32, predictor_hidden=(64, 64), predictor_pairs=512, predictor_train_freq=256,
                    vae_epochs=2, vae_patience=0, memory_size=256, pretrain_steps=64)
    frames = np.random.default_rng(0).integers(0, 4, (200, 2, 16, 16, 3), dtype=np.uint8) * 60

    def trained(split: bool) -> tuple[GoalCuriosityModule, int]:
        helped = [0]
        run2 = SplitWork.run2

        def counting(self, first, second):
            helped[0] += bool(self.helpers)
            return run2(self, first, second)

        with monkeypatch.context() as m:
            m.setattr(SplitWork, "run2", counting)
            if not split:
                m.setattr(Trainer, "_splitting", lambda self: contextlib.nullcontext())
            module = GoalCuriosityModule(space, seed=0, **settings)
            module.recording = True
            for t, f in enumerate(frames):
                module.step(f, np.array([t % 9 == 8, t % 13 == 12]))
            module.add_finished_episode_goals()
            module.train_vae()
            module.train_predictor()
        return module, helped[0]

    (a, helped_a), (b, helped_b) = trained(True), trained(False)
    assert helped_a > 0 and helped_b == 0
    for net in ("vae", "predictor"):
        sa, sb = getattr(a, net).state_dict(), getattr(b, net).state_dict()
        assert all(th.equal(sa[k], sb[k]) for k in sa), net
