"""The mapping node: service loop, keyframe window, cost volume, model, rendering, queries.

Never imports `clients`.
"""
