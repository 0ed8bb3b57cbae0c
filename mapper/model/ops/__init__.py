"""Pure tensor ops of the model: camera geometry, volume rendering, cost volume, shape checks.
"""
