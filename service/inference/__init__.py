"""Pose inference: the ONNX model files, the MC-dropout estimator, acceptance rules."""
