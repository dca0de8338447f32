"""``jaxnm fit``: read (or build) the job, prepare its views, compile the step, fit, write the
outputs; with ``--store``, fit the map again through its storage."""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from pathlib import Path

from ._flags import as_flags, output_path
from ._interrupt import CtrlC

__all__ = ["add_parser", "run", "check_arguments", "read_job", "write_outputs",
           "CHECKPOINT_NAME", "DEFAULT_TIMEOUT", "OVERRIDES", "release_freed_memory"]

#: Why ``jaxnm fit`` wrote no ``loss.png`` (``report.json``'s ``loss_plot``).
_NO_PLOT = 'not drawn: matplotlib is not installed (the cli extra: pip install -e ".[cli]")'

#: The checkpoint ``jaxnm fit`` keeps in its output folder (`jaxnm.fit.checkpoint`).
CHECKPOINT_NAME = "checkpoint.npz"

#: The solver options the command line can override (``--max-steps`` and so on).
OVERRIDES = ("solver", "max_steps", "smoothness", "seed", "lsmr_steps", "coarse_to_fine",
             "ftol", "patience", "texel_sums")

#: ``--timeout`` when not given: seconds the processes of a fit across processes wait to
#: join, and without a heartbeat before one counts as lost.
DEFAULT_TIMEOUT = 300.0

#: The checkpoint interval when ``--checkpoint-every`` is not given (the checkpoint is then
#: removed when the fit ends normally).
_DEFAULT_CHECKPOINT_SECONDS = 30.0


def add_parser(sub) -> None:
    """Add ``jaxnm fit`` and its options to the subcommands ``sub``."""
    from ..fit import SOLVERS, TEXEL_SUMS

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
    p.add_argument("--seed", type=int,
                   help="seed of the random start where the fit file's solver has an "
                   "init_noise (default 0)")
    p.add_argument("--time-limit", type=float, dest="time_limit", metavar="SECONDS",
                   help="stop after SECONDS of fitting, keeping the best map so far")
    p.add_argument("--quick", action="store_true",
                   help="built-in problem at 128x128 renders and a 64x64 map (a smoke test)")
    p.add_argument("--no-progress", action="store_true", dest="no_progress",
                   help="a line per step on stderr instead of a progress bar")
    p.add_argument("--checkpoint-every", type=float, dest="checkpoint_every",
                   metavar="SECONDS",
                   help=f"save the fit to OUTDIR/{CHECKPOINT_NAME} every SECONDS of fitting and "
                   "when it ends, and keep it (default: every "
                   f"{_DEFAULT_CHECKPOINT_SECONDS:g} s, removed when the fit ends unless "
                   "interrupted; 0: no checkpoints)")
    p.add_argument("--keep-checkpoint", action="store_true", dest="keep_checkpoint",
                   help="keep the checkpoint when the fit ends (to --resume it later with "
                   "more steps or time)")
    p.add_argument("--distributed", action="store_true",
                   help="one process of a fit across processes (jax.distributed): joins the "
                   "others (SLURM, Open MPI and cloud clusters are detected, or give "
                   "--coordinator, --num-processes, --process-id); process 0 writes OUTDIR")
    p.add_argument("--coordinator", metavar="HOST:PORT",
                   help="with --distributed: the address of process 0's coordinator")
    p.add_argument("--num-processes", type=int, dest="num_processes", metavar="N",
                   help="with --distributed: how many processes take part")
    p.add_argument("--process-id", type=int, dest="process_id", metavar="I",
                   help="with --distributed: this process's number, 0 to N-1")
    p.add_argument("--timeout", type=float, metavar="SECONDS",
                   help="with --distributed: how long to wait for the other processes to "
                   "join, and after how long without a heartbeat a process counts as lost "
                   f"(default: {DEFAULT_TIMEOUT:g})")
    p.add_argument("--store", choices=("bc5",),
                   help="then fit the map through BC5 blocks to the same targets and write it "
                   "as normal_map.dds (needs the storage extra; the map's size a multiple of "
                   "4); report.json compares its loss as stored with the fitted map "
                   "compressed by quicktex")
    p.add_argument("--resume", action="store_true",
                   help=f"carry on from OUTDIR/{CHECKPOINT_NAME}: the same fit file and options "
                   "give the map an uninterrupted fit gives (--max-steps, --ftol, --patience "
                   "and --time-limit may change)")


