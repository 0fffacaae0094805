"""Geometry shared by the pipeline's stages and the simulator (not by splatting/)."""

from panogeom.equirect import *  # noqa: F401,F403
from panogeom.equirect import __all__  # noqa: F401
