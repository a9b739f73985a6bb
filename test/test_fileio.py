"""Atomic outputs: whole or nothing."""
import pytest

from uw_sil._shared.fileio import atomic_path, write_text_atomic


def test_written_whole_and_failed_writes_leave_nothing(tmp_path):
    p = write_text_atomic(tmp_path / "sub" / "a.json", "{}")
    assert p.read_text() == "{}"
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "b.png") as tmp:
            assert tmp.suffix == ".png" and tmp.parent == tmp_path
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["sub"]
