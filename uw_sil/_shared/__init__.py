"""Small helpers several rooms use: input checks (:mod:`.checks`), atomic file writes (:mod:`.fileio`) and
progress display for terminals and logs (:mod:`.progress`).

Import rules: imports nothing of uw_sil; every other room may import it.
"""
from .checks import check_image, check_mask, check_values
from .fileio import atomic_path, write_text_atomic
from .progress import progress_bar

__all__ = ["atomic_path", "check_image", "check_mask", "check_values", "progress_bar", "write_text_atomic"]
