"""Ctrl-C and warnings for the command line's own process.

**Where SIGINT arrives.** Run as the ``jaxnm`` command, through `jaxnm_launcher`, SIGINT
comes on a thread of its own, at once, whatever the main thread is doing; `CtrlC.install`
takes it from there. Called from Python (`jaxnm.cli.main`), the handler is Python's signal
handler, which runs in the main thread when that thread next runs Python code (after a
compilation it is waiting for, say).

**Why the SIGINT handler never raises.** Python runs a signal handler in the main thread
between two bytecodes, wherever that thread is: in the middle of an import of JAX's compiled
extensions, in a garbage-collector callback of XLA's, or while JAX waits for a program that
XLA compiles on a thread of its own. A ``KeyboardInterrupt`` raised there abandons the
compilation, which goes on and then uses the XLA client that the exiting interpreter has
already torn down (a segmentation fault), or it is swallowed (a callback's exception is only
printed) and the command carries on as if nothing had happened. So the handler only records
the Ctrl-C; the command looks at it where stopping is safe (`CtrlC.check`, between fit
steps, between outputs), and a second Ctrl-C ends the process at once with ``os._exit``,
which runs no interpreter teardown.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

__all__ = ["CtrlC", "Interrupted", "one_line_warnings", "hard_exit"]

#: How a second Ctrl-C ends the process (the tests replace it).
hard_exit = os._exit

_FIRST = {
    "prepare": "stopping after this stage",
    "fit": "stopping after this step, then writing the map and the report",
    "writing": "writing the map and the report only",
}


class Interrupted(Exception):
    """A Ctrl-C, noticed at a stage boundary before anything was written."""


class CtrlC:
    """The command line's SIGINT handler: records Ctrl-C, never raises (see the module).

    - `command`: ``"jaxnm fit"``, for the messages.
    - `phase`: what the command is doing: ``"prepare"`` (reading, rendering, preparing,
      compiling), then for a fit ``"fit"`` and ``"writing"``.
    - `requested`: the phase of the first Ctrl-C, or None.
    - `output`: the folder whose unfinished temporary files a second Ctrl-C removes.
    """

    def __init__(self, command: str = "jaxnm"):
        self.command = command
        self.phase = "prepare"
        self.requested = None
        self.output: Path | None = None
        self._previous = None
        self._receiver = None

    def install(self, receiver=None) -> CtrlC:
        """Handle SIGINT from now on: from ``receiver`` (the launcher's
        `jaxnm_launcher.SigintThread`, whose Ctrl-Cs so far count as the first) or else as
        Python's signal handler (not where SIGINT is ignored, nor outside the main thread).
        `uninstall` puts the previous handler back."""
        if receiver is not None:
            self._receiver = receiver
            if receiver.count:
                self.requested = "prepare"
            receiver.handler = self
        elif (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
            self._previous = signal.signal(signal.SIGINT, self)
        return self

    def uninstall(self) -> None:
        if self._receiver is not None:
            self._receiver.handler = None
            self._receiver = None
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None

    def as_keyboard_interrupt(self) -> None:
        """From now on, a Ctrl-C raises ``KeyboardInterrupt`` in the main thread, as Python
        does by default (a fit across processes: the scheduler signals every process)."""
        if self._receiver is not None:
            import _thread

            self._receiver.handler = lambda signum, frame: _thread.interrupt_main()
            self._receiver = None
        elif self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None

    def __call__(self, signum, frame) -> None:
        if self.requested is not None:
            self.stop_now()
            return
        self.requested = self.phase
        # (os.write: a print here could re-enter one the handler interrupted)
        os.write(2, f"\n{self.command}: Ctrl-C: {_FIRST[self.phase]} (Ctrl-C again to stop "
                    "at once)\n".encode())

    def check(self) -> None:
        """Raise `Interrupted` if Ctrl-C was pressed before the fit (a stage boundary)."""
        if self.requested == "prepare":
            raise Interrupted

    def stop_now(self) -> None:
        """End the process at once, exit code 130, after removing the temporary files of
        this process's unfinished writes in `output` (the files themselves stay as they
        were: every file is written atomically)."""
        os.write(2, f"\n{self.command}: stopped\n".encode())
        if self.output is not None:
            from ..io import unfinished_writes

            for p in unfinished_writes(self.output):
                p.unlink(missing_ok=True)
        sys.stdout.flush()
        hard_exit(130)


@contextlib.contextmanager
def one_line_warnings(command: str):
    """Within the block, show each warning as one line on stderr, ``jaxnm fit: warning:
    MESSAGE`` (jaxnm's own, whose messages name the file) or ``jaxnm fit: warning:
    CATEGORY: MESSAGE`` (others), instead of Python's two lines with a source line."""

    def show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        if not category.__module__.startswith("jaxnm"):
            text = f"{category.__name__}: {text}"
        print(f"{command}: warning: {text}", file=file or sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield
