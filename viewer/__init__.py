"""`pano-pipe view`: a browser viewer (viser) of a run folder; see docs/viewer.md."""
