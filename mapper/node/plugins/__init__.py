"""Optional stages that plug into a running node: the learned model's handlers (learned),
rendered-depth map points (depth_points), in-process OV features (ov_features).
"""
