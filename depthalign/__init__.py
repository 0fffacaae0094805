"""Depth maps made metric by the layout, for the align stage: a robust fit of each depth model to
the layout's depth (`scale_fit`), then back-projection, a scale-only ICP against the layout cloud
and open3d's filtering of the merged cloud (`clouds`). See docs/depth.md."""
