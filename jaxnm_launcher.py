"""The ``jaxnm`` command's entry point.

It lives outside the ``jaxnm`` package so that it runs before ``import jaxnm`` imports JAX.
It blocks SIGINT in the main thread, so that every thread started later (JAX's and XLA's
included) has it blocked too, and receives it on a thread of its own (`SigintThread`,
``signal.sigwait``). A Ctrl-C is then handled at once whatever the main thread is doing —
importing JAX's compiled extensions, or waiting for XLA to compile — without an exception
being raised there: `jaxnm.cli.main` gets the thread and hands Ctrl-C to its own handler.
"""

import os
import signal
import sys
import threading

__all__ = ["SigintThread", "main"]


class SigintThread:
    """Receives SIGINT on a daemon thread and calls `handler(signum, frame)` with it (from
    that thread); until a handler is set, counts the Ctrl-Cs (`count`), and ends the process
    at once (exit code 130) on the second. Start it only while SIGINT is blocked in every
    thread of the process (`start`)."""

    def __init__(self):
        self.handler = None
        self.count = 0

    @classmethod
    def start(cls):
        """Block SIGINT in the calling (main) thread, before any other thread exists, and
        start receiving it; None where SIGINT is ignored or not the default handler's, or
        off the main thread."""
        if (threading.current_thread() is not threading.main_thread()
                or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
            return None
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        receiver = cls()
        threading.Thread(target=receiver._receive, name="jaxnm-sigint", daemon=True).start()
        return receiver

    def _receive(self) -> None:
        while True:
            signum = signal.sigwait({signal.SIGINT})
            handler = self.handler
            if handler is not None:
                handler(signum, None)
                continue
            self.count += 1
            if self.count > 1:
                os.write(2, b"\njaxnm: stopped\n")
                os._exit(130)


def main() -> int:
    """Run the ``jaxnm`` command with ``sys.argv``; returns its exit code."""
    receiver = SigintThread.start()
    from jaxnm.cli import main as run  # imports JAX

    return run(sigint=receiver)


if __name__ == "__main__":
    sys.exit(main())
