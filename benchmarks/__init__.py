"""cloudct's benchmarks, grouped by area: ``forward``, ``gradients``, ``retrieval``,
``gpu`` and ``scale``, with the scenes (:mod:`benchmarks.scenes`) and the result writing
(:mod:`benchmarks.common`) they share. Run one from the repository's root as
``python -m benchmarks NAME [OPTIONS]`` (``python -m benchmarks`` lists them); each writes
its result as JSON (and Markdown where it makes a table) under ``benchmarks/results/``
with the machine, versions, commit, date, command and settings. ``benchmarks/README.md``
says which measures what; ``docs/benchmarks.md`` holds the current figures."""
