"""Command line: ``jaxnm render``, ``jaxnm fit`` and ``jaxnm bake``.

    jaxnm render [SCENE.json | MESH] [-o out.png] [--aovs out.npz] [--derivatives MODE]
                 [--frame FRAME] [--light X,Y,Z ...] [--normal-map PATH] [--width W --height H]
    jaxnm fit [FIT.json] [-o OUTDIR] [--checkpoint-every SECONDS] [--resume] ...
    jaxnm fit FIT.json --distributed [--coordinator HOST:PORT --num-processes N
                                      --process-id I] [--timeout SECONDS] ...
    jaxnm bake HIGH [LOW | --decimate N] -o OUTDIR [--method raycast|fit|both] ...

Options override the scene (or fit) file; with no file the built-in scene or
problem (a rivet-mapped torus, generated in code) is used. Errors in the
input are one line naming the file and the field, with exit code 2; warnings are one line
each (``jaxnm fit: warning: ...``).

**Ctrl-C.** The commands handle SIGINT themselves: the first Ctrl-C is noticed at
the next stage boundary (after reading, after preparing the views, after compiling), between
fit steps, and between outputs. Before the fit the command then stops (exit code 130); during
the fit it stops after the current step; while the outputs are written it leaves out the
optional ones (held-out scores, renders, the loss plot). Either way, once a fit has run,
``normal_map.png``, ``normal_map.npz`` and ``report.json`` are written, the report saying
what was interrupted, and the exit code is 130. A second Ctrl-C ends the process at once;
every file is written atomically, so none is ever left half-written.

``jaxnm fit`` keeps a checkpoint in ``OUTDIR/checkpoint.npz`` while it fits (by default every
30 s); ``--resume`` carries on from it. It is removed when the fit ends, unless the fit was
interrupted, ``--keep-checkpoint`` is given or ``--checkpoint-every`` set.

``jaxnm fit --distributed`` is one process of a fit across processes (one per host): it joins
the others through ``jax.distributed.initialize`` (found from SLURM, Open MPI or a cloud TPU
or GPU cluster, or given by ``--coordinator``, ``--num-processes`` and ``--process-id``),
with gloo for the CPU's collectives, reads and prepares only its own views
(`jaxnm.fit.prepare_processes`), and process 0 writes the outputs and the checkpoints. The
processes first check that they run the same fit (fit file, options, process count) and
refuse in one line if not; a process that stops makes the others stop with one line.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ._interrupt import CtrlC, Interrupted, one_line_warnings

__all__ = ["main"]

#: The XLA flag that makes GPU scatter-adds and reductions run in a fixed order, so that two
#: identical runs give bit-identical results (the CPU's already do). The command line sets it
#: unless ``--nondeterministic``; from Python, put it in ``XLA_FLAGS`` before importing JAX.
_DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"

#: Environment variable naming the command line's compilation cache folder (``off``: none).
_CACHE_ENV = "JAXNM_COMPILATION_CACHE"


def _add_xla_flag(flag: str) -> None:
    """Add ``flag`` to ``XLA_FLAGS`` (read when JAX first starts a backend)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if flag not in flags.split():
        os.environ["XLA_FLAGS"] = f"{flags} {flag}".strip()


def _compilation_cache_dir() -> Path | None:
    """Where the command line keeps compiled programs: ``$JAXNM_COMPILATION_CACHE`` if set
    (``off`` or empty: nowhere), else ``$XDG_CACHE_HOME/jaxnm/xla`` (``~/.cache/jaxnm/xla``)."""
    env = os.environ.get(_CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "false", "no") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxnm" / "xla"


