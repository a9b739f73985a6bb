"""The project cites the paper it implements, and not the one it was once attributed to (issue 22).

"The paper" is Doernbach, Gomez Chavez, Mueller and Birk, *High-Fidelity Deep-Sea Perception Using
Simulation in the Loop* (IFAC 2018). README and docstrings once named Álvarez-Tuñón, Jardón and
Balaguer (Sensors 19(24), 2019) instead; these tests fail if that citation comes back anywhere in
the repository's text files, or if the README stops citing the right paper.
"""
from __future__ import annotations

import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()

#: Where the project's own text lives (relative to the repository root): folders searched recursively.
SEARCHED_DIRS = ("uw_sil", "bench", "launch", "config", "test", "scripts")
SEARCHED_FILES = ("README.md", "package.xml", "setup.py", "setup.cfg")
TEXT_SUFFIXES = {".py", ".md", ".txt", ".rst", ".yaml", ".yml", ".xml", ".cfg", ".toml", ".sh", ".html",
                 ".json", ".csv", ".ini"}
SKIPPED_DIRS = {"__pycache__", ".pytest_cache"}

#: The wrong citation, in ASCII-folded lower case (accents removed: "Álvarez-Tuñón" -> "alvarez-tunon").
WRONG = ("s19245497", "sensors 19", "alvarez-tunon", "alvarez tunon",
         "generation and processing of simulated underwater images")

AUTHORS = "Doernbach"
TITLE = "High-Fidelity Deep-Sea Perception Using Simulation in the Loop"


def _fold(text: str) -> str:
    """Lower case without accents, whitespace runs made single spaces (a citation may wrap lines)."""
    ascii_text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    return " ".join(ascii_text.lower().split())


def _text_files():
    files = [ROOT / name for name in SEARCHED_FILES if (ROOT / name).is_file()]
    for folder in SEARCHED_DIRS:
        base = ROOT / folder
        if not base.is_dir():
            continue
        for path in sorted(base.rglob("*")):
            if path.is_file() and path.suffix.lower() in TEXT_SUFFIXES \
                    and not SKIPPED_DIRS.intersection(path.relative_to(ROOT).parts):
                files.append(path)
    return [f for f in files if f.resolve() != THIS]


def _wrong_in(text: str) -> list:
    folded = _fold(text)
    return [needle for needle in WRONG if needle in folded]


def _wrong_citations(files):
    hits = []
    for path in files:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        hits += [f"{path.relative_to(ROOT)}: {needle!r}" for needle in _wrong_in(text)]
    return hits


def test_the_search_covers_the_project():
    files = {f.relative_to(ROOT).as_posix() for f in _text_files()}
    for expected in ("README.md", "uw_sil/sim/optics.py", "uw_sil/metrics/histsim.py", "uw_sil/metrics/theta.py",
                     "uw_sil/fit/backward.py", "uw_sil/enhance/sil.py", "bench/bench_fog_blur.py"):
        assert expected in files
    assert THIS.relative_to(ROOT).as_posix() not in files


def test_no_wrong_citation_in_the_repository():
    hits = _wrong_citations(_text_files())
    assert not hits, "the wrong paper is cited again (the project implements Doernbach et al. 2018):\n" + \
        "\n".join(hits)


@pytest.mark.parametrize("spelling", ["Álvarez-Tuñón", "Alvarez-Tunon", "doi:10.3390/s19245497",
                                      "Sensors\n   19(24), 5497"])
def test_the_check_finds_each_spelling(spelling):
    assert _wrong_in(f'"""References\n.. [1] O. {spelling} et al."""\n'), spelling
    assert _wrong_in(unicodedata.normalize("NFD", spelling)), spelling     # decomposed accents too
    assert not _wrong_in(f"{AUTHORS} et al., {TITLE}, IFAC 2018")


def test_readme_cites_the_paper():
    readme = _fold((ROOT / "README.md").read_text(encoding="utf-8"))
    assert _fold(AUTHORS) in readme
    assert _fold(TITLE) in readme


def test_modules_that_define_the_paper_cite_it():
    # docstrings that say what "the paper" means throughout uw_sil must name the right one
    defining = [f for f in _text_files() if f.suffix == ".py"
                and "throughout uw_sil" in f.read_text(encoding="utf-8")]
    assert defining, "no module says what 'the paper' is"
    for path in defining:
        text = _fold(path.read_text(encoding="utf-8"))
        assert _fold(AUTHORS) in text and _fold(TITLE) in text, path.relative_to(ROOT)
