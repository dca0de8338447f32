"""docs/guides/extending.md: each example's changes, applied to a copy of the package, give
what the example's code says (a shading model and a tangent frame, end to end)."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "guides" / "extending.md"
_FENCE = re.compile(r"^```(\w+)[^\n]*\n(.*?)^```[ \t]*$", re.M | re.S)


def _sections() -> dict[str, tuple[list[str], list[str]]]:
    """Each ``## `` section of the guide: its diff blocks and its Python blocks."""
    out = {}
    for part in GUIDE.read_text().split("\n## ")[1:]:
        title = part.splitlines()[0].strip()
        blocks = _FENCE.findall(part)
        out[title] = ([b for lang, b in blocks if lang == "diff"],
                      [b for lang, b in blocks if lang == "python"])
    return out


SECTIONS = _sections()


def _run(code: str, package: Path) -> subprocess.CompletedProcess:
    """``code`` in a fresh Python with the jaxnm under ``package`` first on its path."""
    env = {"PYTHONPATH": str(package), "PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-c", code], cwd=package, env=env,
                          capture_output=True, text=True, timeout=900)


def _copy(tmp_path: Path) -> Path:
    dest = tmp_path / "pkg"
    shutil.copytree(ROOT / "jaxnm", dest / "jaxnm",
                    ignore=shutil.ignore_patterns("__pycache__"))
    return dest


def test_the_guide_has_its_two_examples():
    assert list(SECTIONS) == ["Adding a shading model", "Adding a tangent frame"]
    for diffs, code in SECTIONS.values():
        assert diffs and code


@pytest.mark.slow
@pytest.mark.parametrize("section", list(SECTIONS))
def test_each_example_works_on_a_copy_with_its_changes(section, tmp_path):
    """The section's diffs apply to the package as it is (the guide names the code that is
    there), and its code then runs; on the unchanged package the same code fails, so it
    tests what the section adds."""
    diffs, code = SECTIONS[section]
    package = _copy(tmp_path)
    program = "\n".join(code)
    before = _run(program, package)
    assert before.returncode != 0, "the example's code passes without its changes"
    for diff in diffs:
        applied = subprocess.run(
            ["patch", "-p1", "--forward", "--fuzz=0", "--no-backup-if-mismatch"],
            input=diff, cwd=package, capture_output=True, text=True)
        assert applied.returncode == 0, applied.stdout + applied.stderr
    after = _run(program, package)
    assert after.returncode == 0, after.stderr[-3000:]
