"""Structure from motion for panoramas: the upright N-view solver for levelled cameras
(upright_global, on the two-view search of upright_pair), pycolmap reconstruction (reconstruct),
perspective rig views (rig), and the upright, metric world frame (frame). See docs/poses.md."""
