"""The node's answers, one module per request type, over the shared :class:`mapper.node.context.NodeContext`:

* :mod:`~mapper.node.answers.status`: ``status``;
* :mod:`~mapper.node.answers.persistence`: ``save``, ``load``, the autosave;
* :mod:`~mapper.node.answers.query_points`: ``query_points`` (answer cache, background refresh);
* :mod:`~mapper.node.answers.segment`: ``segment_points`` by method, through a backend
  (:mod:`mapper.node.backends`), with the global map's answer beyond the window applied once;
* :mod:`~mapper.node.answers.render`: ``render`` through a backend, with the global map's labels
  where the window has none.

The transport (:mod:`mapper.node.service`) only decodes, dispatches and replies.
"""
