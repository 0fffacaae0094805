"""ONNX depth networks for the depth stage: the model contract, the runner and the cube-face path.

    from depthnet import DepthContract, OnnxDepthModel, run_equirect, run_cubemap
    contract = DepthContract(output="disparity", normalization="imagenet", multiple_of=14)
    model = OnnxDepthModel("da.onnx", contract)
    disparity = run_equirect(model, rgb, (256, 512))

See docs/depth.md.
"""

from depthnet.cubemap import FACE_NAMES, run_cubemap, sample_face, stitch
from depthnet.runner import DepthContract, OnnxDepthModel, resize_map, run_equirect

__all__ = [
    "FACE_NAMES",
    "DepthContract",
    "OnnxDepthModel",
    "resize_map",
    "run_cubemap",
    "run_equirect",
    "sample_face",
    "stitch",
]