def release_freed_memory() -> None:
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


def _say(enabled: bool = True):
    """A stage line on stderr (``say("preparing ...")``), or nothing."""
    if not enabled:
        return lambda msg: None
    return lambda msg: print(msg, file=sys.stderr, flush=True)


def check_arguments(args) -> dict:
    """The fit file's kind and the numeric options checked; returns the solver options the
    command line overrides."""
    from ..io import IMAGE_EXTENSIONS, MESH_EXTENSIONS

    kind = Path(args.config or "").suffix.lower()
    if kind in MESH_EXTENSIONS:
        raise ValueError(f"{args.config}: a mesh file, not a fit file (JSON): 'jaxnm render "
                         f"{args.config} --light X,Y,Z ...' renders targets of it and writes "
                         f"their fit file, and 'jaxnm bake' fits a map to a high-poly mesh")
    if kind in IMAGE_EXTENSIONS:
        raise ValueError(f"{args.config}: an image, not a fit file (JSON), which names its "
                         f"target images, views and lights")
    if args.time_limit is not None and not args.time_limit > 0:
        raise ValueError(f"--time-limit must be a positive number of seconds, got "
                         f"{args.time_limit}")
    every = args.checkpoint_every
    if every is not None and not (math.isfinite(every) and every >= 0):
        raise ValueError(f"--checkpoint-every must be a number of seconds >= 0, got {every}")
    if args.keep_checkpoint and every == 0:
        raise ValueError("--keep-checkpoint keeps the checkpoint that --checkpoint-every 0 "
                         "turns off: give one of them")
    if args.timeout is not None and not args.distributed:
        raise ValueError("--timeout is how long the processes of a fit across processes wait "
                         "for each other: give it with --distributed")
    overrides = {k: getattr(args, k) for k in OVERRIDES if getattr(args, k) is not None}
    from ..fit import FitOptions

    try:  # each value on its own now; with the fit file's, once it is read
        FitOptions(**overrides)
    except ValueError as e:
        raise ValueError(as_flags(str(e).removeprefix("FitOptions: "), OVERRIDES)) from None
    return overrides


def read_job(args, overrides: dict, say, images=None):
    """The `jaxnm.fit.FitJob` of ``args``: the fit file's (``images``: see
    `jaxnm.config.fit_from_dict`) or the built-in problem's, with the command line's
    options."""
    from ..config import load_fit
    from ..fit import level_sizes
    from ..procedural import default_fit_job

    if args.config:
        say(f"reading {args.config} ...")
        job = load_fit(args.config, images=images)
    else:
        say("rendering the built-in problem's targets ...")
        job = default_fit_job(quick=args.quick)
    if overrides:
        try:
            job = dataclasses.replace(job, options=dataclasses.replace(job.options, **overrides))
        except ValueError as e:
            problem = args.config or "the built-in problem"
            raise ValueError(f"{problem} with the command line's options: "
                             f"{as_flags(str(e).removeprefix('FitOptions: '), OVERRIDES)}"
                             ) from None
    if args.time_limit is not None:
        job = dataclasses.replace(job, time_limit=args.time_limit)
    try:  # (before the work: the fit checks its levels once prepared)
        level_sizes(tuple(job.problem.map_size), job.options.coarse_to_fine,
                    args.config or "the built-in problem")
    except ValueError as e:
        raise ValueError(as_flags(str(e), OVERRIDES).replace(" = ", " ", 1)
                         if "coarse_to_fine" in overrides else str(e)) from None
    if args.store:
        from ..fit.stored import check_storage

        check_storage(job.problem, args.store)  # before anything is fitted
    return job


