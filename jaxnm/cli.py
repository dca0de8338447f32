"""Command line: ``jaxnm render`` and ``jaxnm fit``.

    jaxnm render [SCENE.json] [-o out.png] [--aovs out.npz] [--derivatives MODE]
                 [--frame FRAME] [--normal-map PATH] [--width W --height H]
    jaxnm fit [FIT.json] [-o OUTDIR] [--checkpoint-every SECONDS] [--resume] ...
    jaxnm fit FIT.json --distributed [--coordinator HOST:PORT --num-processes N
                                      --process-id I] [--timeout SECONDS] ...

Options override the scene (or fit) file; with no file the built-in scene or
problem (a rivet-mapped torus, generated in code) is used. Errors in the
input are one line naming the file and the field, with exit code 2.

``jaxnm fit`` keeps a checkpoint in ``OUTDIR/checkpoint.npz`` (by default every 30 s of
fitting, and when the fit ends); ``--resume`` carries on from it. Ctrl-C during the fit
stops it after the current step, and during the writing of the outputs leaves out the
optional ones (held-out scores, renders, the loss plot): either way ``normal_map.png``,
``normal_map.npz`` and ``report.json`` are written, the report saying what was
interrupted, and the exit code is 130. A second Ctrl-C stops at once; every file is written
atomically, so none is ever left half-written.

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
import dataclasses
import inspect
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

__all__ = ["main"]

#: The XLA flag that makes GPU scatter-adds and reductions run in a fixed order, so that two
#: identical runs give bit-identical results (the CPU's already do). The command line sets it
#: unless ``--nondeterministic``; from Python, put it in ``XLA_FLAGS`` before importing JAX.
_DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"

#: Environment variable naming the command line's compilation cache folder (``off``: none).
_CACHE_ENV = "JAXNM_COMPILATION_CACHE"

#: The checkpoint ``jaxnm fit`` keeps in its output folder (`jaxnm.fit.checkpoint`).
_CHECKPOINT_NAME = "checkpoint.npz"


def _release_freed_memory() -> None:
    """Hand the memory freed so far back to the system (glibc's ``malloc_trim``; nothing
    elsewhere), between ``jaxnm fit``'s phases: XLA's compiler frees hundreds of megabytes
    that glibc would keep in its heaps, and the next phase's buffers would come on top of
    them; handed back, the peak is the larger phase's, not their sum. The one allocator
    call jaxnm makes, and only here, in the command line's own process."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim if hasattr(libc, "gnu_get_libc_version") else None
    except (OSError, AttributeError):
        trim = None
    if trim is not None:
        trim(0)


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


def _add_render(sub) -> None:
    from .frames import FRAMES
    from .interpolate import DERIVATIVE_MODES, PRECISIONS
    from .render import OUTPUTS

    p = sub.add_parser("render", help="render a scene to a PNG (and optional AOVs)",
                       description="Render SCENE.json (or the built-in default scene) to a PNG.")
    p.add_argument("scene", nargs="?", help="scene JSON file (default: the built-in scene)")
    p.add_argument("-o", "--output", default="render.png", help="output PNG (default: %(default)s)")
    p.add_argument("--aovs", metavar="OUT.npz",
                   help="also write these arrays to an .npz: " + ", ".join(OUTPUTS[:-1])
                   + " and color (linear); see --aov-list")
    p.add_argument("--aov-list", default=",".join(OUTPUTS), metavar="NAMES",
                   help="comma-separated AOV names to write with --aovs (default: all)")
    p.add_argument("--derivatives", choices=DERIVATIVE_MODES, help="screen-space derivative mode")
    p.add_argument("--frame", choices=FRAMES, help="tangent frame method")
    p.add_argument("--precision", choices=PRECISIONS,
                   help="shader arithmetic of the frame and perturbation (float16: mediump)")
    p.add_argument("--normal-map", metavar="PATH",
                   help="use this tangent-space normal map (an 8/16-bit PNG, or a BC5 or DXT5nm "
                   "DDS; unsigned, green up; the scene's uv origin, wrap, filter and strength)")
    p.add_argument("--height-map", metavar="PATH", dest="height_map",
                   help="bump the surface with this height map instead (grayscale image)")
    p.add_argument("--height-scale", type=float, default=0.02, dest="height_scale",
                   help="world units per unit of the height map (default: %(default)s)")
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--exposure", type=float, default=1.0, help="linear scale before sRGB")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bit depth")


