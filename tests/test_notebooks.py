"""The notebooks in notebooks/ are committed without outputs, and the checks that the site's
build runs on each executed notebook (`scripts.docs.notebooks.problems`) catch what they
claim to.

The notebooks themselves run where the site is built: ``mkdocs build`` executes each one
whose executed copy is missing or stale, in a fresh ipykernel on the build's interpreter,
and fails on a cell that raises, a Python warning or a missing figure
(`scripts.docs.notebooks.ensure_executed`). CI builds the site from a clean checkout in an
environment with the docs extra alone, so every notebook runs there with exactly that extra.
"""

import json

import pytest

from scripts.docs import notebooks as docs_notebooks


@pytest.mark.parametrize("path", docs_notebooks.notebooks(), ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    nb = json.loads(path.read_text(encoding="utf-8"))
    dirty = [i for i, c in enumerate(nb["cells"]) if c["cell_type"] == "code"
             and (c.get("outputs") or c.get("execution_count") is not None)]
    assert not dirty, f"{path.name}: clear the outputs of cells {dirty} before committing"


def _cell(source, *outputs, ran=True):
    return {"cell_type": "code", "source": source, "execution_count": 1 if ran else None,
            "outputs": list(outputs)}


def _stream(name, text):
    return {"output_type": "stream", "name": name, "text": text}


_FIGURE = {"output_type": "display_data", "data": {"image/png": "iVBORw0KGgo="}}


def test_the_builds_checks_pass_a_clean_notebook_and_name_each_problem():
    clean = {"cells": [{"cell_type": "markdown", "source": "# A"},
                       _cell("print(1)", _stream("stdout", "1\n")),
                       _cell("plt.show()", _FIGURE)]}
    assert docs_notebooks.problems(clean) == []
    warned = _stream("stderr", "/x/jaxnm/fit/solve.py:12: FitWarning: 3 texels unseen\n")
    error = {"output_type": "error", "ename": "ValueError", "evalue": "bad", "traceback": []}
    bad = {"cells": [_cell("f()", warned), _cell("g()", error), _cell("h()", ran=False),
                     _cell("plt.show()")]}
    found = docs_notebooks.problems(bad)
    assert found == ["code cells [2] did not run", "a cell raised ValueError: bad",
                     "it printed a warning: /x/jaxnm/fit/solve.py:12: FitWarning: 3 texels "
                     "unseen", "it calls plt.show() but shows no figure"]
    # stderr without a warning (a progress bar) is no problem
    quiet = {"cells": [_cell("fit()", _stream("stderr", "step 3/10 loss 0.1\n"))]}
    assert docs_notebooks.problems(quiet) == []
