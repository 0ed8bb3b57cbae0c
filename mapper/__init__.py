"""The mapper: the node core (``node``), its plugins (``node.plugins``), the learned model inside
the node (``runtime``), the network and its ops (``model``, ``model.ops``), open-vocabulary spaces
(``ov``), training and evaluation (``training``). Layout and import rules: docs/concepts/architecture.md.

Never imports ``clients``.
"""
