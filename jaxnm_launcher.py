"""The ``jaxnm`` command's entry point.

It lives outside the ``jaxnm`` package so that it runs before ``import jaxnm``, which imports
JAX (about a second): a Ctrl-C in that second is recorded here instead of raising
``KeyboardInterrupt`` inside the import of JAX's compiled extensions (which can crash the
interpreter as it exits), and `jaxnm.cli.main` stops at its first stage boundary. A second
Ctrl-C ends the process at once.
"""

import os
import signal
import sys
import threading


def main() -> int:
    """Run the ``jaxnm`` command with ``sys.argv``; returns its exit code."""
    early: list[int] = []

    def record(signum, frame) -> None:
        early.append(signum)
        if len(early) > 1:
            os.write(2, b"\njaxnm: stopped\n")
            os._exit(130)

    if (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
        signal.signal(signal.SIGINT, record)
    from jaxnm.cli import main as run  # imports JAX

    return run(interrupted=len(early))


if __name__ == "__main__":
    sys.exit(main())
