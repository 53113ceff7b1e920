"""The grating readers' own event loop, on a thread of the real-time process.

Why a thread: polling a serial port stalls the poller in the kernel. When a tty has no input
ready, the kernel's ``poll`` (``n_tty_poll``) first waits for the port's flip-buffer work to finish
moving received bytes to the line discipline (``flush_work``), uninterruptibly (``D``). That work
runs on a kernel worker thread (``kworker/u…``) at normal priority: on a loaded machine it waits
behind the fit workers and the HTTP side, and whatever polled the tty waits with it — a priority
inversion no ``SCHED_FIFO`` priority of ours can cure. The readers' event loop polls their ttys
after every readiness (``epoll`` re-checks a level-triggered file on each wait, pyserial's ``read``
selects again after each chunk); sharing one event loop with the RSI endpoint, every such wait held
the next telegram's reply: 16 048 such waits in 40 s of a 4 ms run under fits and HTTP load, the
longest several milliseconds, each one a late or lost reply (docs/reliability.md).

On a thread of their own the readers wait alone: their ``epoll`` holds the ttys and nothing else,
the RSI endpoint's holds no tty, and a thread blocked in the kernel has released the interpreter's
lock. The thread inherits the real-time process's CPU and ``SCHED_FIFO`` priority (it is started
after :func:`comp_daemon.rt.scheduling.apply_scheduling`): at the same priority neither pre-empts
the other, so the RSI callback never waits for the interpreter's lock held by a pre-empted reader,
only for the reader's current step (a frame parsed, the next poll scheduled: tens of µs).

The loop runtime reads each reader's latest reading (:meth:`EncoderReader.reading`: attribute reads,
no I/O) from the RSI thread; the reader writes it whole (one tuple) from this thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading

from comp_daemon.rt.encoder_reader import EncoderReader

__all__ = ["ReaderThread"]


class ReaderThread:
    """An event loop on a daemon thread that runs the grating readers (start, stop, close)."""

    def __init__(self, name: str = "rt-gratings") -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_forever()
        finally:
            pending = asyncio.all_tasks(self.loop)
            for task in pending:
                task.cancel()
            if pending:
                self.loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            self.loop.close()

    async def start(self, reader: EncoderReader) -> None:
        """Start ``reader``'s task on this thread's loop."""

        async def begin() -> None:
            reader.start()

        await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(begin(), self.loop))

    async def stop(self, reader: EncoderReader) -> None:
        """Stop ``reader`` (its task ends, its port closes) on this thread's loop."""
        if self.loop.is_closed():
            return
        await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(reader.stop(), self.loop))

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the loop (tasks still running are cancelled) and wait for the thread."""
        with contextlib.suppress(RuntimeError):  # already closed
            self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout_s)