def run(args, ctrl_c: CtrlC, *, process: tuple[int, int] = (0, 1), images=None) -> int:
    """``jaxnm fit`` in this process (``process``: its index and the process count of a fit
    across processes, whose `jaxnm.fit.prepare_processes` it uses). Stage lines go to stderr
    (process 0's); Ctrl-C is noticed between the stages, between the fit's steps and between
    the outputs (`CtrlC`). Returns the exit code."""
    from ..fit import fit_normal_map

    me, count = process
    say = _say(me == 0)
    overrides = check_arguments(args)
    out = output_path("-o", args.output, folder=True)
    ctrl_c.output = out
    checkpoint = out / CHECKPOINT_NAME
    if args.resume and not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: no checkpoint to resume from (--resume)")
    job = read_job(args, overrides, say, images)
    ctrl_c.check()
    prep, t_prep, held_out = _prepare(args, job, ctrl_c, say, process)
    say(f"resuming from {checkpoint} ..." if args.resume else "fitting ...")
    ctrl_c.phase = "fit"
    every = (_DEFAULT_CHECKPOINT_SECONDS if args.checkpoint_every is None
             else args.checkpoint_every)
    result = fit_normal_map(job.problem, job.options, ground_truth=job.ground_truth,
                            progress=(me == 0) and ("lines" if args.no_progress else True),
                            prepared=prep, time_limit=job.time_limit,
                            should_stop=lambda rec: ctrl_c.requested is not None,
                            checkpoint=checkpoint if every > 0 else None,
                            checkpoint_every=every,
                            resume=checkpoint if args.resume else False)
    ctrl_c.phase = "writing"
    seen = None
    if count > 1:
        from ..fit import local_prepared, seen_texels

        if job.ground_truth is not None:  # (a collective: every process's views)
            seen = seen_texels(prep, job.problem.map_size)
        if me != 0:
            return 0  # process 0 writes the outputs
        prep = local_prepared(prep)[0]  # its renders: its own views
    say("writing outputs ...")
    rep, written = write_outputs(
        out, job, prep, result, t_prep, held_out, ctrl_c,
        checkpoint={"file": CHECKPOINT_NAME if every > 0 else None, "resumed": args.resume},
        seen=seen, processes=count)
    if args.store and not rep["interrupted"]:
        written.append(_store(out, job, prep, result, args.store, ctrl_c, say,
                              "lines" if args.no_progress else True))
    if every > 0:
        written += _settle_checkpoint(args, out, rep["interrupted"])
    print(_summary(rep))
    print(f"outputs in {out}/ ({', '.join(written)})")
    if "loss_plot" in rep:
        say(f"no loss.png: {_NO_PLOT}")
    return 130 if rep["interrupted"] else 0


def _prepare(args, job, ctrl_c: CtrlC, say, process: tuple[int, int]):
    """Rasterize the views once (`jaxnm.fit.prepare`, or `prepare_processes` across
    processes) and the held-out ones (on process 0), then compile the fit's step (unless it
    resumes: the checkpoint's fit compiled it); returns the prepared views, their seconds
    and the held-out views."""
    from ..fit import compile_fit, prepare, prepare_held_out, prepare_processes

    me, count = process
    say(f"preparing {len(job.problem.targets)} targets (rasterizing each view once) ...")
    t0 = time.perf_counter()
    prep = prepare_processes(job.problem) if count > 1 else prepare(job.problem)
    t_prep = time.perf_counter() - t0
    # with the same compiled G-buffer program; across processes, process 0 scores them
    held_out = prepare_held_out(job) if me == 0 else ()
    ctrl_c.check()
    if not args.resume and me == 0:  # a new fit: an old checkpoint is not its own
        (Path(args.output) / CHECKPOINT_NAME).unlink(missing_ok=True)
    release_freed_memory()
    if not args.resume:
        say("compiling the fit's step ...")
        compile_fit(job.problem, job.options, prepared=prep)
        release_freed_memory()  # the compiler's, before the step's buffers are allocated
        ctrl_c.check()
    return prep, t_prep, held_out