def _rescaled_camera(scene, width: int, height: int):
    """The scene's camera with the projection's aspect ratio adapted to a new image size."""
    import numpy as np

    from .camera import Camera

    proj = np.array(scene.camera.projection, np.float64)
    proj[0, :] *= (scene.width / scene.height) / (width / height)  # x scale ~ 1 / aspect
    return Camera.from_matrices(np.asarray(scene.camera.view, np.float64), proj)


def _render(args) -> int:
    import numpy as np

    from . import io
    from .config import _load_height_map, load_scene
    from .procedural import default_scene
    from .render import OUTPUTS, render
    from .shading import to_display

    t0 = time.perf_counter()
    names = ["color"]
    if args.aovs:  # check the cheap arguments before loading anything
        asked = [n.strip() for n in args.aov_list.split(",") if n.strip()]
        bad = [n for n in asked if n not in OUTPUTS]
        if bad:
            raise ValueError(f"--aov-list: unknown AOV names {bad}; known: {', '.join(OUTPUTS)}")
        names += [n for n in asked if n != "color"]
    for flag, v in (("--width", args.width), ("--height", args.height)):
        if v is not None and v <= 0:
            raise ValueError(f"{flag} must be positive, got {v}")
    if args.scene:
        scene = load_scene(args.scene)
    else:
        scene = default_scene(width=args.width or 512, height=args.height or 512)
    changes = {}
    if args.width or args.height:
        w, h = args.width or scene.width, args.height or scene.height
        if (w, h) != (scene.width, scene.height):
            changes.update(width=w, height=h, camera=_rescaled_camera(scene, w, h))
    if args.normal_map and Path(args.normal_map).suffix.lower() == ".dds":
        from .storage import load_dds_normal_map

        m = load_dds_normal_map(args.normal_map)  # BC5 or DXT5nm: two channels, z rebuilt
        changes.update(normal_map=m.texels, normal_map_options=dataclasses.replace(
            m.options(scene.normal_map_options), green="up"))
    elif args.normal_map:
        raw, bits = io.load_texture(args.normal_map, channels=3)
        changes.update(normal_map=raw, normal_map_options=dataclasses.replace(
            scene.normal_map_options, encoding="unsigned", channels=3, green="up",
            space="tangent", bits=bits if bits in (8, 16) else 8))
    if args.height_map:
        d, opts = _load_height_map({"path": args.height_map, "scale": args.height_scale},
                                  where="--height-map: ")
        changes.update(normal_map=d, normal_map_options=opts)
    if changes:
        scene = scene.replace(**changes)
    frame = args.frame or scene.frame
    if frame == "vertex" and scene.mesh.tangents is None and scene.mesh.uv is not None:
        scene = scene.replace(mesh=scene.mesh.with_tangents())  # MikkTSpace
    result = render(scene, outputs=tuple(names), derivatives=args.derivatives, frame=args.frame,
                    precision=args.precision)
    io.save_png(args.output, np.asarray(to_display(result["color"], exposure=args.exposure)),
                bits=args.bits)
    msg = f"wrote {args.output} ({scene.width}x{scene.height}, frame {frame}"
    if frame == "vertex":
        msg += f", tangents: {scene.mesh.tangent_source}"
    msg += ")"
    if args.aovs:
        io.save_aovs(args.aovs, result)
        msg += f" and {args.aovs} ({', '.join(result)})"
    print(f"{msg} in {time.perf_counter() - t0:.2f} s")
    return 0


