"""Structure from motion for panoramas: pycolmap reconstruction (reconstruct), perspective rig views
(rig), and the upright, metric world frame (frame). See docs/poses.md."""
