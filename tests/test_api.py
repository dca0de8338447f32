"""API conventions: options are keyword-only, the public surface imports and is documented,
and no module reaches into another's private names."""

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

import jaxnm

ROOT = Path(__file__).resolve().parents[1]

# Positional defaults that are data rather than options (like gluLookAt's `up`).
ALLOWED_POSITIONAL_DEFAULTS = {
    ("look_at", "up"),
    ("sample", "duvdx"),
    ("sample", "duvdy"),
    ("fit_normal_map", "options"),
}


def _public_functions():
    for name in jaxnm.__all__:
        obj = getattr(jaxnm, name)
        if inspect.isfunction(obj) or callable(obj) and not inspect.isclass(obj):
            yield name, obj


def _modules():
    """Every module of the package, imported."""
    yield jaxnm
    for info in pkgutil.walk_packages(jaxnm.__path__, "jaxnm."):
        yield importlib.import_module(info.name)


def test_options_are_keyword_only():
    bad = []
    for name, fn in _public_functions():
        sig = inspect.signature(fn)
        for p in sig.parameters.values():
            if (p.kind == p.POSITIONAL_OR_KEYWORD and p.default is not p.empty
                    and (name, p.name) not in ALLOWED_POSITIONAL_DEFAULTS):
                bad.append(f"{name}({p.name}=...)")
    assert not bad, f"optional arguments should be keyword-only: {bad}"


def _has_own_doc(obj) -> bool:
    doc = (obj.__doc__ or "").strip()
    if inspect.isclass(obj):
        # a class without a docstring inherits one, and @dataclass writes "Name(fields...)"
        return "__doc__" in vars(obj) and bool(doc) and not doc.startswith(obj.__name__ + "(")
    return bool(doc)


def test_every_public_name_is_documented():
    missing = []
    for mod in _modules():
        assert (mod.__doc__ or "").strip(), f"module {mod.__name__} has no docstring"
        for n in getattr(mod, "__all__", ()):
            obj = getattr(mod, n)
            if (inspect.isclass(obj) or inspect.isfunction(obj)) and not _has_own_doc(obj):
                missing.append(f"{mod.__name__}.{n}")
    assert not missing, missing


def test_the_docstring_check_can_fail():
    import dataclasses

    @dataclasses.dataclass
    class Undocumented:
        x: int

    def bare():
        pass

    assert not _has_own_doc(Undocumented) and not _has_own_doc(bare)
    assert _has_own_doc(jaxnm.Scene) and _has_own_doc(jaxnm.render)


def test_all_is_complete_and_importable():
    for mod in _modules():
        names = getattr(mod, "__all__", None)
        if names is None:
            continue
        assert len(set(names)) == len(names), mod.__name__
        for n in names:
            assert hasattr(mod, n), f"{mod.__name__}.{n}"


def _private_imports(path: Path) -> list[str]:
    """`from .x import _name` and `x._name` uses of another jaxnm module's private names."""
    tree = ast.parse(path.read_text())
    aliases = {}  # local name -> imported jaxnm module
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            is_jaxnm = node.level > 0 or (node.module or "").startswith("jaxnm")
            for a in node.names:
                if is_jaxnm and a.name.startswith("_") and a.name != "__version__":
                    bad.append(f"{path.name}:{node.lineno} imports {a.name}")
                if is_jaxnm:
                    aliases[a.asname or a.name] = True
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("jaxnm"):
                    aliases[(a.asname or a.name).split(".")[0]] = True
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__") and isinstance(node.value, ast.Name)
                and node.value.id in aliases):
            bad.append(f"{path.name}:{node.lineno} uses {node.value.id}.{node.attr}")
    return bad


def _resolve_package(path: Path, node: ast.ImportFrom) -> Path | None:
    """The directory of the jaxnm package a ``from ... import`` in ``path`` reads from (None:
    not jaxnm)."""
    if node.level == 0:
        module = node.module or ""
        return ROOT.joinpath(*module.split(".")) if module.split(".")[0] == "jaxnm" else None
    base = path.parent
    for _ in range(node.level - 1):
        base = base.parent
    return base.joinpath(*node.module.split(".")) if node.module else base