def _add_fit(sub) -> None:
    from .fit import SOLVERS, TEXEL_SUMS

    p = sub.add_parser("fit", help="fit a normal map to target shading",
                       description="Fit a tangent-space normal map to target images.")
    p.add_argument("config", nargs="?", help="fit JSON file (default: the built-in problem)")
    p.add_argument("-o", "--output", default="fit_out", help="output folder (default: %(default)s)")
    p.add_argument("--solver", choices=SOLVERS, help="optimiser (default: lm-texel)")
    p.add_argument("--max-steps", type=int, dest="max_steps", help="outer iterations")
    p.add_argument("--lsmr-steps", type=int, dest="lsmr_steps",
                   help="inner iterations per LM/GN step (conjugate gradients for "
                        "lm-texel, LSMR for lm and gn)")
    p.add_argument("--smoothness", type=float, help="slope smoothness weight (default 0)")
    p.add_argument("--coarse-to-fine", type=int, dest="coarse_to_fine",
                   help="number of coarser levels solved first")
    p.add_argument("--ftol", type=float,
                   help="converged when the loss changes by less than this fraction over "
                   "--patience steps at none of which the solver's model, undamped, promised "
                   "more (default 1e-3; 0: only the solver's own test)")
    p.add_argument("--patience", type=int, help="steps the --ftol test spans (default 3)")
    p.add_argument("--texel-sums", dest="texel_sums", choices=TEXEL_SUMS,
                   help="lm-texel's sums into the texels: scatter-adds, or fixed-order tables "
                   "(deterministic without sorting; default auto: tables on a GPU)")
    p.add_argument("--seed", type=int)
    p.add_argument("--time-limit", type=float, dest="time_limit", metavar="SECONDS")
    p.add_argument("--quick", action="store_true",
                   help="built-in problem at 128x128 renders and a 64x64 map (a smoke test)")
    p.add_argument("--no-progress", action="store_true", dest="no_progress")
    p.add_argument("--checkpoint-every", type=float, default=30.0, dest="checkpoint_every",
                   metavar="SECONDS",
                   help=f"save the fit to OUTDIR/{_CHECKPOINT_NAME} every SECONDS of fitting and "
                   "when it ends (default: %(default)s; 0: no checkpoints)")
    p.add_argument("--distributed", action="store_true",
                   help="one process of a fit across processes (jax.distributed): joins the "
                   "others (SLURM, Open MPI and cloud clusters are detected, or give "
                   "--coordinator, --num-processes, --process-id); process 0 writes OUTDIR")
    p.add_argument("--coordinator", metavar="HOST:PORT",
                   help="with --distributed: the address of process 0's coordinator")
    p.add_argument("--num-processes", type=int, dest="num_processes", metavar="N")
    p.add_argument("--process-id", type=int, dest="process_id", metavar="I")
    p.add_argument("--timeout", type=float, default=300.0, metavar="SECONDS",
                   help="with --distributed: how long to wait for the other processes to "
                   "join, and after how long without a heartbeat a process counts as lost "
                   "(default: %(default)s)")
    p.add_argument("--store", choices=("bc5",),
                   help="then fit the map through BC5 blocks to the same targets and write it "
                   "as normal_map.dds (needs the storage extra; the map's size a multiple of "
                   "4); report.json compares its loss as stored with the fitted map "
                   "compressed by quicktex")
    p.add_argument("--resume", action="store_true",
                   help=f"carry on from OUTDIR/{_CHECKPOINT_NAME}: the same fit file and options "
                   "give the map an uninterrupted fit gives (--max-steps, --ftol, --patience "
                   "and --time-limit may change)")


class _CtrlC:
    """``jaxnm fit``'s SIGINT handler. Before the fit a Ctrl-C stops the command at once
    (``KeyboardInterrupt``); the first one during the fit asks it to stop after the
    current step, and while the outputs are written, to leave out the optional ones; the
    next one stops at once."""

    def __init__(self):
        self.phase = "prepare"  # then "fit", then "writing"
        self.requested = None  # the phase of the first Ctrl-C, once there was one

    def __call__(self, signum, frame) -> None:
        if self.phase == "prepare" or self.requested is not None:
            raise KeyboardInterrupt
        self.requested = self.phase
        what = ("stopping after this step" if self.phase == "fit"
                else "writing the map and the report only")
        # (os.write: a print here could re-enter one the handler interrupted)
        os.write(2, f"\njaxnm fit: Ctrl-C: {what} (Ctrl-C again to stop at once)\n".encode())


