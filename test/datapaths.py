"""Where the shared test data lives: ``$UW_SIL_SHARED_DATA``, else ``shared/data`` beside the repository
(the layout of this project's checkouts and of CI)."""
import os
from pathlib import Path

SHARED_DATA = Path(os.environ.get("UW_SIL_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")
if not SHARED_DATA.is_dir():
    raise FileNotFoundError(f"shared test data not found at {SHARED_DATA}: set UW_SIL_SHARED_DATA")
