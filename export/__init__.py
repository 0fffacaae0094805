"""`pano-pipe export`: a trained run's Gaussians as .ply / .splat / .spz, or a coloured room mesh.

Formats live in their own modules (splat.py, spz.py, mesh.py); transform.py holds the
y-down -> y-up rotation; command.py the CLI entry point. See docs/export.md.
"""

from export.splat import read_splat, splat_bytes, write_splat
from export.spz import read_spz, spz_bytes, write_spz
from export.transform import Y_UP, to_y_up

__all__ = ["Y_UP", "to_y_up", "splat_bytes", "write_splat", "read_splat", "spz_bytes", "write_spz", "read_spz"]
