"""The shared output helpers: atomic writes and copies, their leftovers, file hashes."""
import hashlib

import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.files import copy_atomically, file_sha256, partial_files, write_atomically


def test_write_and_copy_replace_the_target(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    write_atomically(target, "new text\n")
    assert target.read_text() == "new text\n" and target.stat().st_mode & 0o777 == 0o644
    copy = copy_atomically(target, tmp_path / "copy.bin")
    assert copy.read_bytes() == b"new text\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy.bin", "out.txt"]


def test_a_failed_write_leaves_the_old_file_and_no_partial(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("precious")

    def explode(handle):
        handle.write(b"half")
        raise KeyboardInterrupt

    from fmubuilder.files import _replace_atomically
    with pytest.raises(KeyboardInterrupt):
        _replace_atomically(target, explode)
    assert target.read_text() == "precious" and partial_files(target) == []


def test_partial_files_finds_leftovers_of_a_killed_write(tmp_path):
    target = tmp_path / "result.csv"
    leftover = tmp_path / ".result.csv.abc123.partial"
    leftover.write_text("half")
    (tmp_path / ".other.csv.abc.partial").write_text("not ours")
    assert partial_files(target) == [leftover]


def test_missing_folder_is_a_one_line_error(tmp_path):
    with pytest.raises(FmuBuilderError, match="does not exist; create it first"):
        write_atomically(tmp_path / "no" / "x.txt", "x")


def test_file_sha256_matches_hashlib(tmp_path):
    path = tmp_path / "data.bin"
    data = bytes(range(256)) * 10000
    path.write_bytes(data)
    assert file_sha256(path) == hashlib.sha256(data).hexdigest()
