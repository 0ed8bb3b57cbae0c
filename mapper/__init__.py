"""The mapper: the node (``node``: transport, answers, backends, workers), the map (``map``) and
its kernels (``kernels``), the learned model inside the node (``runtime``), the network and its ops
(``model``, ``model.ops``), open-vocabulary spaces (``ov``), geometry from posed RGB
(``geometry``), training and evaluation (``training``). Layout and import rules:
docs/concepts/architecture.md.

Never imports ``clients``.
"""
