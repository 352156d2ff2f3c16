"""The model artifact: manifest loading and hashes, the ONNX graph specs and checks, signing."""
