"""uw_sil: an underwater camera simulation fitted to what a real ROV camera sees.

Core library (no ROS imports): camera model and poses, procedural intervention panel,
headless renderer, the underwater image model, image-quality criteria, optimizers,
enhancement, diagnosis and ROS 2 bag I/O. ROS 2 adapters live in :mod:`uw_sil.nodes`.
"""

__version__ = "0.1.0"
