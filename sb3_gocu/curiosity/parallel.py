"""Split products: a curiosity update shares its matrix products with a thread that would only wait.

While PPO's training thread waits for a VAE or predictor update (``overlap_ppo_update``), its core is idle.
With ``split_updates`` on, every large product of an update is computed as two halves, and the second half of
each is posted to a :class:`SplitWork`: a linear layer by its output columns (for the input gradient, by the
input columns), a convolution by halves of the minibatch (output and input gradient) and of its output channels
(weight and bias gradients). The waiting thread (:meth:`SplitWork.help`) takes the second half and runs it
beside the first; when nobody waits, the update's own thread runs both halves, one after the other.

Such a cut leaves the sum behind every output element as it was (the same terms in the same order), so a half
equals its part of the whole product computed in one piece, to the bit, with one torch thread, on the CPU we ran
(tested in ``tests/test_parallel.py`` for the default networks; narrow or odd widths, which take other kernels,
stay whole: ``SPLIT_MULTIPLE``). Whoever computes a half, it is computed the same way (with one torch thread),
so a run's values never depend on when the training thread starts to help.

:class:`SplitLinear`, :class:`SplitConv2d` and :class:`SplitConvTranspose2d` are the torch layers (same
parameters, same initialisation, same state dict) that take the split path only in a thread inside
:func:`splitting`; everywhere else they are the plain layers. Nothing here imports SB3.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Any, Callable, Iterator

import torch as th
from torch import nn
from torch.nn import functional as F

_local = threading.local()

#: a layer is split only if its output width (features or channels) is a multiple of this; an input gradient
#: is split only if the input width is too. Narrow or odd widths take other kernels in the BLAS we ran (for
#: instance a 10-wide half), whose sums are not those of the whole product, so they stay whole.
SPLIT_MULTIPLE = 32


class _Half:
    """A posted half: the callable, whether a thread took it, and its outcome."""

    __slots__ = ("fn", "claimed", "done", "result", "error")

    def __init__(self, fn: Callable[[], Any]) -> None:
        self.fn = fn
        self.claimed = False
        self.done = threading.Event()
        self.result: Any = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with th.no_grad():
                self.result = self.fn()
        except BaseException as error:  # re-raised in the thread that posted it
            self.error = error
            if not isinstance(error, Exception):
                raise  # a KeyboardInterrupt (or SystemExit) also stops the helping thread
        finally:
            self.done.set()


class SplitWork:
    """Work sharing between an update's thread (:meth:`run2`) and threads that wait for it (:meth:`help`)."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._posted: _Half | None = None
        self._helpers = 0  # threads inside help()

    @property
    def helpers(self) -> int:
        """Threads inside :meth:`help` now."""
        return self._helpers

    def run2(self, first: Callable[[], Any], second: Callable[[], Any]) -> tuple[Any, Any]:
        """``(first(), second())``: ``first`` here, ``second`` in a helping thread if one takes it in time,
        else here after ``first``. Both must run with one torch thread (the calling thread's count)."""
        if not self._helpers:  # nobody to take it (one arriving meanwhile finds the next half)
            return first(), second()
        half = _Half(second)
        with self._cv:
            self._posted = half
            self._cv.notify()
        a = first()
        with self._cv:
            mine = not half.claimed
            if mine:
                half.claimed = True
                self._posted = None
        if mine:
            return a, second()
        half.done.wait()
        if half.error is not None:
            raise half.error
        return a, half.result

    def help(self, finished: threading.Event) -> None:
        """Run posted halves, with one torch thread, until ``finished`` is set (call :meth:`wake` after
        setting it, so a helper waiting for work sees it at once)."""
        before = th.get_num_threads()
        if before != 1:
            th.set_num_threads(1)
        with self._cv:
            self._helpers += 1
        try:
            while True:
                with self._cv:
                    while self._posted is None:
                        if finished.is_set():
                            return
                        self._cv.wait(0.05)
                    half, self._posted = self._posted, None
                    half.claimed = True
                half.run()
        finally:
            with self._cv:
                self._helpers -= 1
            if before != 1:
                th.set_num_threads(before)

    def wake(self) -> None:
        """Wake the helpers (after the work they help with has finished)."""
        with self._cv:
            self._cv.notify_all()


