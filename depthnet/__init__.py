"""ONNX depth networks for the depth stage: the model contract, the runner and the cube-face path.

    from depthnet.cubemap import run_cubemap
    from depthnet.runner import DepthContract, OnnxDepthModel, run_equirect
    contract = DepthContract(output="disparity", normalization="imagenet", multiple_of=14)
    model = OnnxDepthModel("da.onnx", contract)
    disparity = run_equirect(model, rgb, (256, 512))

See docs/depth.md. The package imports nothing, so the CLI lists its commands without OpenCV.
"""
