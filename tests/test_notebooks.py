"""The notebooks in notebooks/ run from top to bottom, as committed, without errors.

Each notebook is executed with nbclient in a fresh ipykernel that runs on this
interpreter (``sys.executable``): `scripts.docs.notebooks.kernel_manager` writes its own
kernel spec into a temporary folder, so neither a user's ``python3`` kernel spec nor the
``python`` on PATH can swap in another environment. The kernel's working directory is a
temporary folder, so a notebook can neither rely on the checkout's files by relative path
nor leave files in it.

A notebook that runs leaves its executed copy in ``docs/tutorials/`` (ignored by git): the
documentation site shows those copies, so the notebooks run once in CI, here.
"""

import json
import re

import pytest

from scripts.docs import notebooks as docs_notebooks

# A Python warning as the warnings module prints it ("file:line: SomeWarning: message").
# The kernel is a separate process, so pytest's `filterwarnings = error` does not reach it:
# a warning there (a FitWarning, a JAX or matplotlib deprecation) would only be printed.
_PY_WARNING = re.compile(r"\b\w*Warning: ")


@pytest.mark.parametrize("path", docs_notebooks.notebooks(), ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    nb = json.loads(path.read_text(encoding="utf-8"))
    dirty = [i for i, c in enumerate(nb["cells"]) if c["cell_type"] == "code"
             and (c.get("outputs") or c.get("execution_count") is not None)]
    assert not dirty, f"{path.name}: clear the outputs of cells {dirty} before committing"


@pytest.mark.slow
@pytest.mark.parametrize("path", docs_notebooks.notebooks(), ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    pytest.importorskip("ipykernel", reason="notebook tests need ipykernel "
                        "(pip install -e '.[test]')")
    pytest.importorskip("nbformat", reason="notebook tests need nbformat "
                        "(pip install -e '.[test]')")
    pytest.importorskip("nbclient", reason="notebook tests need nbclient "
                        "(pip install -e '.[test]')")
    nb = docs_notebooks.execute(path, tmp_path)

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
    docs_notebooks.write_executed(nb, path)
    assert docs_notebooks.is_current(path)
