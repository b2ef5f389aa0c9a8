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


# -- nothing but what the run created is removed; only fmubuilder's folders are replaced ---------

def test_a_failed_run_removes_what_it_created_and_nothing_else(tmp_path, monkeypatch):
    from fmubuilder.files import JOURNAL_ENV, make_folder, remove_created, staging_folder
    journal = tmp_path / "journal"
    monkeypatch.setenv(JOURNAL_ENV, str(journal))
    mine, theirs, kept = tmp_path / "new.csv", tmp_path / "other.csv", tmp_path / "old.csv"
    kept.write_text("the user's")
    write_atomically(mine, "created by this run")
    write_atomically(kept, "replaced by this run (with --force)")
    write_atomically(theirs, "created by this run, then ...")
    theirs.unlink()
    theirs.write_text("... written anew by another program")
    staged = staging_folder(tmp_path / "report")
    (tmp_path / ".notes.txt.x.partial").write_text("the user's, named like a leftover")
    empty, shared = make_folder(tmp_path / "plots" / "empty"), make_folder(tmp_path / "shared")
    (shared / "theirs.txt").write_text("another program's, in a folder this run made")
    removed = remove_created(journal)
    assert sorted(removed) == sorted([mine, staged, empty, empty.parent])
    assert (shared / "theirs.txt").is_file()
    assert kept.read_text() == "replaced by this run (with --force)"
    assert theirs.read_text() == "... written anew by another program"
    assert (tmp_path / ".notes.txt.x.partial").read_text() == "the user's, named like a leftover"


def test_what_a_failed_run_keeps_for_the_user_stays(tmp_path, monkeypatch):
    """An error that points to a report of the failed run: the clean-up leaves that report."""
    from fmubuilder.files import JOURNAL_ENV, keep_for_the_user, remove_created, replace_folder, staging_folder
    journal = tmp_path / "journal"
    monkeypatch.setenv(JOURNAL_ENV, str(journal))
    staged = staging_folder(tmp_path / "report")
    (staged / "report.md").write_text("why the run failed")
    report = keep_for_the_user(replace_folder(staged, tmp_path / "report"))
    other = tmp_path / "hybrid.fmu"
    write_atomically(other, "created by this run")
    assert remove_created(journal) == [other]
    assert (report / "report.md").read_text() == "why the run failed"


def test_without_a_journal_nothing_is_recorded(tmp_path, monkeypatch):
    from fmubuilder.files import JOURNAL_ENV
    monkeypatch.delenv(JOURNAL_ENV, raising=False)
    write_atomically(tmp_path / "x.txt", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.txt"]


@pytest.mark.parametrize("kind", ["symbolic link", "FIFO", "folder"])
def test_a_non_regular_file_is_never_replaced(tmp_path, kind):
    import os
    from fmubuilder.files import refuse_existing
    target, thesis = tmp_path / "out", tmp_path / "thesis.txt"
    thesis.write_text("years of work")
    {"symbolic link": lambda: target.symlink_to(thesis), "FIFO": lambda: os.mkfifo(target),
     "folder": target.mkdir}[kind]()
    with pytest.raises(FmuBuilderError):
        refuse_existing(target, force=True)
    with pytest.raises(FmuBuilderError):
        write_atomically(target, "new")
    assert thesis.read_text() == "years of work" and os.path.lexists(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "thesis.txt"]


def test_a_copy_onto_its_source_is_refused(tmp_path):
    source = tmp_path / "m.fmu"
    source.write_bytes(b"the model")
    with pytest.raises(FmuBuilderError, match="onto itself"):
        copy_atomically(source, tmp_path / "." / "m.fmu")
    assert source.read_bytes() == b"the model"


def test_replace_folder_replaces_only_a_folder_fmubuilder_wrote(tmp_path):
    from fmubuilder.files import MANIFEST_NAME, foreign_content, replace_folder, staging_folder
    target = tmp_path / "report"

    def new_report(text):
        staging = staging_folder(target)
        (staging / "plots").mkdir()
        (staging / "plots" / "a.png").write_bytes(b"png")
        (staging / "report.md").write_text(text)
        return staging

    replace_folder(new_report("first"), target)
    assert (target / MANIFEST_NAME).is_file() and foreign_content(target) is None
    replace_folder(new_report("second"), target)            # fmubuilder's own: replaced
    assert (target / "report.md").read_text() == "second"
    (target / "notes.txt").write_text("the user's")
    staging = new_report("third")
    with pytest.raises(FmuBuilderError, match="notes.txt"):
        replace_folder(staging, target)
    (target / "notes.txt").unlink()
    (target / "report.md").write_text("edited by the user")
    with pytest.raises(FmuBuilderError, match="changed since"):
        replace_folder(staging, target)
    assert (target / "report.md").read_text() == "edited by the user"