def _join(args) -> None:
    """Join a fit across processes (``--distributed``): gloo for the CPU's collectives (the
    command line's choice, made before JAX starts a backend), then
    ``jax.distributed.initialize`` with what the command line gives (else auto-detected)."""
    explicit = (args.coordinator, args.num_processes, args.process_id)
    if not args.distributed:
        raise ValueError("--coordinator, --num-processes and --process-id need --distributed")
    if any(v is not None for v in explicit) and not all(v is not None for v in explicit):
        raise ValueError("--coordinator, --num-processes and --process-id go together")
    if args.num_processes is not None and not 0 <= args.process_id < args.num_processes:
        raise ValueError(f"--process-id must be 0 to {args.num_processes - 1}, got "
                         f"{args.process_id}")
    if not (math.isfinite(args.timeout) and args.timeout >= 1):
        raise ValueError(f"--timeout must be a number of seconds >= 1, got {args.timeout}")
    if args.store:
        raise ValueError("--store is not available with --distributed (it fits the map through "
                         "its storage on one process: run it without --distributed)")
    import jax

    if "jax_cpu_collectives_implementation" in jax.config.values:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    t = max(1, int(args.timeout))
    timeouts = {"initialization_timeout": t, "heartbeat_timeout_seconds": t}
    if "shutdown_timeout_seconds" in inspect.signature(jax.distributed.initialize).parameters:
        timeouts["shutdown_timeout_seconds"] = t  # (not in the oldest JAX jaxnm supports)
    try:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id,
                                   **timeouts)
    except Exception as e:  # noqa: BLE001 (one line, whatever the runtime raised)
        where = args.coordinator or "the detected cluster"
        raise _Lost(f"could not join the other processes through {where} within {t} s: "
                    f"{_first_line(e)}") from None


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


