"""`pano-pipe export`: a trained run's Gaussians as .ply / .splat / .spz / .sog or one self-contained
.html viewer page, or a coloured room mesh.

Formats live in their own modules (splat.py, spz.py, sog.py, html.py, mesh.py); transform.py holds
the y-down -> y-up rotation; command.py the CLI entry point. See docs/export.md. The package
imports nothing, so the CLI lists its commands without torch.
"""
