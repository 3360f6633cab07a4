"""Scoring in a worker process: :class:`ProcessScorer`.

The process has its own interpreter and so its own GIL: the env stepping and the scoring no longer wait for each
other's. It keeps a copy of the encoder, of the folded predictor and of each env's goal halves, sent to it only
when they change; per step it receives the raw observations to embed and the memoised phi of the others, and sends
back phi and the rewards. It runs the same operations on the same inputs (:func:`~sb3_gocu.curiosity.scoring.score_rows`)
with as many torch threads as the caller had, so its values are the same to the bit as scoring in the caller
(``tests/test_scoring_process.py``). Messages to it are written by a writer thread, so the caller never waits for
room in the pipe. No SB3 import.
"""

from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import time
import traceback
import weakref
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import torch as th

from sb3_gocu.curiosity.scoring import score_rows


class _ProcessFuture:
    """What :meth:`ProcessScorer.submit` returns: ``result()`` waits for the process's answer (the rewards)."""

    def __init__(self, scorer: "ProcessScorer", ticket: Any, tid: int, answer_bytes: int) -> None:
        self._scorer, self.ticket, self.tid = scorer, ticket, tid
        self.answer_bytes = answer_bytes  # the answer's size, about
        self._done = False
        self._result: Any = None

    def done(self) -> bool:
        return self._done

    def result(self) -> Any:
        while not self._done:
            self._scorer._receive_one()
        return self._result


