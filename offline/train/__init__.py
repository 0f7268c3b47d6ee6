"""KSNN training (PyTorch, offline only), ONNX export of the skin predictor and its error report."""
