"""fmubuilder.build: CMake builds, the example cache, and the add_fmu() CMake helper."""

import os
import pathlib
import shutil
import subprocess
import sys
import textwrap
import zipfile

import pytest
from fmpy.validation import validate_fmu

from fmubuilder import build
from fmubuilder.errors import FmuBuilderError

REPO = pathlib.Path(build.__file__).resolve().parent.parent


def make_example_tree(root: pathlib.Path, broken_example: bool = False) -> pathlib.Path:
    """A small copy of the repository's example tree: the CMake helper and the bouncing ball."""
    shutil.copytree(REPO / "cmake", root / "cmake")
    shutil.copytree(REPO / "examples" / "common", root / "examples" / "common")
    shutil.copytree(REPO / "examples" / "bouncing_ball", root / "examples" / "bouncing_ball")
    lines = [
        "cmake_minimum_required(VERSION 3.16)",
        "project(copy LANGUAGES C)",
        "include(cmake/fmu.cmake)",
        "add_fmu(TARGET bouncing_ball MODEL_DIR examples/bouncing_ball)",
    ]
    if broken_example:
        broken = root / "examples" / "broken"
        shutil.copytree(root / "examples" / "bouncing_ball", broken)
        model_c = broken / "model.c"
        model_c.write_text(model_c.read_text() + "\nint this_does_not_compile(void) { return undefined_name; }\n")
        lines.append("add_fmu(TARGET broken MODEL_DIR examples/broken)")
    (root / "CMakeLists.txt").write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture
def example_tree(tmp_path, monkeypatch):
    tree = make_example_tree(tmp_path / "tree")
    monkeypatch.setattr(build, "repo_root", lambda: tree)
    monkeypatch.setenv("FMUBUILDER_CACHE", str(tmp_path / "cache"))
    return tree


def test_example_cache_is_reused_and_rebuilt_after_an_edit(example_tree):
    first = build.example_fmu("bouncing_ball")
    built_at = first.stat().st_mtime_ns
    assert build.example_fmu("bouncing_ball") == first
    assert first.stat().st_mtime_ns == built_at  # not rebuilt

    model_c = example_tree / "examples" / "bouncing_ball" / "model.c"
    model_c.write_text(model_c.read_text() + "\n/* edited */\n")
    second = build.example_fmu("bouncing_ball")
    assert second != first and second.is_file()
    assert validate_fmu(str(second)) == []


