"""The room the layout describes, as geometry: the per-view floor plans merged into one
(`union`), its walls, floor and ceiling sampled into points (`box_sampling`), and the depth it
implies along each ray of a panorama (`layout_depth`). The union and sampling stages are glue over
this package; the align stage and the diagnosis use its depth."""