def _fit(args, ctrl_c: _CtrlC) -> int:
    from .config import load_fit
    from .fit import compile_fit, fit_normal_map, prepare, prepare_held_out
    from .procedural import default_fit_job

    if args.distributed:
        import jax

        from .fit import check_same_across_processes, prepare_processes, process_targets
        me, count = jax.process_index(), jax.process_count()
    else:
        me, count = 0, 1

    say = (lambda msg: None) if args.no_progress else (  # noqa: E731
        lambda msg: print(msg, file=sys.stderr, flush=True))
    overrides = {k: getattr(args, k) for k in ("solver", "max_steps", "smoothness", "seed",
                                                "lsmr_steps", "coarse_to_fine", "ftol",
                                                "patience", "texel_sums")
                 if getattr(args, k) is not None}
    if args.time_limit is not None and not args.time_limit > 0:
        raise ValueError(f"--time-limit must be a positive number of seconds, got "
                         f"{args.time_limit}")
    if not (math.isfinite(args.checkpoint_every) and args.checkpoint_every >= 0):
        raise ValueError(f"--checkpoint-every must be a number of seconds >= 0, got "
                         f"{args.checkpoint_every}")
    out = Path(args.output)
    checkpoint = out / _CHECKPOINT_NAME
    if args.distributed:  # the same fit everywhere, before anything is read
        if args.config and not Path(args.config).is_file():
            raise FileNotFoundError(f"{args.config}: no such fit file")
        identity = _fit_identity(args, overrides)
        if args.resume:
            identity["a checkpoint to resume from"] = checkpoint.is_file()
        check_same_across_processes(identity, what="jaxnm fit --distributed")
        say = say if me == 0 else (lambda msg: None)  # noqa: E731
    if args.resume and not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: no checkpoint to resume from (--resume)")
    if args.config and args.distributed:
        say(f"reading {args.config} (each process its own views) ...")

        def images(key, targets):  # this process's views; the held-out ones on process 0
            if key == "held_out":
                return range(len(targets)) if me == 0 else ()
            return process_targets(targets, count)[me]

        job = load_fit(args.config, images=images)
    elif args.config:
        say(f"reading {args.config} ...")
        job = load_fit(args.config)
    else:
        say("rendering the built-in problem's targets ...")
        job = default_fit_job(quick=args.quick)
    if overrides:
        try:
            job = dataclasses.replace(job, options=dataclasses.replace(job.options, **overrides))
        except ValueError as e:
            raise ValueError(f"command line: {str(e).removeprefix('FitOptions: ')}") from None
    if args.time_limit is not None:
        job = dataclasses.replace(job, time_limit=args.time_limit)
    if args.store:
        from .fit.stored import check_storage

        check_storage(job.problem, args.store)  # before anything is fitted
    say(f"preparing {len(job.problem.targets)} targets (rasterizing each view once) ...")
    t0 = time.perf_counter()
    prep = prepare_processes(job.problem) if args.distributed else prepare(job.problem)
    t_prep = time.perf_counter() - t0
    # with the same compiled G-buffer program; across processes, process 0 scores them
    held_out = prepare_held_out(job) if me == 0 else ()
    if not args.resume and me == 0:
        checkpoint.unlink(missing_ok=True)  # a new fit: an old checkpoint is not its own
    _release_freed_memory()
    if not args.resume:
        say("compiling the fit's step ...")
        compile_fit(job.problem, job.options, prepared=prep)
        _release_freed_memory()  # the compiler's, before the step's buffers are allocated
    say(f"resuming from {checkpoint} ..." if args.resume else "fitting ...")
    ctrl_c.phase = "fit"
    result = fit_normal_map(job.problem, job.options, ground_truth=job.ground_truth,
                            progress=not args.no_progress and me == 0, prepared=prep,
                            time_limit=job.time_limit,
                            should_stop=lambda rec: ctrl_c.requested is not None,
                            checkpoint=checkpoint if args.checkpoint_every > 0 else None,
                            checkpoint_every=args.checkpoint_every,
                            resume=checkpoint if args.resume else False)
    ctrl_c.phase = "writing"
    seen = None
    if args.distributed:
        from .fit import local_prepared, seen_texels

        if job.ground_truth is not None:  # (a collective: every process's views)
            seen = seen_texels(prep, job.problem.map_size)
        if me != 0:
            return 0  # process 0 writes the outputs
        prep = local_prepared(prep)[0]  # its renders: its own views
    say("writing outputs ...")
    rep, written = _write_fit_outputs(
        out, job, prep, result, t_prep, held_out, ctrl_c,
        checkpoint={"file": _CHECKPOINT_NAME if args.checkpoint_every > 0 else None,
                    "resumed": args.resume}, seen=seen, processes=count)
    if args.store and not rep["interrupted"]:
        written.append(_store(out, job, prep, result, args.store, say, not args.no_progress))
    line = f"fit {rep['stopped']} after {rep['steps']} steps in {rep['fit_seconds']:.1f} s"
    if rep["interrupted"]:
        when = "during the fit" if rep["interrupted_phase"] == "fit" else "while writing"
        line += f" (interrupted {when})"
    if "error" in rep:
        e = rep["error"]
        line += (f"; angular error over {e['seen_texels']} seen texels: mean {e['mean_deg']:.3f}"
                 f", median {e['median_deg']:.3f}, p95 {e['p95_deg']:.3f} deg")
    for h in rep.get("held_out", []):
        line += f"; held-out PSNR {h['psnr_db_vs_target']:.1f} dB"
    print(line)
    print(f"outputs in {out}/ ({', '.join(written)})")
    return 130 if rep["interrupted"] else 0


def _store(out: Path, job, prep, result, storage: str, say, progress: bool) -> str:
    """``jaxnm fit --store``: the fitted map fitted again through ``storage``, written as
    ``normal_map.dds``, its losses added to ``report.json``; returns the file's name."""
    from . import io
    from .fit.stored import fit_stored_map

    say(f"fitting the map through {storage} ...")
    sf = fit_stored_map(job.problem, job.options, storage=storage, start=result,
                        green=job.output.green, ground_truth=job.ground_truth, prepared=prep,
                        progress=progress)
    sf.save(out / "normal_map.dds")
    report = io.load_json(out / "report.json")
    report["stored"] = {"file": "normal_map.dds", "storage": storage, "loss": sf.loss,
                        "loss_compressed_afterwards": sf.start_loss,
                        "loss_float": sf.float_loss, "mean_angular_error_deg": sf.errors,
                        "seconds": sf.seconds}
    io.save_json(out / "report.json", report)
    print(f"stored as {storage}: loss {sf.loss:.4g} (the fitted map compressed by quicktex: "
          f"{sf.start_loss:.4g}; unstored: {sf.float_loss:.4g})")
    return "normal_map.dds"


