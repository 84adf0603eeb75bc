"""The retrieval: synthetic or real measurements in, a 3D cloud extinction out.

- :mod:`cloudct.retrieval.carving`: space carving of the cloud's hull, the initial medium.
- :mod:`cloudct.retrieval.loss`: the image loss and its gradient (one estimator call).
- :mod:`cloudct.retrieval.loop`: the iterations (Adam/SGD or L-BFGS-B windows), coarse to
  fine stages, path recycling, checkpoints (:class:`~cloudct.retrieval.loop.Retrieval`).
- :mod:`cloudct.retrieval.metrics`, :mod:`cloudct.retrieval.report`: epsilon / delta and the
  report with its figures; :mod:`cloudct.retrieval.cli`: ``cloudct retrieve``, ``report``,
  ``demo``.
"""
