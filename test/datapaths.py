"""Where the test images live.

``TEST_DATA`` is ``test/data`` in this repository (see ``test/data/PROVENANCE.md``): the images every
test needs, so a fresh clone passes its tests with nothing beside it. Nothing under ``test/`` or
``bench/`` reads outside the repository unless an environment variable asks for it:

``UW_SIL_SHARED_DATA``
    A directory laid out like ``test/data`` holding more images (the project's shared data set,
    e.g. ``/work/shared/data``). Only the tests of :func:`external_file` use it; they are skipped,
    with a reason naming the variable, when it is not set.
"""
import os
from pathlib import Path

import pytest

TEST_DATA = Path(__file__).resolve().parent / "data"
SHARED_DATA = TEST_DATA  # the old name: the same layout as the shared data set, restricted to what the tests need
ENV_EXTERNAL = "UW_SIL_SHARED_DATA"


def external_file(relative: str) -> Path:
    """A file of the data set named by ``$UW_SIL_SHARED_DATA``; skips the calling test when the variable
    is unset, fails (FileNotFoundError) when it is set but the file is not there."""
    root = os.environ.get(ENV_EXTERNAL)
    if not root:
        pytest.skip(f"needs {relative} from outside the repository: set {ENV_EXTERNAL} to the shared data directory")
    path = Path(root) / relative
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found ({ENV_EXTERNAL}={root})")
    return path
