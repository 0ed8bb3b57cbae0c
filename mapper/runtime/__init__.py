"""The learned model inside the node: ModelRuntime (model_runtime.py) and its torch-free config.
"""
