"""Running the stages on recordings: what the ``aeromag`` commands and the post-flight flow
share, so that ``flows/`` only wires (parse, one call here, print).

- :mod:`pipeline.run.fields`: which fields a run works on (segmentation, the configured
  models a flight can fit, compensated fields already recorded, the map's field, the quality
  states);
- :mod:`pipeline.run.steps`: the post-flight stages, one function each, and
  :class:`~pipeline.run.steps.FlightResults`;
- :mod:`pipeline.run.postflight`: the stages in order (:func:`postflight_steps`, with a
  ``call`` hook for Prefect tasks) and :func:`run_plain`;
- :mod:`pipeline.run.outputs`: the post-flight write step and the figures and channels the
  commands share;
- :mod:`pipeline.run.commands`, :mod:`pipeline.run.navigate`: the single-stage commands;
- :mod:`pipeline.run.archive`: an archive's job folders, plan and index.

Nothing here imports Prefect.
"""
