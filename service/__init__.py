"""lowres3d detection service: FastAPI over the ONNX Runtime :class:`pipeline.detector.Detector`.

``python -m service --help`` to run it; :func:`service.app.create_app` to embed it.
Imports no torch.
"""
