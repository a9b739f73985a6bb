"""ament_python package uw_sil: builds with colcon in a ROS 2 workspace and installs with pip."""
from glob import glob

from setuptools import find_packages, setup

package_name = "uw_sil"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench"]),
    package_data={"uw_sil.sim": ["models/*.glb", "models/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.xml")),
        ("share/" + package_name + "/models", glob("uw_sil/sim/models/*.glb") + glob("uw_sil/sim/models/*.yaml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        # OpenCV 5 moved KAZE/AKAZE to cv2.xfeatures2d; the 4.x line keeps them in cv2.
        "opencv-contrib-python-headless>=4.8,<5",
        "trimesh>=4.0",
        "pyrender2==0.2.2",
        "PyOpenGL>=3.1.5",
        "pyswarm==1.1.2",
        "cma>=3.3",
        "rosbags>=0.11.9",  # Stores.ROS2_KILTED, rosbag2 metadata version 9
        "mcap>=1.1",
        # uw_sil.bags.mcap_recover decompresses cut MCAP chunks itself (both also come with mcap).
        "zstandard>=0.20",
        "lz4>=4.0",
        "matplotlib>=3.7",
        # uw_sil.sim.scene builds the panel texture as a PIL image (already pulled in by pyrender2).
        "Pillow>=9.0",
        "PyYAML>=6.0",
        "tqdm>=4.60",
        # SURF for the feature-match table (absent from every PyPI OpenCV wheel; MIT).
        "mahotas>=1.4.19",
        # campaign.parquet of `uw-sil batch`
        "pyarrow>=14",
        # the diagnosis keeps BLAS to one thread: its own threads evaluate θ in parallel, and OpenBLAS's
        # threads on top of them made a 43200x16 SVD 12x slower on a busy 2-core machine (0.42 s vs 0.035 s)
        "threadpoolctl>=3.1",
    ],
    extras_require={
        # ROS 2 Kilted from PyPI wheels; inside a sourced ROS 2 workspace these come from /opt/ros.
        "ros": [
            "ros-kilted-rclpy[fastrtps]",
            "ros-kilted-sensor-msgs",
            "ros-kilted-geometry-msgs",
            "ros-kilted-std-srvs",
            "ros-kilted-rcl-interfaces",
            "ros-kilted-std-msgs",
            "ros-kilted-rosgraph-msgs",
            # /diagnostics of backward_fit's live diagnosis
            "ros-kilted-diagnostic-msgs",
        ],
        # `uw-sil batch --executor dask://HOST:PORT`
        "dask": ["dask[distributed]>=2024.1"],
        "test": ["pytest>=7", "pytest-xdist>=3.5", "dask[distributed]>=2024.1", "hypothesis>=6.100"],
    },
    zip_safe=True,
    maintainer="uw_sil developers",
    maintainer_email="uw-sil@example.org",
    description="Underwater camera simulation fitted to real ROV imagery (sim-to-real for subsea perception).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "uw-sil = uw_sil.cli:main",
            # ROS 2 nodes (`ros2 run uw_sil <name>` in a workspace; plain commands in a venv)
            "sim_camera = uw_sil.nodes.entry:sim_camera",
            "backward_fit = uw_sil.nodes.entry:backward_fit",
            "bag_play = uw_sil.nodes.entry:bag_play",
            "enhancer = uw_sil.nodes.entry:enhancer",
            "panel_pose = uw_sil.nodes.entry:panel_pose",
        ],
    },
)
