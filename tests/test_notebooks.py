"""The notebooks in notebooks/ run from top to bottom, as committed, without errors.

Each notebook is executed with nbclient in a fresh ipykernel that runs on this
interpreter (``sys.executable``): the test writes its own kernel spec into a
temporary folder, so neither a user's ``python3`` kernel spec nor the ``python``
on PATH can swap in another environment. The kernel's working directory is a
temporary folder, so a notebook can neither rely on the checkout's files by relative path
nor leave files in it.
"""

import json
import re
import sys
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
CELL_TIMEOUT = 300  # seconds per cell; the whole notebook takes about a minute on 2 cores

# A Python warning as the warnings module prints it ("file:line: SomeWarning: message").
# The kernel is a separate process, so pytest's `filterwarnings = error` does not reach it:
# a warning there (a FitWarning, a JAX or matplotlib deprecation) would only be printed.
_PY_WARNING = re.compile(r"\b\w*Warning: ")


def _notebooks():
    return sorted(NOTEBOOKS.glob("*.ipynb"))


@pytest.mark.parametrize("path", _notebooks(), ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    nb = json.loads(path.read_text(encoding="utf-8"))
    dirty = [i for i, c in enumerate(nb["cells"]) if c["cell_type"] == "code"
             and (c.get("outputs") or c.get("execution_count") is not None)]
    assert not dirty, f"{path.name}: clear the outputs of cells {dirty} before committing"


def _kernel_manager(tmp_path):
    """An AsyncKernelManager whose only kernel spec starts ipykernel on sys.executable."""
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import AsyncKernelManager

    kernels = tmp_path / "kernels"
    spec = kernels / "jaxnm-test"
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "jaxnm test kernel", "language": "python"}))
    ksm = KernelSpecManager(kernel_dirs=[str(kernels)], ensure_native_kernel=False)
    return AsyncKernelManager(kernel_name="jaxnm-test", kernel_spec_manager=ksm)


@pytest.mark.slow
@pytest.mark.parametrize("path", _notebooks(), ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    pytest.importorskip("ipykernel", reason="notebook tests need ipykernel "
                        "(pip install -e '.[test]')")
    nbformat = pytest.importorskip("nbformat", reason="notebook tests need nbformat "
                                   "(pip install -e '.[test]')")
    nbclient = pytest.importorskip("nbclient", reason="notebook tests need nbclient "
                                   "(pip install -e '.[test]')")
    nb = nbformat.read(path, as_version=4)
    workdir = tmp_path / "work"
    workdir.mkdir()
    client = nbclient.NotebookClient(
        nb, km=_kernel_manager(tmp_path), timeout=CELL_TIMEOUT, allow_errors=False,
        resources={"metadata": {"path": str(workdir)}})
    # cleanup_kc: a client given its own kernel manager (km=) leaves the kernel running and
    # its sockets open by default; shut both down here, also when a cell fails (which raises
    # CellExecutionError with the cell's traceback)
    client.execute(cleanup_kc=True)

    code = [c for c in nb.cells if c.cell_type == "code"]
    assert all(c.execution_count is not None for c in code), "not every code cell ran"
    outputs = [o for c in code for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    stderr = "".join(o.text for o in outputs
                     if o.output_type == "stream" and o.name == "stderr")
    assert not _PY_WARNING.search(stderr), f"{path.name} printed a warning:\n{stderr}"
    if "plt.show()" in "".join(c.source for c in code):
        images = [o for o in outputs if "image/png" in o.get("data", {})]
        assert images, f"{path.name}: no inline figure was produced"
