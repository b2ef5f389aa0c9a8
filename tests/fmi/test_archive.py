"""Damaged and hostile FMU archives end in one line that says what is wrong and what to do."""
import os
import zipfile

from tests.fmi.broken_fmus import (add_entries, add_zip_bomb, billion_laughs, binary_name, declare_size,
                                   flip_byte_in_entry, replace_binary, rewrite_fmu, truncate)
from tests.test_cli_errors import assert_one_line_error, run_cli


def test_bad_crc_of_the_binary(tmp_path, bouncing_ball_fmu):
    path = flip_byte_in_entry(bouncing_ball_fmu, tmp_path / "crc.fmu", binary_name(bouncing_ball_fmu), compressed=False)
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() == binary_name(bouncing_ball_fmu)  # the damage zipfile itself sees
    for command in ("inspect", "simulate"):  # inspect checks the archive too, without extracting it
        assert_one_line_error(run_cli(command, path), "is corrupt", "CRC", "export the FMU again")


def test_damaged_deflate_data(tmp_path, bouncing_ball_fmu):
    path = flip_byte_in_entry(bouncing_ball_fmu, tmp_path / "deflate.fmu", binary_name(bouncing_ball_fmu), compressed=True)
    assert_one_line_error(run_cli("simulate", path), "is corrupt", "export the FMU again")


def test_damaged_model_description(tmp_path, bouncing_ball_fmu):
    path = flip_byte_in_entry(bouncing_ball_fmu, tmp_path / "xml.fmu", "modelDescription.xml", compressed=True)
    assert_one_line_error(run_cli("inspect", path), "is corrupt", "modelDescription.xml")


def test_truncated_archive(tmp_path, bouncing_ball_fmu):
    assert_one_line_error(run_cli("inspect", truncate(bouncing_ball_fmu, tmp_path / "half.fmu")), "truncated")


def test_entry_outside_the_archive(tmp_path, bouncing_ball_fmu):
    path = add_entries(bouncing_ball_fmu, tmp_path / "evil.fmu", {"resources/../../evil.txt": b"x"})
    for command in ("inspect", "simulate"):
        assert_one_line_error(run_cli(command, path), "points outside the archive")
    assert not (tmp_path.parent / "evil.txt").exists()


def test_zip_bomb_is_refused_and_the_cap_can_be_raised(tmp_path, bouncing_ball_fmu, monkeypatch):
    path = add_zip_bomb(bouncing_ball_fmu, tmp_path / "bomb.fmu", megabytes=12)
    monkeypatch.setenv("FMUBUILDER_MAX_EXTRACT_MB", "5")
    for command in ("inspect", "simulate"):
        assert_one_line_error(run_cli(command, path), "zip bomb", "FMUBUILDER_MAX_EXTRACT_MB=")
    monkeypatch.setenv("FMUBUILDER_MAX_EXTRACT_MB", "50")
    proc = run_cli("simulate", path, "--stop-time", "0.1")
    assert proc.returncode == 0, proc.stderr


def test_a_lying_size_header_is_caught_while_inflating(tmp_path, bouncing_ball_fmu, monkeypatch):
    """The declared size says 1 KB; the bytes actually inflated count against the cap."""
    path = add_zip_bomb(bouncing_ball_fmu, tmp_path / "liar.fmu", megabytes=12)
    declare_size(path, "resources/bomb.bin", 1024)
    with zipfile.ZipFile(path) as zf:
        assert zf.getinfo("resources/bomb.bin").file_size == 1024
    monkeypatch.setenv("FMUBUILDER_MAX_EXTRACT_MB", "5")
    proc = run_cli("simulate", path, "--stop-time", "0.1")
    assert_one_line_error(proc)
    assert "zip bomb" in proc.stderr or "is corrupt" in proc.stderr


def test_entity_expansion_in_the_model_description(tmp_path, bouncing_ball_fmu):
    path = rewrite_fmu(bouncing_ball_fmu, tmp_path / "laughs.fmu", xml=billion_laughs)
    assert_one_line_error(run_cli("inspect", path), "cannot read modelDescription.xml")


def test_broken_binary(tmp_path, bouncing_ball_fmu):
    path = replace_binary(bouncing_ball_fmu, tmp_path / "garbage.fmu", b"\x7fELF not really")
    proc = run_cli("simulate", path, "--stop-time", "0.1")
    assert_one_line_error(proc, "cannot load the FMU binary", "export the FMU again")
    assert os.fspath(tmp_path) not in proc.stderr.split("(")[1]  # the loader's reason, not the temp paths


# -- what fmpy reads without validating, checked ------------------------------------------------

def _alias_of_h(text: str) -> str:
    """An output alias of the state h: the same valueReference and type, no start of its own."""
    alias = ('<ScalarVariable name="height" valueReference="0" causality="local" variability="continuous">'
             '<Real unit="m"/></ScalarVariable>\n  ')
    return text.replace("</ModelVariables>", alias + "</ModelVariables>", 1)     # last: the indices stay


def test_true_aliases_are_accepted(tmp_path, bouncing_ball_fmu):
    from fmubuilder.fmi import read_model_info
    info = read_model_info(rewrite_fmu(bouncing_ball_fmu, tmp_path / "alias.fmu", xml=_alias_of_h))
    assert info.variables["height"].value_reference == info.variables["h"].value_reference == 0


def test_an_alias_with_another_start_value_is_refused(tmp_path, bouncing_ball_fmu):
    from fmubuilder.errors import FmuBuilderError
    from fmubuilder.fmi import read_model_info
    edit = lambda text: _alias_of_h(text).replace('<Real unit="m"/>', '<Real unit="m" start="2"/>', 1)  # noqa: E731
    path = rewrite_fmu(bouncing_ball_fmu, tmp_path / "alias.fmu", xml=edit)
    try:
        read_model_info(path)
    except FmuBuilderError as exc:
        assert "'h' and 'height' share the value reference 0" in str(exc)
    else:
        raise AssertionError("an alias starting elsewhere was accepted")


def test_every_bundled_example_passes_the_checks():
    from fmubuilder.build import example_fmu, list_examples
    from fmubuilder.fmi import read_model_info
    for name in list_examples():
        assert read_model_info(example_fmu(name)).guid
