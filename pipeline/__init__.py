"""lowres3d's runtime: 3D car boxes from a LiDAR scan and a camera image in ONNX Runtime (NumPy, OpenCV; no torch).

For a program of one's own (README, "In your own code"):

- :class:`pipeline.detector.Detector` loads a model directory and detects in a frame (``Detector.detect``; its
  docstring lists the exceptions a caller catches);
- :class:`pipeline.calib.Calibration` is the camera–LiDAR calibration (``Calibration.from_matrices`` for matrices
  in code, :func:`pipeline.kitti.read_calib` for a KITTI file);
- :class:`pipeline.errors.InputError` is raised for an input it cannot use, naming the field.

This package imports nothing itself: ``import pipeline`` loads no ONNX Runtime; import the modules above.
"""
