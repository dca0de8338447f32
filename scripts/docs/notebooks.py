"""The tutorials as the site shows them: each notebook of ``notebooks/`` executed once, with
its outputs, in ``docs/tutorials/`` (ignored by git).

``mkdocs build`` (`scripts.docs.hooks`) executes every notebook whose executed copy is
missing or stale (`is_current`: the copy records the SHA-256 of the notebook it was executed
from) and checks it (`problems`): every code cell ran, none raised, none printed a Python
warning, and a notebook that shows figures shows at least one. A notebook that fails a check
fails the build and leaves no copy. CI builds the site from a clean checkout, in an
environment with the docs extra alone, so there every notebook runs and is checked.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
EXECUTED = ROOT / "docs" / "tutorials"
#: Seconds per cell; a whole notebook takes about a minute on 2 cores.
CELL_TIMEOUT = 300
_KEY = "jaxnm_docs"
# A Python warning as the warnings module prints it ("file:line: SomeWarning: message"). The
# kernel is a separate process, so pytest's or a caller's warning filters do not reach it.
_PY_WARNING = re.compile(r"\b\w*Warning: ")


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


def problems(nb) -> list[str]:
    """What is wrong with an executed notebook ``nb``: code cells that did not run, error
    outputs, a Python warning printed to stderr, no figure where the notebook calls
    ``plt.show()``; an empty list when nothing is."""
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    found = []
    skipped = [i for i, c in enumerate(code) if c.get("execution_count") is None]
    if skipped:
        found.append(f"code cells {skipped} did not run")
    outputs = [o for c in code for o in c.get("outputs", [])]
    for o in outputs:
        if o["output_type"] == "error":
            found.append(f"a cell raised {o.get('ename')}: {o.get('evalue')}")
    stderr = "".join(o.get("text", "") for o in outputs
                     if o["output_type"] == "stream" and o.get("name") == "stderr")
    warning = next((line for line in stderr.splitlines() if _PY_WARNING.search(line)), None)
    if warning is not None:
        found.append(f"it printed a warning: {warning.strip()}")
    if ("plt.show()" in "".join("".join(c["source"]) for c in code)
            and not any("image/png" in o.get("data", {}) for o in outputs)):
        found.append("it calls plt.show() but shows no figure")
    return found


def ensure_executed(log=print) -> list[Path]:
    """Execute and check (`problems`) every notebook without a current executed copy;
    returns those executed. A failing cell or check raises a one-line ``RuntimeError``
    naming the notebook, and leaves no executed copy of it."""
    done = []
    for source in notebooks():
        if is_current(source):
            continue
        log(f"executing {source.name} for the site (no current executed copy)")
        with tempfile.TemporaryDirectory() as folder:
            try:
                nb = execute(source, Path(folder))
            except Exception as e:  # nbclient's CellExecutionError carries the traceback
                raise RuntimeError(f"{source.name}: a cell failed: "
                                   f"{str(e).strip().splitlines()[-1]}") from e
            found = problems(nb)
            if found:
                raise RuntimeError(f"{source.name}: {'; '.join(found)}")
            write_executed(nb, source)
        done.append(source)
    return done
