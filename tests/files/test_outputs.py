"""Output paths checked before any work (the CLI's cases are in tests/commands)."""

from __future__ import annotations

import pytest

from invglare.errors import ConfigError
from invglare.files.outputs import check_disk, output_file, output_folder


def test_a_good_path_is_accepted_and_nothing_is_created(tmp_path):
    target = tmp_path / "new" / "deeper" / "psf.EXR"
    assert output_file(target, "--out", (".exr",)) == target
    assert output_folder(tmp_path / "reports" / "eye", "--out-dir", replaced=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no folder made, no probe left


@pytest.mark.parametrize(
    ("name", "match"),
    [
        ("x.txt", r"--out '.*x\.txt' has extension '\.txt'; .*: \.exr or \.png$"),
        ("x", r"has no extension; .*\.exr or \.png"),
        ("folder", r"is a folder; give a file name ending in \.exr or \.png"),
        ("file/x.exr", r"'.*file' is not a folder \(it is a file\)"),
    ],
)
def test_bad_file_paths_are_one_line(tmp_path, name, match):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match=match):
        output_file(tmp_path / name, "--out", (".exr", ".png"))


def test_a_file_given_as_a_folder_is_refused(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(ConfigError, match="is not a folder"):
        output_folder(tmp_path / "file", "--out-dir")


def test_more_than_the_disk_holds_is_refused(tmp_path):
    check_disk(1.0, tmp_path / "frames", "one byte")
    with pytest.raises(Exception, match=r"needs about .* of disk; the limit is the .* free"):
        check_disk(1e18, tmp_path / "frames", "a million frames (--frames)")
