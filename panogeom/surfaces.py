"""Labels of a room layout's surfaces: the surface ids of the sampled layout cloud
(`sampling`) and the per-pixel layout labels (`align`) use the same encoding."""

WALL, FLOOR, CEILING = 0, 1, 2
NONE = -1  # a pixel that sees no layout surface
SURFACE_NAMES = ("wall", "floor", "ceiling")  # indexed by label