class _Writer:
    """Writes messages into a pipe, in order, from a thread of its own: the caller never waits for the reader to
    make room (a scoring process busy with earlier tickets; a trained agent's changed goal halves, ~100 KB a
    step, fill the 64 KiB pipe). ``error`` holds the ``OSError`` that ended it, if any."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.error: OSError | None = None
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="gocu-score-writer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            payload = self._queue.get()
            if payload is None:
                return
            try:
                self.conn.send_bytes(payload)
            except OSError as error:
                self.error = error
                return

    def send(self, payload: bytes) -> None:
        self._queue.put(payload)

    def stop(self) -> None:
        """Stop after the messages queued so far (it does not wait)."""
        self._queue.put(None)


class ProcessScorer:
    """Scores :class:`~sb3_gocu.curiosity.scoring.ScoringTicket` s in a child process, in submission order.

    The child is started with ``python -c`` (not ``multiprocessing``: the caller's script, guarded by
    ``if __name__ == "__main__"`` or not, is not run again) and talks over two pipes. It exits when the pipes close
    (this object is collected or :meth:`close` is called, or the parent dies).

    :param to_tensor: picklable callable turning a raw batch into the encoder's input (the module's adapter)
    :param num_threads: torch threads of the child (default: the caller's ``torch.get_num_threads()``, which
        keeps the values the same to the bit as scoring in the caller)
    """

    def __init__(self, to_tensor: Any, num_threads: int | None = None) -> None:
        num_threads = th.get_num_threads() if num_threads is None else int(num_threads)
        if num_threads < 1:
            raise ValueError(f"num_threads must be >= 1, got {num_threads}")
        to_child_r, to_child_w = os.pipe()
        from_child_r, from_child_w = os.pipe()
        code = f"from sb3_gocu.curiosity.process import _serve; _serve({to_child_r}, {from_child_w}, {num_threads})"
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code],
            pass_fds=(to_child_r, from_child_w),
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)},  # the caller's modules
        )
        os.close(to_child_r)
        os.close(from_child_w)
        self._send = _Writer(Connection(to_child_w, readable=False))
        self._recv = Connection(from_child_r, writable=False)
        self._finalizer = weakref.finalize(self, ProcessScorer._shutdown, self._send, self._recv, self._proc)
        self._send.send(pickle.dumps(("init", to_tensor), protocol=pickle.HIGHEST_PROTOCOL))
        self._encoder: Any = None  # the objects the child holds copies of
        self._folded: Any = None
        self._goal_versions: dict[int, int] = {}
        self._next_tid = 0
        self._in_flight: list[_ProcessFuture] = []  # in submission order, answers not received yet
        self.max_answer_bytes = 32 * 1024  # bound on their answers' sizes (see submit)
        self.bytes_sent = 0

    @staticmethod
    def _shutdown(send: _Writer, recv: Connection, proc: subprocess.Popen) -> None:
        send.stop()
        send._thread.join(timeout=10)  # the messages queued are written (the child reads them) before the pipe closes
        for conn in (send.conn, recv):
            try:
                conn.close()
            except OSError:
                pass
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()

    @property
    def _answer_bytes(self) -> int:
        """Sizes of the answers not received yet, about."""
        return sum(f.answer_bytes for f in self._in_flight)

    def close(self) -> None:
        """Wait for the answers still due, then stop the child."""
        while self._in_flight:
            self._receive_one()
        self._finalizer()

    def submit(self, ticket: Any, eq13_args: tuple[float, str, float], goal_parts: th.Tensor, goal_versions: np.ndarray) -> _ProcessFuture:
        """Send a ticket (its ``miss`` rows: phi known or to embed, their envs' goals) to the child.

        :param goal_parts: every env's current goal halves, (n_envs, K, h): the rows of the ticket's envs whose
            version the child does not have are copied into the message
        :param goal_versions: their versions, (n_envs,)
        """
        if self._proc.poll() is not None or self._send.error is not None:
            raise self._ended()
        # the child answers in order into a pipe that holds 64 KiB: if the answers not read yet outgrew it, the
        # child would block writing one and stop reading, and the messages queued for the writer thread would pile
        # up (a caller submitting many tickets before collecting). Read answers first while they would pass the bound.
        answer_bytes = self._answer_size(ticket)
        while self.would_wait(ticket):
            self._receive_one()
        tid = self._next_tid
        self._next_tid += 1
        miss = ticket.miss
        phi = ticket.phi[miss]
        embed_pos = np.searchsorted(miss, ticket.embed_rows)
        refs = []  # (position in miss, earlier tid, earlier row): phi the child is computing (or has)
        for j, earlier, row in ticket.phi_from:
            pos = int(np.searchsorted(miss, j))
            fut = earlier.future
            if isinstance(fut, _ProcessFuture) and fut._scorer is self and not fut.done():
                refs.append((pos, fut.tid, int(np.searchsorted(earlier.miss, row))))
            else:  # computed in the caller, or its answer is back: the caller has it
                if fut is not None:
                    fut.result()
                phi[pos] = earlier.phi[row]
        envs = ticket.env_indices[miss]
        goals: dict[int, th.Tensor] = {}
        for e, version in zip(envs.tolist(), goal_versions[envs].tolist()):
            if self._goal_versions.get(e) != version:
                goals[e] = goal_parts[e].clone()
                self._goal_versions[e] = version
        message: dict[str, Any] = {
            "tid": tid, "phi": phi, "embed_pos": embed_pos, "raw": ticket.raw if len(embed_pos) else None, "refs": refs,
            "envs": envs, "has_goals": ticket.has_goals, "goals": goals, "eq13": eq13_args,
            "keep_from": self._in_flight[0].tid if self._in_flight else tid,
        }
        if len(embed_pos) and ticket.encoder is not self._encoder:
            message["encoder"] = self._encoder = ticket.encoder
        if ticket.folded is not self._folded:
            message["folded"] = self._folded = ticket.folded
        payload = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self.bytes_sent += len(payload)
        self._send.send(payload)  # written by the writer thread, in order
        future = _ProcessFuture(self, ticket, tid, answer_bytes)
        self._in_flight.append(future)
        return future

    @staticmethod
    def _answer_size(ticket: Any) -> int:
        return len(ticket.miss) * (ticket.phi.shape[1] + 1) * 4 + 1024

    def would_wait(self, ticket: Any) -> bool:
        """Whether :meth:`submit` would first wait for answers (their bound, ``max_answer_bytes``)."""
        return bool(self._in_flight) and self._answer_bytes + self._answer_size(ticket) > self.max_answer_bytes

    def unanswered(self) -> int:
        """Take the answers already sent (without waiting) and return how many tickets are still unanswered."""
        try:
            while self._in_flight and self._recv.poll():
                self._receive_one()
        except (EOFError, OSError) as error:
            raise self._ended() from error
        return len(self._in_flight)

    def _ended(self) -> RuntimeError:
        return RuntimeError(
            f"the GoCu scoring process ended (exit code {self._proc.poll()}; its error output, if any, is above): "
            "the scores in flight are lost, so the run cannot go on"
        )

    def _receive_one(self) -> None:
        future = self._in_flight[0]
        try:
            answer = pickle.loads(self._recv.recv_bytes())
        except (EOFError, OSError) as error:
            raise self._ended() from error
        if answer[0] == "error":
            self._in_flight.pop(0)
            future._done = True
            raise RuntimeError(f"the GoCu scoring process failed:\n{answer[1]}")
        tid = answer[1]
        if tid != future.tid:
            raise RuntimeError(f"the GoCu scoring process answered ticket {tid}, expected {future.tid}")
        self._in_flight.pop(0)
        _, _, phi, rewards, wall, cpu = answer
        ticket = future.ticket
        ticket.phi[ticket.miss] = phi
        ticket.compute_time, ticket.compute_cpu_time = wall, cpu
        future._result = rewards
        future._done = True


def _serve(read_fd: int, write_fd: int, num_threads: int) -> None:
    """The child's loop: answer every ticket in order; exit when the parent closes its end. A ticket's
    ``refs`` point at rows (positions in ``miss``) of earlier tickets whose phi the parent has not taken yet."""
    th.set_num_threads(num_threads)
    recv, send = Connection(read_fd, writable=False), Connection(write_fd, readable=False)
    to_tensor = encoder = folded = None
    goals: dict[int, th.Tensor] = {}
    phis: dict[int, np.ndarray] = {}  # phi of the tickets the parent has not taken yet
    while True:
        try:
            message = pickle.loads(recv.recv_bytes())
        except (EOFError, OSError):
            return
        try:
            if isinstance(message, tuple):
                to_tensor = message[1]
                continue
            for tid in [t for t in phis if t < message["keep_from"]]:
                del phis[tid]
            t0, c0 = time.perf_counter(), time.thread_time()
            encoder = message.get("encoder", encoder)
            folded = message.get("folded", folded)
            goals.update(message["goals"])
            phi = message["phi"]
            for pos, tid, row in message["refs"]:
                phi[pos] = phis[tid][row]
            envs = message["envs"].tolist()
            goal_parts = th.stack([goals[e] for e in envs]) if envs else th.zeros(0)
            rewards = score_rows(
                phi, message["embed_pos"], message["raw"], encoder, to_tensor, goal_parts, message["has_goals"], folded, message["eq13"]
            )
            phis[message["tid"]] = phi
            answer = ("ok", message["tid"], phi, rewards, time.perf_counter() - t0, time.thread_time() - c0)
        except BaseException:
            answer = ("error", traceback.format_exc())
        send.send_bytes(pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL))