def _cross_module_private_uses(path: Path) -> list[str]:
    """Uses in ``path`` of another module's private (``_``) name: ``from .x import _name``
    and ``x._name`` with ``x`` an imported module. Importing a module whose own name starts
    with ``_`` is not one: such a module is where names shared between modules live. Other
    packages' names are not looked at."""
    tree = ast.parse(path.read_text())
    modules = set()  # local names bound to imported modules
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            package = _resolve_package(path, node)
            for a in node.names:
                is_module = package is not None and (
                    (package / a.name).is_dir() or (package / f"{a.name}.py").exists())
                if is_module:
                    modules.add(a.asname or a.name)
                elif a.name.startswith("_") and not a.name.startswith("__"):
                    bad.append(f"{path.name}:{node.lineno} imports {a.name}")
        elif isinstance(node, ast.Import):
            modules |= {(a.asname or a.name).split(".")[0] for a in node.names
                        if a.name.split(".")[0] == "jaxnm"}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__") and isinstance(node.value, ast.Name)
                and node.value.id in modules):
            bad.append(f"{path.name}:{node.lineno} uses {node.value.id}.{node.attr}")
    return bad


def test_modules_use_no_other_modules_private_names():
    """A ``_`` name is used only in its own module: what modules share is public, or lives in
    a module whose name starts with ``_`` (`jaxnm._exec`, `jaxnm.fit._processes`, ...)."""
    bad = [b for f in sorted((ROOT / "jaxnm").rglob("*.py"))
           for b in _cross_module_private_uses(f)]
    assert not bad, bad


def test_the_cross_module_private_name_check_can_fail(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "_shared").mkdir(parents=True)
    (pkg / "_shared" / "__init__.py").write_text("")
    (pkg / "_shared" / "tools.py").write_text("def helper(): pass\n")
    (pkg / "stage.py").write_text("def _secret(): pass\n")
    user = pkg / "user.py"
    user.write_text("from . import stage, _shared\nfrom ._shared import tools\n"
                    "from ._shared.tools import helper\nfrom .stage import _secret\n"
                    "import numpy as np\nstage._secret()\ntools.helper()\nnp._core\n"
                    "_shared.tools.helper()\n")
    assert _cross_module_private_uses(user) == ["user.py:4 imports _secret",
                                                "user.py:6 uses stage._secret"]


#: A backticked (dotted) name in a docstring.
_REFERENCE = re.compile(r"`+([A-Za-z_][\w.]*)")


def _public_docstrings():
    """``(name, docstring)`` of every public module, every name its ``__all__`` lists and
    their public methods and properties."""
    for mod in _modules():
        if any(part.startswith("_") for part in mod.__name__.split(".")):
            continue
        yield mod.__name__, mod.__doc__ or ""
        for n in getattr(mod, "__all__", ()):
            obj = getattr(mod, n)
            yield f"{mod.__name__}.{n}", inspect.getdoc(obj) or ""
            if inspect.isclass(obj):
                for k, v in vars(obj).items():
                    if not k.startswith("_") and (inspect.isfunction(v)
                                                  or isinstance(v, property)):
                        yield f"{mod.__name__}.{n}.{k}", inspect.getdoc(v) or ""


def _private_references(doc: str) -> list[str]:
    """The names ``doc`` refers to that start with ``_`` (not dunders), and the jaxnm paths
    through such a name."""
    def private(part: str) -> bool:
        return re.match(r"_[A-Za-z]", part) is not None

    names = [m.group(1).rstrip(".") for m in _REFERENCE.finditer(doc)]
    return [n for n in names if private(n) or (n.startswith("jaxnm.")
                                               and any(map(private, n.split("."))))]


def test_no_public_docstring_sends_users_to_a_private_name():
    """What a user reads (the public modules, classes and functions) names public things
    only: a private name may change or go without notice."""
    bad = [f"{name}: {ref}" for name, doc in _public_docstrings()
           for ref in _private_references(doc)]
    assert not bad, bad


def test_the_private_reference_check_can_fail():
    doc = ("Computed by `_helper` (see `jaxnm.render._frame`, `jaxnm._exec.pixels`); "
           "`os._exit`, `render`, ``__init__`` and ``-``/``_`` are fine.")
    assert _private_references(doc) == ["_helper", "jaxnm.render._frame", "jaxnm._exec.pixels"]


def test_scripts_use_only_the_public_api():
    """A ``_`` name is private to the jaxnm package: its modules share such names, but the
    scripts (examples, studies, benchmarks) use only what users may rely on."""
    bad = [b for f in sorted((ROOT / "scripts").rglob("*.py")) for b in _private_imports(f)]
    assert not bad, bad


def _module_level_names(path: Path) -> tuple[list[str] | None, list[str]]:
    """(``__all__`` or None, the names a module defines at its top level)."""
    tree = ast.parse(path.read_text())
    exported, defined = None, []
    for node in tree.body:
        targets = ([node.target] if isinstance(node, ast.AnnAssign)
                   else node.targets if isinstance(node, ast.Assign) else [])
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            exported = list(ast.literal_eval(node.value))
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            defined.append(node.name)
        else:
            defined += [t.id for t in targets if isinstance(t, ast.Name)]
    return exported, defined


