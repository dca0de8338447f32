"""The scripts' command lines (`scripts._cli`): an output they could not write is one line
naming the option, exit 2, before the study or benchmark runs."""

from __future__ import annotations

import importlib
import sys

import pytest

from scripts._cli import run_script

# script, the option that names its output, whether the output is a folder
SCRIPTS = [
    ("scripts.studies.hard_cases", "--out", True),
    ("scripts.studies.study_frames", "--out", True),
    ("scripts.studies.speed_vs_error", "--out", True),
    ("scripts.studies.study_baking", "--out", True),
    ("scripts.studies.study_representations", "--out", True),
    ("scripts.studies.study_bake", "--out", True),
    ("scripts.studies.blender_bake_cases", "--out", True),
    ("scripts.benchmarks.bench", "--out", True),
    ("scripts.examples.make_example_fit", "OUTDIR", True),
    ("scripts.examples.teaser", "--out", False),
    ("scripts.benchmarks.gpu_check", "--out", False),
    ("scripts.benchmarks.bench_distributed", "--out", False),
]


@pytest.mark.parametrize("module, flag, folder", SCRIPTS)
def test_an_output_that_cannot_be_written_stops_the_script_first(tmp_path, capsys, monkeypatch,
                                                                 module, flag, folder):
    """A folder's name that is a file (or a file's name that is a folder): it was a traceback
    after the work, for `bench` after every benchmark had run."""
    main = importlib.import_module(module).main
    (tmp_path / "file").write_text("x")
    (tmp_path / "folder").mkdir()
    bad = tmp_path / ("file" if folder else "folder")
    argv = [str(bad)] if flag == "OUTDIR" else [flag, str(bad)]
    monkeypatch.setattr(sys, "argv", [f"{module.rsplit('.', 1)[1]}.py", *argv])
    assert run_script(main) == 2
    why = "is a file, not a folder" if folder else "is a folder; name the file to write"
    name = module.rsplit(".", 1)[1]
    assert capsys.readouterr().err == f"{name}.py: error: {flag} {bad}: {why}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "folder"]
    assert not any((tmp_path / "folder").iterdir())


def test_a_script_returns_its_own_exit_code_or_zero():
    assert run_script(lambda: 3) == 3
    assert run_script(lambda: {"rows": []}) == 0  # (a study's result is not an exit code)
    with pytest.raises(RuntimeError):  # other errors keep their traceback
        run_script(lambda: (_ for _ in ()).throw(RuntimeError("bug")))
