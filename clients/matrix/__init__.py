"""The scenario matrix (``govnesf matrix``, docs/how-to/scenario-matrix.md): many small held-out
scenarios, each streamed through a real node over loopback and scored against the simulator's ground truth.

- :mod:`clients.matrix.scenarios`: the axes, the sample of their combinations, the seed split;
- :mod:`clients.matrix.driver`: one scenario through a node (the frames, the answers, the scores);
- :mod:`clients.matrix.report`: per-scenario JSON lines, the Markdown summary, the heat map;
- :mod:`clients.matrix.cli`: the command.

The node is reached only through the protocol (:class:`clients.harness.NodeProcess`).
"""
