"""``jaxnm fit --distributed``: one process of a fit across processes (`jax.distributed`)."""

from __future__ import annotations

import inspect
import math
import os
import sys
from pathlib import Path

from ._fit import CHECKPOINT_NAME, DEFAULT_TIMEOUT, check_arguments
from ._fit import run as run_fit
from ._interrupt import CtrlC

__all__ = ["run"]


def _join(args) -> None:
    """Join a fit across processes (``--distributed``): gloo for the CPU's collectives (the
    command line's choice, made before JAX starts a backend), then
    ``jax.distributed.initialize`` with what the command line gives (else auto-detected)."""
    explicit = (args.coordinator, args.num_processes, args.process_id)
    if not args.distributed:
        raise ValueError("--coordinator, --num-processes and --process-id need --distributed")
    if any(v is not None for v in explicit) and not all(v is not None for v in explicit):
        raise ValueError("--coordinator, --num-processes and --process-id go together")
    if args.num_processes is not None and args.num_processes < 1:
        raise ValueError(f"--num-processes must be at least 1, got {args.num_processes}")
    if args.num_processes is not None and not 0 <= args.process_id < args.num_processes:
        raise ValueError(f"--process-id must be 0 to {args.num_processes - 1}, got "
                         f"{args.process_id}")
    if args.coordinator is not None:
        _host_port(args.coordinator)
    timeout = DEFAULT_TIMEOUT if args.timeout is None else args.timeout
    if not (math.isfinite(timeout) and timeout >= 1):
        raise ValueError(f"--timeout must be a number of seconds >= 1, got {timeout}")
    if args.store:
        raise ValueError("--store is not available with --distributed (it fits the map through "
                         "its storage on one process: run it without --distributed)")
    import jax

    if "jax_cpu_collectives_implementation" in jax.config.values:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    t = max(1, int(timeout))
    timeouts = {"initialization_timeout": t, "heartbeat_timeout_seconds": t}
    if "shutdown_timeout_seconds" in inspect.signature(jax.distributed.initialize).parameters:
        timeouts["shutdown_timeout_seconds"] = t  # (not in the oldest JAX jaxnm supports)
    if args.coordinator is not None and args.process_id != 0:
        _wait_for(args.coordinator, t)  # (process 0 serves it)
    try:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id,
                                   **timeouts)
    except Exception as e:  # noqa: BLE001 (one line, whatever the runtime raised)
        if args.coordinator is None and isinstance(e, ValueError):
            raise ValueError(f"--distributed: no cluster was detected to join (SLURM, Open "
                             f"MPI, a cloud cluster); give --coordinator HOST:PORT, "
                             f"--num-processes N and --process-id I ({_first_line(e)})"
                             ) from None
        where = args.coordinator or "the detected cluster"
        raise _Lost(f"could not join the other processes through {where} within {t} s: "
                    f"{_first_line(e)}") from None


def _host_port(address: str) -> tuple[str, int]:
    """``--coordinator``'s host and port, or a ValueError naming the flag."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--coordinator must be HOST:PORT (process 0's address and a free "
                         f"port, 1 to 65535), got {address!r}")
    return host.strip("[]"), int(port)


def _wait_for(address: str, seconds: float) -> None:
    """Wait until process 0's coordinator at ``address`` takes a connection, for at most
    ``seconds``; else `_Lost`. JAX's own wait for an unreachable coordinator ends the process
    with a fatal error and a native stack trace, not an exception."""
    import socket
    import time

    host, port = _host_port(address)
    end = time.monotonic() + seconds
    while True:
        try:
            with socket.create_connection((host, port), timeout=min(5.0, seconds)):
                return
        except OSError as e:
            if time.monotonic() >= end:
                raise _Lost(f"could not reach the coordinator {address} within "
                            f"{seconds:g} s ({e.strerror or e}); is process 0 running "
                            f"there?") from None
        time.sleep(0.25)


class _Lost(RuntimeError):
    """A fit across processes lost (or never reached) another process."""


def _first_line(e: BaseException) -> str:
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return f"{type(e).__name__}: {lines[0] if lines else ''}"


def _fit_identity(args, overrides: dict) -> dict:
    """What every process of a fit across processes must agree on: the fit file (a hash of
    its bytes), the options the command line changes, the output folder and the process
    count each was told."""
    import hashlib

    import jax

    fit = (hashlib.sha256(Path(args.config).read_bytes()).hexdigest()[:16] if args.config
           else f"built-in (quick {args.quick})")
    return {"the fit file": fit, "the options": sorted(overrides.items()),
            "the time limit": args.time_limit, "the output folder": str(args.output),
            "--resume": args.resume, "--checkpoint-every": args.checkpoint_every,
            "the process count": (args.num_processes if args.num_processes is not None
                                  else jax.process_count())}


def run(args) -> int:
    """``jaxnm fit --distributed``: the fit in a fit across processes. Any error ends the
    process at once with one line naming it (``jaxnm fit: error: process I of N: ...``;
    exit code 2 for bad input, 1 for a lost process), without the runtime's shutdown
    (whose barrier would wait for, and then report, the processes that are gone)."""
    where = "jaxnm fit: error"
    try:
        _join(args)
        import jax

        where = f"jaxnm fit: error: process {jax.process_index()} of {jax.process_count()}"
        # no Ctrl-C handler: a stop must reach every process (the scheduler signals them all)
        code = _fit_here(args)
    except (ValueError, FileNotFoundError, ImportError) as e:
        lost = _is_lost(e)
        msg = (f"lost another process ({_first_line(e)})" if lost
               else str(e).splitlines()[0] if str(e) else type(e).__name__)
        return _exit_now(f"{where}: {msg}", 1 if lost else 2)
    except _Lost as e:
        return _exit_now(f"{where}: {e}", 1)
    except KeyboardInterrupt:
        return _exit_now(f"{where}: interrupted", 130)
    except Exception as e:  # noqa: BLE001 (the runtime's errors: one line, not a trace)
        what = "lost another process" if _is_lost(e) else "failed"
        return _exit_now(f"{where}: {what} ({_first_line(e)})", 1)
    return code


def _is_lost(e: BaseException) -> bool:
    """Whether ``e`` is a collective or the coordination service failing for want of another
    process (gloo's, or the distributed runtime's, error)."""
    text = str(e)
    return any(k in text for k in ("Gloo", "gloo", "Connection closed", "coordination",
                                   "heartbeat", "DEADLINE_EXCEEDED", "UNAVAILABLE"))


def _exit_now(line: str, code: int) -> int:
    """Print ``line`` and end the process with ``code`` at once (no interpreter shutdown:
    `jax.distributed`'s would wait at a barrier for the processes that are gone)."""
    print(line, file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(code)



def _fit_here(args) -> int:
    """This process's part: check that every process runs the same fit, before anything is
    read, then read this process's own views (the held-out ones on process 0) and fit."""
    import jax

    from ..fit import check_same_across_processes, process_targets

    me, count = jax.process_index(), jax.process_count()
    if args.config and not Path(args.config).is_file():
        raise FileNotFoundError(f"{args.config}: no such fit file")
    identity = _fit_identity(args, check_arguments(args))
    if args.resume:
        identity["a checkpoint to resume from"] = (Path(args.output) / CHECKPOINT_NAME).is_file()
    check_same_across_processes(identity, what="jaxnm fit --distributed")

    def images(key, targets):  # this process's views; the held-out ones on process 0
        if key == "held_out":
            return range(len(targets)) if me == 0 else ()
        return process_targets(targets, count)[me]

    return run_fit(args, CtrlC("jaxnm fit"), process=(me, count),
                   images=images if args.config else None)
