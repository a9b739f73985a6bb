"""Small helpers several rooms use: input checks (:mod:`.checks`), atomic file writes (:mod:`.fileio`),
progress display for terminals and logs (:mod:`.progress`), and a worker process's thread budget and
allocator settings (:mod:`.process`).

Import rules: imports nothing of uw_sil; every other room may import it.
"""
from .checks import check_image, check_mask, check_values
from .fileio import atomic_path, write_text_atomic
from .progress import progress_bar
from .process import default_threads

__all__ = ["atomic_path", "check_image", "check_mask", "check_values", "default_threads", "progress_bar", "write_text_atomic"]
