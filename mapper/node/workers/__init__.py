"""Background workers of the node: work done after an ack, off the ingest and query threads.

Each worker hooks into the node's context (:class:`mapper.node.context.NodeContext`) the same way:
a keyframe listener that queues work (``ctx.keyframe_listeners``, called after integration), a
thread (``ctx.workers``, started by ``node.start()``), a ``status`` key (``ctx.status_providers``),
``pending()`` (keyframes queued or being worked on) and ``process_pending()`` (do the queued work in
place, for tests and evaluation):

* :mod:`~mapper.node.workers.map_features`: the learned model's blended features into the global
  map before keyframes leave the window;
* :mod:`~mapper.node.workers.depth_points`: global-map points from the model's rendered depth for
  keyframes without depth;
* :mod:`~mapper.node.workers.triangulation`: sparse points and plane-sweep stereo from posed RGB;
* :mod:`~mapper.node.workers.ov_features`: OV features from an in-process encoder (CLIP) for
  keyframes without ``ov``.
"""
