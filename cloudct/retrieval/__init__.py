"""The retrieval: synthetic or real measurements in, a 3D cloud extinction out.

- :mod:`cloudct.retrieval.cloudy_pixels`, :mod:`cloudct.retrieval.carving`,
  :mod:`cloudct.retrieval.carving_figure`: space carving of the cloud's hull, the initial
  medium, and its figure.
- :mod:`cloudct.retrieval.loss`: the image loss and its gradient (one estimator call).
- :mod:`cloudct.retrieval.config`, :mod:`cloudct.retrieval.config_file`: the run's settings
  (:class:`RetrievalConfig`) and their TOML file (``cloudct retrieve --config``).
- :mod:`cloudct.retrieval.loop`: the iterations (Adam/SGD or L-BFGS-B windows), coarse to
  fine stages, path recycling, checkpoints (:class:`~cloudct.retrieval.loop.Retrieval`).
- :mod:`cloudct.retrieval.metrics`, :mod:`cloudct.retrieval.report`: epsilon / delta and the
  report with its figures. The commands are in :mod:`cloudct.cli.retrieve` and
  :mod:`cloudct.cli.carve`.
"""
