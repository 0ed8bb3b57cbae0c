"""The map: the bounded keyframe window (``window``), the global semantic point map
(``global_map``), the views of keyframes that left the window (``evicted_views``), the compiled
kernels of map queries (``query_kernels``) and their configs, side by side.

Torch-free when it runs, not only when it is imported (tests/test_architecture.py runs real
``average`` / ``average_depth`` / ``query_points`` answers in a process where importing torch fails).
"""
