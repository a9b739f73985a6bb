"""Small helpers several rooms use: input checks (:mod:`.checks`) and atomic file writes (:mod:`.fileio`).

Import rules: imports nothing of uw_sil; every other room may import it.
"""
from .checks import check_image, check_mask, check_values
from .fileio import atomic_path, write_text_atomic

__all__ = ["atomic_path", "check_image", "check_mask", "check_values", "write_text_atomic"]
