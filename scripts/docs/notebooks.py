"""The tutorials as the site shows them: each notebook of ``notebooks/`` executed once, with
its outputs, in ``docs/tutorials/`` (ignored by git).

``tests/test_notebooks.py`` executes every notebook and leaves its executed copy there
(`write_executed`); ``mkdocs build`` (`scripts.docs.hooks`) then uses those copies and
executes only the notebooks whose copy is missing or stale (`is_current`: the copy records
the SHA-256 of the notebook it was executed from). So CI, which runs the tests before the
build, executes each notebook once.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
EXECUTED = ROOT / "docs" / "tutorials"
#: Seconds per cell; a whole notebook takes about a minute on 2 cores.
CELL_TIMEOUT = 300
_KEY = "jaxnm_docs"


def notebooks() -> list[Path]:
    """The committed notebooks, sorted by name."""
    return sorted(NOTEBOOKS.glob("*.ipynb"))


def source_hash(path: Path) -> str:
    """SHA-256 of a notebook file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def executed_path(source: Path) -> Path:
    """Where the executed copy of ``source`` lives."""
    return EXECUTED / Path(source).name


def is_current(source: Path) -> bool:
    """Whether ``source`` has an executed copy made from its present contents."""
    copy = executed_path(source)
    if not copy.exists():
        return False
    try:
        meta = json.loads(copy.read_text(encoding="utf-8"))["metadata"].get(_KEY, {})
    except (ValueError, KeyError):
        return False
    return meta.get("source_sha256") == source_hash(source)


def kernel_manager(folder: Path):
    """An AsyncKernelManager whose only kernel spec starts ipykernel on this interpreter
    (``sys.executable``), so that neither a user's ``python3`` kernel spec nor the
    ``python`` on PATH can swap in another environment; the spec is written into
    ``folder``."""
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import AsyncKernelManager

    spec = Path(folder) / "kernels" / "jaxnm-docs"
    spec.mkdir(parents=True, exist_ok=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "jaxnm", "language": "python"}))
    ksm = KernelSpecManager(kernel_dirs=[str(spec.parent)], ensure_native_kernel=False)
    return AsyncKernelManager(kernel_name="jaxnm-docs", kernel_spec_manager=ksm)


def execute(source: Path, folder: Path):
    """Run ``source`` from top to bottom in a fresh kernel whose working directory is
    ``folder/work``; returns the executed notebook (an ``nbformat`` node). A failing cell
    raises nbclient's ``CellExecutionError`` with its traceback."""
    import nbclient
    import nbformat

    nb = nbformat.read(source, as_version=4)
    work = Path(folder) / "work"
    work.mkdir(parents=True, exist_ok=True)
    client = nbclient.NotebookClient(
        nb, km=kernel_manager(folder), timeout=CELL_TIMEOUT, allow_errors=False,
        resources={"metadata": {"path": str(work)}})
    # cleanup_kc: a client given its own kernel manager leaves the kernel running and its
    # sockets open by default; shut both down here, also when a cell fails
    client.execute(cleanup_kc=True)
    return nb


def write_executed(nb, source: Path) -> Path:
    """Write the executed notebook ``nb`` of ``source`` to `executed_path` (atomically),
    recording the source's hash; returns the path."""
    import nbformat

    nb.metadata[_KEY] = {"source_sha256": source_hash(source)}
    EXECUTED.mkdir(parents=True, exist_ok=True)
    dest = executed_path(source)
    fd, tmp = tempfile.mkstemp(dir=EXECUTED, suffix=".tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        nbformat.write(nb, f)
    os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide the file from a web server
    os.replace(tmp, dest)
    return dest


def ensure_executed(log=print) -> list[Path]:
    """Execute every notebook without a current executed copy; returns those executed."""
    done = []
    for source in notebooks():
        if is_current(source):
            continue
        log(f"executing {source.name} for the site (no current executed copy)")
        with tempfile.TemporaryDirectory() as folder:
            write_executed(execute(source, Path(folder)), source)
        done.append(source)
    return done
