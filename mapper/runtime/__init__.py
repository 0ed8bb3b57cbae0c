"""The learned model inside the node: ModelRuntime (model_runtime.py), the parts it composes
(loading, volume, entries, prepared, views, text, points, density, rendering) and its torch-free config.
"""
