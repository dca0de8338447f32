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


# ------------------------------------------------------------------ the notebook extra

# the jaxnm modules that need an extra, and the third-party imports the notebooks may use
_MODULE_EXTRAS = {"jaxnm.storage": "storage", "jaxnm.transfer": "bake"}
_DISTRIBUTIONS = {"matplotlib": "matplotlib", "numpy": "numpy", "jax": "jax",
                  "imageio": "imageio", "trimesh": "trimesh", "optimistix": "optimistix"}


def _extras():
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    return project["project"]["optional-dependencies"], project["project"]["dependencies"]


def _resolved(extra: str, extras: dict) -> tuple[set[str], set[str]]:
    """The extras ``extra`` brings (itself included) and the distribution names it adds."""
    import re

    names, dists = {extra}, set()
    for req in extras[extra]:
        m = re.fullmatch(r"jaxnm\[([\w,]+)\]", req)
        if m is None:
            dists.add(re.match(r"[A-Za-z0-9_.-]+", req).group(0).lower())
            continue
        for inner in m.group(1).split(","):
            n, d = _resolved(inner, extras)
            names |= n
            dists |= d
    return names, dists


def _not_covered(source: str, extra: str, extras: dict, base: list[str]) -> list[str]:
    """What the code ``source`` imports that ``extra`` (with the base dependencies) does not
    install."""
    import ast
    import re

    names, dists = _resolved(extra, extras)
    dists |= {re.match(r"[A-Za-z0-9_.-]+", d).group(0).lower() for d in base}
    imported = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            imported |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            imported |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    missing = []
    for module in sorted(imported):
        top = module.split(".")[0]
        need = next((e for m, e in _MODULE_EXTRAS.items()
                     if module == m or module.startswith(m + ".")), None)
        if need is not None and need not in names:
            missing.append(f"{module} (the {need} extra)")
        elif top in _DISTRIBUTIONS and _DISTRIBUTIONS[top] not in dists:
            missing.append(f"{module} ({_DISTRIBUTIONS[top]})")
    return missing


@pytest.mark.parametrize("path", docs_notebooks.notebooks(), ids=lambda p: p.name)
def test_the_notebook_extra_installs_what_each_notebook_imports(path):
    """The README runs the notebooks with ``pip install -e ".[notebook]"``: that extra alone
    must bring every package a notebook imports, through jaxnm's modules too."""
    nb = json.loads(path.read_text(encoding="utf-8"))
    source = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    source = "\n".join(line for line in source.splitlines() if not line.startswith(("%", "!")))
    extras, base = _extras()
    assert _not_covered(source, "notebook", extras, base) == []


def test_the_notebook_extra_check_can_fail():
    extras = {"notebook": ["matplotlib>=3.8"], "bake": ["embreex"]}
    source = "import matplotlib.pyplot as plt\nfrom jaxnm import transfer\nimport numpy\n"
    assert _not_covered(source, "notebook", extras, ["numpy>=2"]) == [
        "jaxnm.transfer (the bake extra)"]
    assert _not_covered(source, "notebook", {**extras, "notebook": []}, ["numpy>=2"]) == [
        "jaxnm.transfer (the bake extra)", "matplotlib.pyplot (matplotlib)"]


def test_the_site_runs_the_notebooks_with_the_notebook_extra_alone():
    """CI builds the site, which executes every notebook, in an environment with the docs
    extra alone; that proves the notebook extra enough only if the docs extra adds no other
    jaxnm extra."""
    extras, _ = _extras()
    names, _ = _resolved("docs", extras)
    assert names - {"docs"} == _resolved("notebook", extras)[0]
