"""The documentation is checked like code.

- Every Python block of README.md and docs/ runs, in order, one namespace per file. A block
  is left out only behind an HTML comment on the line before it,
  ``<!-- docs-test: skip (why) -->``, for blocks that need a GPU, files that are not in the
  repository, or a fresh process; every other marker is an error.
- Every JSON block parses; a scene file shown with ``<!-- docs-test: scene DIR -->`` loads
  (`jaxnm.config.scene_from_dict`, paths relative to DIR); a fit file uses only fit keys.
- Every name in ``jaxnm.__all__`` and ``jaxnm.fit.__all__`` is documented by the API
  reference (a ``::: module`` directive of a page in docs/api/ whose module exports it), the
  file formats page names every key and value of the scene vocabulary, and the command line
  page names every option.
- No development-process words (work-session numbers, "workplace", "VM", "lent", issue
  numbers, commit hashes) in README.md, the repository's papers, docs/ and jaxnm/.
"""

import importlib
import inspect
import json
import re
from pathlib import Path

import numpy as np
import pytest

import jaxnm

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAPERS = ["README.md", "CHANGELOG.md", "CONTRIBUTING.md", "CITATION.cff"]


def _pages() -> list[Path]:
    return [ROOT / "README.md"] + sorted(DOCS.rglob("*.md"))


_FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```[ \t]*$", re.M | re.S)
_MARKER = re.compile(r"<!--\s*docs-test:\s*(.*?)\s*-->\s*$")
_SKIP = re.compile(r"skip \((.+)\)")


def blocks(text: str) -> list[tuple[str, str, int, str | None]]:
    """The fenced blocks of a Markdown text: (language, code, line, marker), where marker is
    the ``docs-test:`` comment on the line right before the block, if any."""
    out = []
    for m in _FENCE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        mark = _MARKER.search(before)
        out.append((m.group(1).lower(), m.group(2), line, mark.group(1) if mark else None))
    return out


def test_blocks_reads_fences_and_markers():
    text = ("x\n<!-- docs-test: skip (needs a GPU) -->\n```python\na = 1\n```\n\n"
            "```json\n{}\n```\n")
    assert blocks(text) == [("python", "a = 1\n", 3, "skip (needs a GPU)"),
                            ("json", "{}\n", 7, None)]


def _python_pages():
    return [p for p in _pages() if any(b[0] in ("python", "py") for b in blocks(p.read_text()))]


@pytest.mark.parametrize("page", _python_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_python_blocks_run(page, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # a block that writes a file writes it here
    namespace = {"__name__": "__docs__"}
    ran = 0
    for lang, code, line, mark in blocks(page.read_text()):
        if lang not in ("python", "py"):
            continue
        if mark is not None:
            assert _SKIP.fullmatch(mark), f"{page.name}:{line}: unknown marker {mark!r}"
            continue
        exec(compile(code, f"{page.relative_to(ROOT)}:{line}", "exec"), namespace)  # noqa: S102
        ran += 1
    assert ran, f"{page.name}: every Python block is skipped"


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_json_blocks_parse_and_scene_files_load(page):
    from jaxnm import config

    for lang, code, line, mark in blocks(page.read_text()):
        if lang != "json":
            continue
        data = json.loads(code)
        where = f"{page.name}:{line}"
        if mark is not None:
            kind, _, folder = mark.partition(" ")
            assert kind == "scene", f"{where}: unknown marker {mark!r}"
            scene = config.scene_from_dict(data, base_dir=ROOT / folder, source=where)
            assert scene.width == data["width"]
        elif "targets" in data:
            assert set(data) <= set(config.FIT_KEYS), (where, set(data) - set(config.FIT_KEYS))
        elif "mesh" in data:
            assert set(data) <= set(config.SCENE_KEYS), (where, set(data) - set(config.SCENE_KEYS))


def test_the_readme_example_is_tested():
    """The README's Python example is among the blocks that run (not skipped)."""
    readme = [b for b in blocks((ROOT / "README.md").read_text()) if b[0] == "python"]
    assert readme and all(mark is None for *_, mark in readme)
    code = "".join(b[1] for b in readme)
    for call in ("jaxnm.render(", "jax.grad(", "fit_normal_map("):
        assert call in code


def test_the_readme_stays_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 260


# --------------------------------------------------------------------------------------
# the API reference covers the public names
# --------------------------------------------------------------------------------------

_DIRECTIVE = re.compile(r"^::: ([\w.]+)[ \t]*\n((?:[ \t]+.*\n|[ \t]*\n)*)", re.M)


def directives(pages: list[str]) -> dict[str, bool]:
    """``::: path`` directives of API pages -> whether they render the members."""
    found = {}
    for text in pages:
        for m in _DIRECTIVE.finditer(text + "\n"):
            found[m.group(1)] = not re.search(r"members:\s*(false|\[\])", m.group(2))
    return found


def _resolve(path: str):
    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for p in parts[k:]:
            obj = getattr(obj, p)
        return obj
    raise ImportError(path)


def defined_names(module) -> set[str]:
    """The public names a module defines itself (its top-level functions, classes and
    assignments, not its imports): what the API reference renders for a ``::: module``
    directive."""
    import ast

    tree = ast.parse(Path(module.__file__).read_text(encoding="utf-8"))
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    return {n for n in names if not n.startswith("_")}


def undocumented(module, pages: list[str]) -> list[str]:
    """The names of ``module.__all__`` that no directive of ``pages`` documents: neither
    named by its own directive nor defined by a module whose directive renders its
    members."""
    shown = []  # objects a page renders
    for path, members in directives(pages).items():
        obj = _resolve(path)
        shown.append(obj)
        if members and inspect.ismodule(obj) and hasattr(obj, "__file__"):
            shown += [getattr(obj, n) for n in defined_names(obj) if hasattr(obj, n)]
    return [n for n in module.__all__ if not any(getattr(module, n) is o for o in shown)]


def _api_pages() -> list[str]:
    return [p.read_text() for p in sorted((DOCS / "api").glob("*.md"))]


@pytest.mark.parametrize("module", ["jaxnm", "jaxnm.fit"])
def test_every_public_name_is_in_the_api_reference(module):
    mod = importlib.import_module(module)
    assert not undocumented(mod, _api_pages()), undocumented(mod, _api_pages())


def test_every_public_module_has_an_api_page():
    import pkgutil

    found = directives(_api_pages())
    modules = ["jaxnm"] + [m.name for m in pkgutil.walk_packages(jaxnm.__path__, "jaxnm.")
                           if not any(part.startswith("_") for part in m.name.split("."))]
    assert not [m for m in modules if m not in found], [m for m in modules if m not in found]


def test_the_api_check_can_fail():
    page = "::: jaxnm.render\n    options:\n      members: false\n\n::: jaxnm.fit.solve\n"
    missing = undocumented(jaxnm, [page])
    assert "render" in missing and "Scene" in missing  # members: false shows none
    assert "fit_normal_map" not in missing  # jaxnm.fit.solve exports it


# --------------------------------------------------------------------------------------
# the reference pages name what the code accepts
# --------------------------------------------------------------------------------------


def test_the_file_formats_page_names_every_key_and_value():
    config, frames, interpolate, shading, textures = (
        importlib.import_module(f"jaxnm.{m}")
        for m in ("config", "frames", "interpolate", "shading", "textures"))
    page = (DOCS / "getting-started" / "files.md").read_text()
    vocab = (config.SCENE_KEYS + config.FIT_KEYS + config.TANGENT_MODES + frames.FRAMES
             + interpolate.DERIVATIVE_MODES + interpolate.PRECISIONS + textures.FILTERS
             + textures.WRAPS + textures.UV_ORIGINS + textures.ENCODINGS
             + shading.SHADING_MODELS + shading.FALLOFFS)
    assert not [v for v in vocab if f"`{v}`" not in page], [v for v in vocab
                                                             if f"`{v}`" not in page]


@pytest.mark.parametrize("command", ["fit", "bake", "render"])
def test_the_command_line_page_names_every_option(command, capsys):
    from jaxnm import cli

    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    options = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", capsys.readouterr().out))
    options -= {"--help"}
    page = (DOCS / "getting-started" / "cli.md").read_text()
    assert options and not [o for o in options if f"{o}" not in page], sorted(
        o for o in options if o not in page)


# --------------------------------------------------------------------------------------
# no development-process words
# --------------------------------------------------------------------------------------

PROCESS_WORDS = [
    ("a work-session number", re.compile(r"\bsessions?\s+\d+", re.I)),
    ("workplace", re.compile(r"\bworkplaces?\b", re.I)),
    ("VM", re.compile(r"\bVMs?\b")),
    ("lent", re.compile(r"\blent\b", re.I)),
    ("an issue number", re.compile(r"\bissues?\s*#?\d+", re.I)),
    # a commit hash: 7-40 lowercase hex digits with at least one letter and one digit
    ("a commit hash", re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")),
]


def process_words(text: str) -> list[str]:
    """``"line N: what (match)"`` for each development-process word in ``text``."""
    hits = []
    for n, line in enumerate(text.splitlines(), 1):
        for what, pattern in PROCESS_WORDS:
            hits += [f"line {n}: {what} ({m.group(0)!r})" for m in pattern.finditer(line)]
    return hits


def test_the_process_word_check_can_fail():
    bad = ("Measured in session 40 on the workplace's 2-core VM, lent for issue 11; "
           "see commit 4f3446b.")
    found = process_words(bad)
    assert len(found) == 6, found
    assert not process_words("Measured on a 2-core x86-64 cloud instance with "
                             "`python -m scripts.benchmarks.bench` (jaxnm 0.2.0, 2^16 slots, "
                             "float16, 1024x1024, a session of work, an issue tracker).")


def _checked_files() -> list[Path]:
    return ([ROOT / p for p in PAPERS] + sorted(DOCS.rglob("*.md"))
            + sorted((ROOT / "jaxnm").rglob("*.py")))


@pytest.mark.parametrize("path", _checked_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_process_words(path):
    hits = process_words(path.read_text(encoding="utf-8"))
    assert not hits, f"{path.relative_to(ROOT)}: " + "; ".join(hits)


@pytest.mark.slow
def test_the_teaser_script_draws_its_picture(tmp_path):
    pytest.importorskip("matplotlib")
    from scripts.examples import teaser

    panels = teaser.make(render_size=48, map_size=16, steps=2)
    assert panels["seen"].any() and np.isfinite(panels["mean_error"])
    teaser.draw(panels, tmp_path / "teaser.png")
    assert (tmp_path / "teaser.png").stat().st_size > 1000


def test_docstrings_become_markdown():
    """The API reference's docstring clean-up (scripts/docs/griffe_markdown.py)."""
    from scripts.docs.griffe_markdown import to_markdown

    text = ("Render it.\n\n**Arguments:**\n- `a`: one.\n  More of one.\n- `b`: two.\n\n"
            "The pipeline::\n\n    x = f(y)\n\n"
            ".. math::\n    b_i = \\frac{E_i}{\\sum_m E_m}\n\nEnd.")
    md = to_markdown(text)
    assert "**Arguments:**\n\n- `a`: one.\n  More of one.\n- `b`: two." in md
    assert "The pipeline:\n\n    x = f(y)" in md
    assert ".. math::" not in md and ("<math" in md or "```tex" in md)
    assert to_markdown("- a\n- b") == "- a\n- b"  # a list that starts the text stays as it is
