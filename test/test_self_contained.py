"""A fresh clone passes its tests on its own: nothing under test/ or bench/ builds a path outside the repository
(only an explicit environment variable, UW_SIL_SHARED_DATA, may point elsewhere), and every test image in use
is in test/data with its provenance."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted(p for d in ("test", "bench") for p in (ROOT / d).rglob("*.py") if "generated" not in p.parts)


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_path_leaves_the_repository(path):
    text = path.read_text()
    depth = len(path.relative_to(ROOT).parts) - 1          # Path(__file__).resolve().parents[depth] is the root
    for m in re.finditer(r"parents\[(\d+)\]", text):
        assert int(m.group(1)) <= depth, f"{path.name}: {m.group(0)} is above the repository"
    for m in re.finditer(r"""["'](/work/|\.\./|~/)""", text):
        assert False, f"{path.name}: path literal {m.group(0)}... points outside the repository"
    ups = re.findall(r"\.parent((?:\.parent)*)", text)
    assert all(len(u) // len(".parent") + 1 <= depth + 1 for u in ups), f"{path.name}: .parent chain above the root"


def test_test_images_are_in_the_repository_with_provenance():
    data = ROOT / "test" / "data"
    provenance = (data / "PROVENANCE.md").read_text()
    images = sorted(p for p in data.rglob("*") if p.is_file() and p.name != "PROVENANCE.md")
    assert images and sum(p.stat().st_size for p in images) < 5_000_000      # a few MB at most
    for p in images:
        rel = str(p.relative_to(data))
        assert rel in provenance, f"{rel} has no SHA-256 line in test/data/PROVENANCE.md"
    # every image named by a test that reads test images (through datapaths) is there
    for src in (ROOT / "test").glob("test_*.py"):
        text = src.read_text()
        if "from datapaths import" not in text:
            continue
        for name in re.findall(r"""["']([\w/]+\.(?:jpg|gif|BMP|bmp|png))["']""", text):
            assert any(p.name == Path(name).name for p in images), f"{src.name} reads {name}, not in test/data"