def test_concurrent_builds_agree_on_one_cached_fmu(tmp_path):
    tree = make_example_tree(tmp_path / "tree")
    script = textwrap.dedent(
        f"""
        import pathlib
        from fmubuilder import build
        build.repo_root = lambda: pathlib.Path({str(tree)!r})
        print(build.example_fmu("bouncing_ball"))
        """
    )
    env = dict(os.environ, FMUBUILDER_CACHE=str(tmp_path / "cache"))
    processes = [
        subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outputs = [process.communicate(timeout=300) for process in processes]
    assert [process.returncode for process in processes] == [0, 0], outputs
    paths = {stdout.strip() for stdout, _ in outputs}
    assert len(paths) == 1
    assert zipfile.is_zipfile(paths.pop())
    leftovers = [p.name for p in (tmp_path / "cache" / "examples").iterdir() if not p.name.endswith(".lock")]
    assert len(leftovers) == 1  # no scratch folders left behind


def test_a_broken_example_does_not_block_the_others(tmp_path, monkeypatch):
    tree = make_example_tree(tmp_path / "tree", broken_example=True)
    monkeypatch.setattr(build, "repo_root", lambda: tree)
    monkeypatch.setenv("FMUBUILDER_CACHE", str(tmp_path / "cache"))
    assert build.list_examples() == ["bouncing_ball", "broken"]
    assert build.example_fmu("bouncing_ball").is_file()
    with pytest.raises(FmuBuilderError, match="(?s)example FMU 'broken' failed to build.*undefined_name"):
        build.example_fmu("broken")


def test_examples_compile_without_warnings(tmp_path):
    tree = make_example_tree(tmp_path / "tree")
    result = build.build_cmake_project(tree, tmp_path / "build")
    assert "warning" not in result.output.lower()
    assert [fmu.name for fmu in result.fmus()] == ["bouncing_ball.fmu"]


def test_add_fmu_packs_generic_sources_and_resources(tmp_path):
    """The helper also serves FMUs that bring their own sources (no shared glue defaults)."""
    project = tmp_path / "project"
    model = project / "model"
    shutil.copytree(REPO / "examples" / "bouncing_ball", model)
    for name in ("fmi2_glue.c", "model.h"):
        shutil.copy(REPO / "examples" / "common" / name, model / name)
    (project / "data.csv").write_text("time,value\n0,1\n")
    (project / "CMakeLists.txt").write_text(
        textwrap.dedent(
            f"""
            cmake_minimum_required(VERSION 3.16)
            project(generic LANGUAGES C)
            include({(REPO / "cmake" / "fmu.cmake").as_posix()})
            add_fmu(TARGET packed
                    MODEL_DESCRIPTION model/modelDescription.xml
                    SOURCES model/model.c model/fmi2_glue.c
                    HEADERS model/config.h model/model.h
                    INCLUDE_DIRS model
                    FMU_NAME custom_name.fmu
                    RESOURCES data.csv)
            """
        )
    )
    result = build.build_cmake_project(project, tmp_path / "build", target="packed")
    assert [fmu.name for fmu in result.fmus()] == ["custom_name.fmu"]
    with zipfile.ZipFile(result.fmus()[0]) as archive:
        names = set(archive.namelist())
    assert {"modelDescription.xml", "binaries/linux64/bouncing_ball.so", "sources/model.c",
            "sources/fmi2_glue.c", "resources/data.csv"} <= names
    assert validate_fmu(str(result.fmus()[0])) == []


def test_add_fmu_rejects_a_mismatching_model_identifier(tmp_path):
    project = tmp_path / "project"
    shutil.copytree(REPO / "examples" / "bouncing_ball", project / "model")
    (project / "CMakeLists.txt").write_text(
        f"cmake_minimum_required(VERSION 3.16)\nproject(p LANGUAGES C)\n"
        f"include({(REPO / 'cmake' / 'fmu.cmake').as_posix()})\n"
        "add_fmu(TARGET x MODEL_DIR model MODEL_IDENTIFIER other_name)\n"
    )
    with pytest.raises(FmuBuilderError, match="(?s)configuring.*differs from 'bouncing_ball'"):
        build.build_cmake_project(project, tmp_path / "build")


def test_compile_error_shows_the_compiler_output(tmp_path):
    project = tmp_path / "project"
    project.mkdir()
    (project / "broken.c").write_text("int broken(void) { return not_declared_anywhere; }\n")
    (project / "CMakeLists.txt").write_text(
        "cmake_minimum_required(VERSION 3.16)\nproject(p LANGUAGES C)\nadd_library(broken SHARED broken.c)\n"
    )
    with pytest.raises(FmuBuilderError, match="(?s)building .* failed.*not_declared_anywhere"):
        build.build_cmake_project(project, tmp_path / "build")


def test_missing_project_is_a_user_error(tmp_path):
    with pytest.raises(FmuBuilderError, match="no CMakeLists.txt"):
        build.build_cmake_project(tmp_path, tmp_path / "build")


def test_missing_tools_are_user_errors(tmp_path, monkeypatch):
    (tmp_path / "CMakeLists.txt").write_text("project(p C)\n")
    real_which = shutil.which

    monkeypatch.setattr(build.shutil, "which", lambda name, path=None: None if name == "cmake" else real_which(name))
    monkeypatch.setitem(sys.modules, "cmake", None)  # nor the cmake Python package
    with pytest.raises(FmuBuilderError, match="cmake not found"):
        build.build_cmake_project(tmp_path, tmp_path / "build")

    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setattr(build.shutil, "which", lambda name, path=None: real_which(name) if name == "cmake" else None)
    with pytest.raises(FmuBuilderError, match="no C compiler found"):
        build.build_cmake_project(tmp_path, tmp_path / "build")
