"""The learned crater detector's weights (ONNX) and how each was trained (JSON)."""