def _settle_checkpoint(args, out: Path, interrupted: bool) -> list[str]:
    """Remove the checkpoint of a fit that ended, unless asked to keep it (``report.json``
    then says so); returns its name where it stays."""
    checkpoint = out / CHECKPOINT_NAME
    if interrupted or args.keep_checkpoint or args.checkpoint_every is not None:
        return [CHECKPOINT_NAME] if checkpoint.is_file() else []
    checkpoint.unlink(missing_ok=True)  # the fit is over: nothing to resume
    _mark_checkpoint_removed(out)
    return []


def _mark_checkpoint_removed(out: Path) -> None:
    from .. import io

    report = io.load_json(out / "report.json")
    report["checkpoint"]["file"] = None
    report["checkpoint"]["removed"] = "the fit ended (--keep-checkpoint keeps it)"
    io.save_json(out / "report.json", report)


def _summary(rep: dict) -> str:
    """The one line that says how the fit went."""
    n = rep["steps"]
    line = (f"fit {rep['stopped_because']} after {n} step{'' if n == 1 else 's'} in "
            f"{rep['fit_seconds']:.1f} s")
    if rep["interrupted"] and rep.get("interrupted_phase") == "writing":
        line += " (Ctrl-C while writing: " + ", ".join(rep.get("skipped", [])) + " left out)"
    if "error" in rep:
        e = rep["error"]
        line += (f"; angular error over {e['seen_texels']} seen texels: mean {e['mean_deg']:.3f}"
                 f", median {e['median_deg']:.3f}, p95 {e['p95_deg']:.3f} deg")
    for h in rep.get("held_out", []):
        line += f"; held-out PSNR {h['psnr_db_vs_target']:.1f} dB"
    return line


def _store(out: Path, job, prep, result, storage: str, ctrl_c: CtrlC, say,
           progress) -> str:
    """``jaxnm fit --store``: the fitted map fitted again through ``storage``, written as
    ``normal_map.dds``, its losses added to ``report.json``; returns the file's name. A
    Ctrl-C ends it after the current round, keeping the best blocks so far."""
    from .. import io
    from ..fit.stored import fit_stored_map

    say(f"fitting the map through {storage} ...")
    sf = fit_stored_map(job.problem, job.options, storage=storage, start=result,
                        green=job.output.green, ground_truth=job.ground_truth, prepared=prep,
                        progress=bool(progress),
                        should_stop=lambda: ctrl_c.requested is not None)
    sf.save(out / "normal_map.dds")
    report = io.load_json(out / "report.json")
    report["stored"] = {"file": "normal_map.dds", "storage": storage, "loss": sf.loss,
                        "loss_compressed_afterwards": sf.start_loss,
                        "loss_float": sf.float_loss, "mean_angular_error_deg": sf.errors,
                        "seconds": sf.seconds, "interrupted": ctrl_c.requested is not None}
    io.save_json(out / "report.json", report)
    print(f"stored as {storage}: loss {sf.loss:.4g} (the fitted map compressed by quicktex: "
          f"{sf.start_loss:.4g}; unstored: {sf.float_loss:.4g})")
    return "normal_map.dds"


def write_outputs(out: Path, job, prep, result, prepare_seconds: float, held_out,
                  ctrl_c: CtrlC, checkpoint: dict, seen=None,
                  processes: int = 1) -> tuple[dict, list]:
    """Write the outputs of ``result`` to ``out``: the map and a report listing what is
    ``"pending"`` first, then what is optional (held-out scores, renders, the loss plot) as
    long as Ctrl-C was not pressed (what was left out is ``"skipped"``), then the final
    report. ``checkpoint`` goes into the report. Returns the report and the names
    written."""
    from .. import io
    from ..fit import fit_outputs, fit_renders, score_held_out

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
        else:
            report["loss_plot"] = _NO_PLOT
    del report["pending"]
    if skipped:
        report["skipped"] = skipped
    mark()
    io.save_json(out / "report.json", report)
    return report, written
