"""The real KITTI excerpt in ../shared/realdata (non-commercial: read from there, never copied into the project;
tests using it skip when it is absent) and what the tests make from it."""
from pathlib import Path

from satloc.datasets.lidar_mosaic import lidar_mosaic  # noqa: F401  (the satellite stand-in the tests use)

REAL = (Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kitti_raw_2011_09_26_drive_0023_7frames"
        / "2011_09_26" / "2011_09_26_drive_0023_sync")