def _use_compilation_cache() -> Path | None:
    """Turn on JAX's persistent compilation cache in `_compilation_cache_dir`, so that a second
    run loads its compiled programs from disk; leaves a cache configured elsewhere alone."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    path = _compilation_cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.05)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path




#: What ``jaxnm --help`` says the command is.
_DESCRIPTION = ("Render a scene, fit a tangent-space normal map to target shading, or bake a "
               "high-poly mesh's detail into a low-poly mesh's normal map. 'jaxnm COMMAND "
               "--help' lists each command's options.")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``jaxnm render: error: ...`` and where to look,
    instead of the usage block."""

    def error(self, message: str):
        if message.startswith("argument --light: expected one argument"):
            message += " (a direction that starts with a minus goes as --light=-1,0,1)"
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _parser() -> argparse.ArgumentParser:
    from . import _bake, _fit, _render

    parser = _Parser(prog="jaxnm", description=_DESCRIPTION)
    parser.add_argument("--version", action="version", version=_version(),
                        help="print jaxnm's version and JAX's, and exit")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _render.add_parser(sub)
    _fit.add_parser(sub)
    _bake.add_parser(sub)
    for p in sub.choices.values():
        p.add_argument("--no-compile-cache", action="store_true", dest="no_compile_cache",
                       help="do not use the persistent compilation cache (default: "
                       "$JAXNM_COMPILATION_CACHE or ~/.cache/jaxnm/xla)")
        p.add_argument("--nondeterministic", action="store_true",
                       help="allow run-to-run differences on a GPU (faster scatter-adds); "
                       "by default results are reproducible on every backend")
    return parser


def _version() -> str:
    """What ``jaxnm --version`` prints: jaxnm's version and the JAX it runs on."""
    import jax

    from jaxnm import __version__

    return f"jaxnm {__version__} (JAX {jax.__version__})"


def main(argv=None, *, sigint=None) -> int:
    """Run ``jaxnm render``, ``jaxnm fit`` or ``jaxnm bake`` with ``argv`` (default:
    ``sys.argv[1:]``); returns the exit code (2 for bad input, with a one-line error on
    stderr; 130 after Ctrl-C). ``sigint``: the ``jaxnm`` launcher's
    `jaxnm_launcher.SigintThread`, which receives SIGINT on a thread of its own. The command
    handles SIGINT while it runs (`CtrlC`; not where SIGINT is ignored, nor outside the main
    thread), shows warnings as one line each, and puts the previous handler and warning
    display back."""
    ctrl_c = CtrlC().install(sigint)
    try:
        args = _parser().parse_args(argv)
        ctrl_c.command = command = f"jaxnm {args.command}"
        if args.command == "fit" and (args.distributed or args.coordinator is not None
                                      or args.num_processes is not None
                                      or args.process_id is not None):
            ctrl_c.as_keyboard_interrupt()  # the scheduler signals every process
            return _distributed_fit(args)
        with one_line_warnings(command):
            return _run(args, ctrl_c)
    except (Interrupted, KeyboardInterrupt):  # (the latter where the handler is not installed)
        print(f"{ctrl_c.command}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, ImportError) as e:  # OSError: a file that cannot be written
        print(f"{ctrl_c.command}: error: {e}", file=sys.stderr)
        return 2
    finally:
        ctrl_c.uninstall()


def _run(args, ctrl_c: CtrlC) -> int:
    """The command of ``args``, after the process settings it opts in to."""
    from . import _bake, _fit, _render

    if not args.nondeterministic:
        _add_xla_flag(_DETERMINISTIC_FLAG)  # before JAX starts a backend
    if not args.no_compile_cache:
        _use_compilation_cache()
    ctrl_c.check()
    run = {"render": _render.run, "fit": _fit.run, "bake": _bake.run}[args.command]
    return run(args, ctrl_c)


def _distributed_fit(args) -> int:
    from . import _distributed

    if not args.nondeterministic:
        _add_xla_flag(_DETERMINISTIC_FLAG)
    if not args.no_compile_cache:
        _use_compilation_cache()
    with one_line_warnings("jaxnm fit"):
        return _distributed.run(args)

