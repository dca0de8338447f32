"""A griffe extension for the API reference: the docstrings' reStructuredText leftovers as
Markdown, so that mkdocstrings renders them as the reader expects.

- ``.. math::`` blocks become MathML (`latex2mathml`; no script needed in the browser), or a
  TeX code block where the converter does not know a command;
- a paragraph line ending in ``::`` (an RST literal block follows) ends in ``:``;
- a list that follows a paragraph line directly gets the blank line Markdown needs to see
  it as a list;
- a module or class attribute documented by ``#:`` comments right above it (the Sphinx
  convention, which jaxnm's constants use) gets those comments as its docstring.

Loaded by ``mkdocs.yml`` (the Python handler's ``extensions``); `to_markdown` is the
transformation, tested in ``tests/test_docs.py``.
"""

from __future__ import annotations

import re

try:  # the docs extra; `to_markdown` alone needs nothing
    import griffe
except ImportError:  # pragma: no cover
    griffe = None

_MATH = re.compile(r"^(\s*)\.\. math::\s*(.*)$")
_ITEM = re.compile(r"^\s*(?:[-*+]|\d+[.)])\s+\S")
_FENCE = re.compile(r"^\s*(```|~~~)")


def _mathml(tex: str) -> str | None:
    try:
        from latex2mathml.converter import convert

        return convert(tex, display="block")
    except Exception:  # noqa: BLE001 - an unknown command: show the TeX itself
        return None


def _math_block(tex: str) -> list[str]:
    html = _mathml(tex)
    if html is None:
        return ["", "```tex", tex, "```", ""]
    return ["", f'<div class="jaxnm-math">{html}</div>', ""]


def to_markdown(text: str) -> str:
    """``text`` (a docstring) with `.. math::` blocks, ``::`` endings and unseparated
    lists made Markdown (see the module docstring)."""
    lines = text.splitlines()
    out: list[str] = []
    i, fenced, in_list = 0, False, False
    while i < len(lines):
        line = lines[i]
        if _FENCE.match(line):
            fenced = not fenced
            out.append(line)
            i += 1
            continue
        if fenced:
            out.append(line)
            i += 1
            continue
        m = _MATH.match(line)
        if m:
            indent = len(m.group(1))
            tex = [m.group(2)] if m.group(2).strip() else []
            i += 1
            while i < len(lines) and (not lines[i].strip()
                                      or len(lines[i]) - len(lines[i].lstrip()) > indent):
                tex.append(lines[i].strip())
                i += 1
            while tex and not tex[-1]:
                tex.pop()
            out.extend(_math_block(" ".join(t for t in tex if t)))
            in_list = False
            continue
        stripped = line.strip()
        if stripped.endswith("::") and not stripped.startswith(".."):
            line = line[: line.rindex("::")] + ":"
        if _ITEM.match(line):
            if out and out[-1].strip() and not in_list:
                out.append("")
            in_list = True
        elif not stripped:
            in_list = False
        out.append(line)
        i += 1
    return "\n".join(out)


def comment_docstring(lines: list[str], lineno: int) -> str | None:
    """The ``#:`` comment lines right above line ``lineno`` (1-based) of ``lines``, as
    text, or None."""
    doc = []
    k = lineno - 2
    while k >= 0 and lines[k].lstrip().startswith("#:"):
        doc.append(lines[k].lstrip()[2:].strip())
        k -= 1
    return "\n".join(reversed(doc)) if doc else None


if griffe is not None:
    class DocstringMarkdown(griffe.Extension):
        """Apply `to_markdown` to every docstring griffe loads; give attributes their
        ``#:`` comments as docstrings."""

        def on_instance(self, *, obj, **kwargs) -> None:
            if obj.docstring is None and obj.is_attribute and obj.lineno:
                try:
                    lines = obj.lines_collection[obj.filepath]
                except (KeyError, TypeError):
                    lines = None
                text = comment_docstring(lines, obj.lineno) if lines else None
                if text:
                    obj.docstring = griffe.Docstring(text, lineno=obj.lineno, parent=obj)
            if obj.docstring is not None:
                obj.docstring.value = to_markdown(obj.docstring.value)