def _write_fit_outputs(out: Path, job, prep, result, prepare_seconds: float, held_out,
                       ctrl_c: _CtrlC, checkpoint: dict, seen=None,
                       processes: int = 1) -> tuple[dict, list]:
    """Write the outputs of ``result`` to ``out``: the map and a report listing what is
    ``"pending"`` first, then what is optional (held-out scores, renders, the loss plot) as
    long as Ctrl-C was not pressed (`_CtrlC`; what was left out is ``"skipped"``), then the
    final report. ``checkpoint`` goes into the report. Returns the report and the names
    written."""
    from . import io
    from .fit import fit_outputs, fit_renders, score_held_out

    outputs = fit_outputs(job, prep, result, prepare_seconds=prepare_seconds, optional=False,
                          seen=seen)
    report = outputs.report
    report["processes"] = processes
    report["checkpoint"] = checkpoint

    def mark() -> None:
        phase = ctrl_c.requested or ("fit" if result.stopped == "interrupted" else None)
        report["interrupted"] = phase is not None
        if phase is not None:
            report["interrupted_phase"] = phase

    parts = (["held_out"] if job.held_out else []) + ["renders", "loss_plot"]
    report.pop("skipped", None)
    report["pending"] = parts  # (what a report left by a second Ctrl-C is without)
    mark()
    written = io.write_fit_outputs(out, outputs, plot=False)
    skipped = []
    for part in parts:
        if ctrl_c.requested is not None:
            skipped.append(part)
        elif part == "held_out":
            report["held_out"] = score_held_out(job, result.normals, held_out)
        elif part == "renders":
            written += io.write_fit_renders(out, fit_renders(prep, result.normals))
        elif io.save_loss_plot(out / "loss.png", result.history):
            written.append("loss.png")
    del report["pending"]
    if skipped:
        report["skipped"] = skipped
    mark()
    io.save_json(out / "report.json", report)
    return report, written


def main(argv=None) -> int:
    """Run ``jaxnm render`` or ``jaxnm fit`` with ``argv`` (default: ``sys.argv[1:]``);
    returns the exit code (2 for bad input, with a one-line error on stderr; 130 after
    Ctrl-C). ``jaxnm fit`` handles SIGINT while it runs (`_CtrlC`; not where SIGINT is
    ignored, nor outside the main thread) and puts the previous handler back."""
    parser = argparse.ArgumentParser(prog="jaxnm", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    _add_render(sub)
    _add_fit(sub)
    for p in sub.choices.values():
        p.add_argument("--no-compile-cache", action="store_true", dest="no_compile_cache",
                       help="do not use the persistent compilation cache (default: "
                       "$JAXNM_COMPILATION_CACHE or ~/.cache/jaxnm/xla)")
        p.add_argument("--nondeterministic", action="store_true",
                       help="allow run-to-run differences on a GPU (faster scatter-adds); "
                       "by default results are reproducible on every backend")
    args = parser.parse_args(argv)
    if not args.nondeterministic:
        _add_xla_flag(_DETERMINISTIC_FLAG)  # before JAX starts a backend
    if not args.no_compile_cache:
        _use_compilation_cache()
    if args.command == "fit" and (args.distributed or args.coordinator is not None
                                  or args.num_processes is not None
                                  or args.process_id is not None):
        return _distributed_fit(args)
    ctrl_c, previous = _CtrlC(), None
    if (args.command == "fit" and threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
        previous = signal.signal(signal.SIGINT, ctrl_c)  # restored below
    try:
        return _render(args) if args.command == "render" else _fit(args, ctrl_c)
    except (ValueError, FileNotFoundError, ImportError) as e:
        print(f"jaxnm {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"jaxnm {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def _distributed_fit(args) -> int:
    """``jaxnm fit --distributed``: `_fit` in a fit across processes. Any error ends the
    process at once with one line naming it (``jaxnm fit: error: process I of N: ...``;
    exit code 2 for bad input, 1 for a lost process), without the runtime's shutdown
    (whose barrier would wait for, and then report, the processes that are gone)."""
    where = "jaxnm fit: error"
    try:
        _join(args)
        import jax

        where = f"jaxnm fit: error: process {jax.process_index()} of {jax.process_count()}"
        # no Ctrl-C handler: a stop must reach every process (the scheduler signals them all)
        code = _fit(args, _CtrlC())
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


if __name__ == "__main__":
    sys.exit(main())