def _unlisted_public_names(path: Path) -> list[str]:
    exported, defined = _module_level_names(path)
    return [n for n in defined if not n.startswith("_") and n not in (exported or [])]


@pytest.mark.parametrize("path", [p for p in sorted((ROOT / "jaxnm").rglob("*.py"))
                                  if p.name != "__init__.py"],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_internals_are_named_private(path):
    """Each module's ``__all__`` is what a user may rely on: every other name the module
    defines starts with ``_``, and ``__all__`` lists no ``_`` name."""
    exported, _ = _module_level_names(path)
    assert exported is not None, f"{path.name} has no __all__"
    assert not [n for n in exported if n.startswith("_")]
    assert _unlisted_public_names(path) == []


def test_the_naming_check_can_fail(tmp_path):
    f = tmp_path / "x.py"
    f.write_text('__all__ = ["render"]\nLIMIT = 3\ndef render(): pass\ndef helper(): pass\n'
                 "def _private(): pass\n")
    assert _unlisted_public_names(f) == ["LIMIT", "helper"]


def test_the_private_name_check_can_fail(tmp_path):
    f = tmp_path / "x.py"
    f.write_text("from .scene import _camera\nfrom jaxnm import fit as F\nF._loss(1)\n")
    assert len(_private_imports(f)) == 2


def test_one_version_string():
    import importlib.metadata
    import tomllib

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in meta["project"] and "version" in meta["project"]["dynamic"]
    assert meta["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "jaxnm.__version__"}
    assert re.fullmatch(r"\d+\.\d+\.\d+", jaxnm.__version__)
    assert importlib.metadata.version("jaxnm") == jaxnm.__version__


@pytest.mark.parametrize("vocab,owner", [
    ("FRAMES", "jaxnm.frames"), ("DERIVATIVE_MODES", "jaxnm.interpolate"),
    ("SHADING_MODELS", "jaxnm.shading"), ("FILTERS", "jaxnm.textures"),
    ("WRAPS", "jaxnm.textures"), ("ENCODINGS", "jaxnm.textures"), ("SOLVERS", "jaxnm.fit"),
])
def test_each_vocabulary_is_defined_once(vocab, owner):
    """One list per vocabulary, in the module of the stage that owns it."""
    defined = [m.__name__ for m in _modules()
               if re.search(rf"^{vocab}\s*=", inspect.getsource(m), re.M)]
    owner_mod = importlib.import_module(owner)
    assert defined in ([owner], [owner_mod.__name__ + ".problem"]), defined


def test_the_design_pages_module_table_matches_the_package():
    """Every module (or subpackage) in jaxnm/ appears in the module table of the design page
    (docs/guides/design.md, "The package"), and the table names nothing that does not
    exist."""
    page = (ROOT / "docs" / "guides" / "design.md").read_text()
    table = page[page.index("## The package"):]
    table = table[:table.index("\n## ")]
    listed = set(re.findall(r"^\| `(jaxnm/[\w/.]+)` \|", table, re.M))
    actual = {f"jaxnm/{p.name}" for p in (ROOT / "jaxnm").glob("*.py")
              if p.name != "__init__.py"}
    actual |= {f"jaxnm/{p.name}/" for p in (ROOT / "jaxnm").iterdir()
               if p.is_dir() and (p / "__init__.py").exists()}
    assert listed == actual, (sorted(listed - actual), sorted(actual - listed))


def _long_functions(path: Path, limit: int = 80) -> list[str]:
    """The functions of a Python file longer than ``limit`` lines, docstring included."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [f"{path}:{n.lineno} {n.name} ({n.end_lineno - n.lineno + 1} lines)"
            for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
            and n.end_lineno - n.lineno + 1 > limit]


def test_no_function_is_over_80_lines():
    """A function reads on one screen: none in ``jaxnm/`` is over 80 lines."""
    root = Path(jaxnm.__file__).parent
    assert [f for p in sorted(root.rglob("*.py")) for f in _long_functions(p)] == []


def test_the_function_length_check_can_fail(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(80))
    (tmp_path / "m.py").write_text(f"def short():\n    return 1\n\n\ndef long():\n{body}\n")
    assert _long_functions(tmp_path / "m.py") == [f"{tmp_path / 'm.py'}:5 long (81 lines)"]
