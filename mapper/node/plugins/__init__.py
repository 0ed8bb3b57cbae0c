"""Optional stages that plug into a running node: the learned model's handlers (learned),
rendered-depth map points (depth_points), in-process OV features (ov_features); ``serve`` installs
the ones a node's config asks for, as ``govnesf serve`` does.
"""
