"""Room layout from panoramas: HorizonNet-compatible ONNX inference, supplied
boundary formats, and the post-processing to a metric room (docs/layout.md)."""
