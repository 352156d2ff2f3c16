"""msdnet.models: exported models shipped with the package (one folder per model, each with its
four ONNX graphs and manifest.json, read by ``msdnet.runtime.Pipeline.from_dir``)."""