@contextlib.contextmanager
def splitting(work: SplitWork | None) -> Iterator[None]:
    """In the calling thread, let :class:`SplitLinear` and :class:`SplitConv2d` split their products and post
    halves to ``work`` (None: leave them whole). The thread must run with one torch thread."""
    before = getattr(_local, "work", None)
    _local.work = work
    try:
        yield
    finally:
        _local.work = before


def _active() -> SplitWork | None:
    return getattr(_local, "work", None)


class _SplitLinearFn(th.autograd.Function):
    """``F.linear`` with each product in two column halves (see the module docstring), each written straight
    into its columns of the result."""

    @staticmethod
    def forward(ctx: Any, x: th.Tensor, weight: th.Tensor, bias: th.Tensor | None, work: SplitWork) -> th.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.work, ctx.has_bias = work, bias is not None
        n = weight.shape[0]
        out = x.new_empty((x.shape[0], n))

        def half(cols: slice) -> None:  # as F.linear: addmm(bias, x, W^T)
            if bias is None:
                th.mm(x, weight[cols].t(), out=out[:, cols])
            else:
                th.addmm(bias[cols], x, weight[cols].t(), out=out[:, cols])

        work.run2(lambda: half(slice(0, n // 2)), lambda: half(slice(n // 2, n)))
        return out

    @staticmethod
    def backward(ctx: Any, grad: th.Tensor) -> tuple[th.Tensor | None, ...]:
        x, weight = ctx.saved_tensors
        (n, k), need_x = weight.shape, ctx.needs_input_grad[0]
        gx = grad.new_empty((grad.shape[0], k)) if need_x else None
        gw = grad.new_empty((n, k))

        def half(out_rows: slice, in_cols: slice) -> None:
            # as addmm's backward: input grad = grad @ W (cut by input columns), weight grad = grad^T @ x (cut
            # by output rows)
            if need_x:
                th.mm(grad, weight[:, in_cols], out=gx[:, in_cols])
            th.mm(grad[:, out_rows].t(), x, out=gw[out_rows])

        ctx.work.run2(lambda: half(slice(0, n // 2), slice(0, k // 2)), lambda: half(slice(n // 2, n), slice(k // 2, k)))
        return gx, gw, grad.sum(0) if ctx.has_bias else None, None


class SplitLinear(nn.Linear):
    """``nn.Linear`` whose products are split in two column halves inside :func:`splitting` (2-D inputs, input
    and output features multiples of ``SPLIT_MULTIPLE``; otherwise the plain layer)."""

    def forward(self, x: th.Tensor) -> th.Tensor:
        work = _active()
        if (
            work is None or x.dim() != 2 or x.dtype != self.weight.dtype
            or self.out_features % SPLIT_MULTIPLE or self.in_features % SPLIT_MULTIPLE
        ):
            return super().forward(x)
        return _SplitLinearFn.apply(x, self.weight, self.bias, work)


def _conv_backward(grad: th.Tensor, x: th.Tensor, weight: th.Tensor, conv: nn.Conv2d | nn.ConvTranspose2d, mask: list[bool]) -> tuple:
    transposed = isinstance(conv, nn.ConvTranspose2d)
    return th.ops.aten.convolution_backward(
        grad, x, weight, [weight.shape[1] if transposed else weight.shape[0]], list(conv.stride), list(conv.padding),
        list(conv.dilation), transposed, list(conv.output_padding) if transposed else [0, 0], conv.groups, mask,
    )


class _SplitConvFn(th.autograd.Function):
    """A convolution (``nn.Conv2d`` or ``nn.ConvTranspose2d``) in two halves: the output and the input gradient
    by halves of the minibatch (each sample's rows are computed on their own), the weight and bias gradients by
    halves of the output channels (a ``Conv2d`` whose output channels are a multiple of ``SPLIT_MULTIPLE``;
    otherwise whole, beside the first half of the input gradient)."""

    @staticmethod
    def forward(ctx: Any, x: th.Tensor, weight: th.Tensor, bias: th.Tensor | None, conv: nn.Conv2d | nn.ConvTranspose2d, work: SplitWork) -> th.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.work, ctx.conv, ctx.has_bias = work, conv, bias is not None
        m = x.shape[0] // 2

        def rows(part: th.Tensor) -> th.Tensor:  # as the layer's own forward
            if isinstance(conv, nn.ConvTranspose2d):
                return F.conv_transpose2d(part, weight, bias, conv.stride, conv.padding, conv.output_padding, conv.groups, conv.dilation)
            return F.conv2d(part, weight, bias, conv.stride, conv.padding, conv.dilation, conv.groups)

        a, b = work.run2(lambda: rows(x[:m]), lambda: rows(x[m:]))
        return th.cat([a, b])

    @staticmethod
    def backward(ctx: Any, grad: th.Tensor) -> tuple[th.Tensor | None, ...]:
        x, weight = ctx.saved_tensors
        conv, bias = ctx.conv, ctx.has_bias
        need_x = ctx.needs_input_grad[0]
        m, c = x.shape[0] // 2, weight.shape[0]  # c: a Conv2d's output channels (a ConvTranspose2d's weight is (in, out, ...))
        split_w = not isinstance(conv, nn.ConvTranspose2d) and c % SPLIT_MULTIPLE == 0

        def half(rows: slice, out_ch: slice | None) -> tuple[th.Tensor | None, th.Tensor | None, th.Tensor | None]:
            gx = _conv_backward(grad[rows], x[rows], weight, conv, [True, False, False])[0] if need_x else None
            if out_ch is None:
                return gx, None, None
            _, gw, gb = _conv_backward(grad[:, out_ch].contiguous(), x, weight[out_ch], conv, [False, True, bias])
            return gx, gw, gb

        first, second = (slice(0, c // 2), slice(c // 2, c)) if split_w else (slice(None), None)  # None: whole in the first
        (gx_a, gw_a, gb_a), (gx_b, gw_b, gb_b) = ctx.work.run2(
            lambda: half(slice(0, m), first), lambda: half(slice(m, None), second)
        )
        gx = th.cat([gx_a, gx_b]) if need_x else None
        gw = th.cat([gw_a, gw_b]) if split_w else gw_a
        gb = (th.cat([gb_a, gb_b]) if split_w else gb_a) if bias else None
        return gx, gw, gb, None, None


def _conv_splits(conv: nn.Conv2d | nn.ConvTranspose2d, x: th.Tensor) -> SplitWork | None:
    work = _active()
    if (
        work is None or conv.groups != 1 or conv.padding_mode != "zeros" or isinstance(conv.padding, str)
        or x.dim() != 4 or x.shape[0] < 2 or x.dtype != conv.weight.dtype
    ):
        return None
    return work


class SplitConv2d(nn.Conv2d):
    """``nn.Conv2d`` computed in two halves inside :func:`splitting` (zero padding, one group, 4-D inputs of at
    least two samples; otherwise the plain layer): see :class:`_SplitConvFn`."""

    def forward(self, x: th.Tensor) -> th.Tensor:
        work = _conv_splits(self, x)
        return super().forward(x) if work is None else _SplitConvFn.apply(x, self.weight, self.bias, self, work)


class SplitConvTranspose2d(nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` computed in two halves inside :func:`splitting` (as :class:`SplitConv2d`; no
    ``output_size`` argument); the weight gradient stays whole."""

    def forward(self, x: th.Tensor, output_size: list[int] | None = None) -> th.Tensor:
        work = None if output_size is not None else _conv_splits(self, x)
        return super().forward(x, output_size) if work is None else _SplitConvFn.apply(x, self.weight, self.bias, self, work)
