"""Compiled CPU kernels (numba + numpy, no torch) that the map's queries and the model's point
answers share: the multi-view averaging and its primitives (``average_kernel``) and the numpy
driver of the averaging (``average``)."""
